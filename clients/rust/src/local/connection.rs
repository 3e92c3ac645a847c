//! Where and how a local session's Follow stream connects: open one on an address, or
//! on the first that answers, with backoff (SPEC §9, §13).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::proto::{self, follow_request, follow_response};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataMap;
use tonic::{Status, Streaming};

use crate::remote::failure::{connect_error, resumable};
use crate::remote::targets::Targets;
use crate::remote::{FIRST_PAUSE, MAX_PAUSE};
use crate::rpc::request;

/// Where and how the driver connects.
pub(crate) struct Connection {
    pub targets: Arc<Targets>,
    pub metadata: MetadataMap,
    pub tls: bool,
    pub resume_timeout: Option<Duration>,
    pub task_id: String,
    pub num_envs: u32,
    pub client_id: String,
}

/// An open Follow stream: its sender and what it receives.
pub(crate) struct Stream {
    pub(crate) tx: mpsc::Sender<proto::FollowRequest>,
    pub(crate) inbound: Streaming<proto::FollowResponse>,
}

/// One of the first messages of a Follow stream (the stream must not end before them).
async fn first_messages(
    inbound: &mut Streaming<proto::FollowResponse>,
    target: &str,
    tls: bool,
) -> Result<follow_response::Kind, Status> {
    match inbound.message().await {
        Ok(Some(proto::FollowResponse { kind: Some(kind) })) => Ok(kind),
        Ok(_) => Err(Status::unavailable(
            "the server ended the Follow stream before sending the pool",
        )),
        Err(s) => Err(connect_error(target, tls, s)),
    }
}

impl Connection {
    /// Opens a Follow stream on address `at`: the opened task and the pool snapshot.
    pub(crate) async fn open_at(
        &self,
        at: usize,
    ) -> Result<(Stream, proto::Task, proto::Pool), Status> {
        let target = self.targets.get(at);
        let name = target.endpoint.uri().to_string();
        let (tx, rx) = mpsc::channel(16);
        let open = proto::FollowRequest {
            kind: Some(follow_request::Kind::Open(proto::FollowOpen {
                task_id: self.task_id.clone(),
                num_envs: self.num_envs,
                client_id: self.client_id.clone(),
            })),
        };
        tx.send(open)
            .await
            .map_err(|_| Status::internal("the stream's sender closed"))?;
        let mut client = target.client.clone();
        let req = request(ReceiverStream::new(rx), &self.metadata, None);
        let mut inbound = client
            .follow(req)
            .await
            .map_err(|s| connect_error(&name, self.tls, s))?
            .into_inner();
        let task = match first_messages(&mut inbound, &name, self.tls).await? {
            follow_response::Kind::Opened(task) => task,
            _ => {
                return Err(Status::internal(
                    "expected 'opened' first on a Follow stream",
                ))
            }
        };
        let pool = match first_messages(&mut inbound, &name, self.tls).await? {
            follow_response::Kind::Snapshot(pool) => pool,
            _ => {
                return Err(Status::internal(
                    "expected the pool's snapshot after 'opened'",
                ))
            }
        };
        Ok((Stream { tx, inbound }, task, pool))
    }

    /// Opens a stream on the current address or, failing that, on the next ones that
    /// answer, retrying with backoff for up to `resume_timeout` (once without one).
    pub(crate) async fn open(&self) -> Result<(Stream, proto::Task, proto::Pool), Status> {
        let deadline = self.resume_timeout.map(|t| Instant::now() + t);
        let mut pause = FIRST_PAUSE;
        let mut at = self.targets.current();
        loop {
            let mut failure = None;
            for i in std::iter::once(at).chain(self.targets.after(at).take(self.targets.len() - 1))
            {
                match self.open_at(i).await {
                    Ok(opened) => {
                        self.targets.set_current(i);
                        return Ok(opened);
                    }
                    Err(s) if resumable(&s) => failure = Some(s),
                    Err(s) => return Err(s),
                }
            }
            let failure = failure.unwrap_or_else(|| Status::unavailable("no server"));
            match deadline {
                Some(d) if Instant::now() + pause < d => {}
                _ => {
                    return Err(Status::unavailable(format!(
                        "no server answered the Follow stream of task {:?} ({}): {}",
                        self.task_id,
                        self.targets.names(),
                        failure.message()
                    )))
                }
            }
            tokio::time::sleep(pause).await;
            pause = (pause * 2).min(MAX_PAUSE);
            at = self.targets.current();
        }
    }
}
