//! The addresses of a channel: each a lazily connecting tonic channel, and the one in use.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use tamrm::proto::shaping_client::ShapingClient;
use tokio::runtime::Runtime;
use tonic::transport::{Channel as TonicChannel, Endpoint};

use crate::error::Error;
use crate::options::ChannelOptions;

/// Largest message sent (requests) and received (answers).
const MAX_SEND: usize = 64 * 1024 * 1024;
const MAX_RECEIVE: usize = 256 * 1024 * 1024;

/// A `Shaping` client on `channel`, with the message size limits.
pub(crate) fn client(channel: TonicChannel) -> ShapingClient<TonicChannel> {
    ShapingClient::new(channel)
        .max_decoding_message_size(MAX_RECEIVE)
        .max_encoding_message_size(MAX_SEND)
}

/// One server address of a channel, connected lazily.
pub(crate) struct Target {
    /// The address as given (for messages).
    name: String,
    pub(crate) endpoint: Endpoint,
    /// For `unix:PATH`: the socket (the endpoint's URI is a placeholder then).
    unix: Option<PathBuf>,
    pub(crate) channel: TonicChannel,
    /// A client on the channel shared by the unary calls (its connection runs on the
    /// client's runtime).
    pub(crate) client: ShapingClient<TonicChannel>,
}

impl Target {
    /// A lazily connecting channel to `target` with `options`, on `rt`.
    pub(crate) fn connect_lazy(
        rt: &Runtime,
        target: &str,
        options: &ChannelOptions,
    ) -> Result<Target, Error> {
        let (authority, unix) = split_target(target)?;
        let endpoint = options.endpoint(target, &authority)?;
        let channel = lazy_channel(rt, &endpoint, unix.as_deref());
        Ok(Target {
            name: target.to_string(),
            endpoint,
            unix,
            client: client(channel.clone()),
            channel,
        })
    }

    /// A new lazily connecting channel to this address, whose connection runs on `rt`.
    pub(crate) fn channel_on(&self, rt: &Runtime) -> TonicChannel {
        lazy_channel(rt, &self.endpoint, self.unix.as_deref())
    }

    /// The address for messages (the endpoint's URI).
    pub(crate) fn uri(&self) -> String {
        self.endpoint.uri().to_string()
    }
}

/// The addresses of a channel and the one in use: calls and streams go to the current
/// address and move on to the next when it cannot be reached (SPEC §9, §10: any replica
/// serves any task).
pub(crate) struct Targets {
    list: Vec<Target>,
    current: AtomicUsize,
}

impl Targets {
    /// The addresses, the first one current.
    pub(crate) fn new(list: Vec<Target>) -> Targets {
        Targets {
            list,
            current: AtomicUsize::new(0),
        }
    }

    /// The address in use.
    pub(crate) fn current(&self) -> usize {
        self.current.load(Ordering::Relaxed) % self.list.len()
    }

    /// Makes address `i` the one to use first.
    pub(crate) fn set_current(&self, i: usize) {
        self.current.store(i % self.list.len(), Ordering::Relaxed);
    }

    /// How many addresses.
    pub(crate) fn len(&self) -> usize {
        self.list.len()
    }

    pub(crate) fn get(&self, i: usize) -> &Target {
        &self.list[i % self.list.len()]
    }

    /// The order to try the addresses in after address `failed` failed: every other one,
    /// then `failed` itself last.
    pub(crate) fn after(&self, failed: usize) -> impl Iterator<Item = usize> {
        let n = self.list.len();
        (1..=n).map(move |k| (failed + k) % n)
    }

    /// All addresses, for messages.
    pub(crate) fn names(&self) -> String {
        let names: Vec<&str> = self.list.iter().map(|t| t.name.as_str()).collect();
        names.join(", ")
    }
}

/// The HTTP authority of `target` and, for `unix:PATH` (or `unix:///PATH`), the socket
/// path. gRPC's `dns:`, `ipv4:` and `ipv6:` schemes name a `host:port`.
fn split_target(target: &str) -> Result<(String, Option<PathBuf>), Error> {
    if let Some(path) = target.strip_prefix("unix:") {
        let path = path.strip_prefix("//").unwrap_or(path);
        return Ok(("localhost".to_string(), Some(path.into())));
    }
    for scheme in ["dns:", "ipv4:", "ipv6:"] {
        if let Some(rest) = target.strip_prefix(scheme) {
            let rest = rest.trim_start_matches('/');
            return Ok((rest.to_string(), None));
        }
    }
    if let Some((scheme, _)) = target
        .split_once(':')
        .filter(|(s, _)| s.starts_with("unix-abstract") || *s == "vsock")
    {
        return Err(Error::Invalid(format!(
            "target {target:?}: the {scheme}: scheme is not supported by tamrm.Client; use host:port or unix:PATH"
        )));
    }
    Ok((target.to_string(), None))
}

/// A channel to `endpoint` (or the Unix socket `unix`) that connects at its first call;
/// its connection is a task of `rt`.
fn lazy_channel(rt: &Runtime, endpoint: &Endpoint, unix: Option<&Path>) -> TonicChannel {
    // The lazy channels spawn on the current runtime.
    let _enter = rt.enter();
    match unix {
        None => endpoint.connect_lazy(),
        Some(path) => {
            let path = path.to_path_buf();
            endpoint.connect_with_connector_lazy(tower::service_fn(
                move |_: tonic::transport::Uri| {
                    let path = path.clone();
                    async move {
                        let stream = tokio::net::UnixStream::connect(path).await?;
                        Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
                    }
                },
            ))
        }
    }
}
