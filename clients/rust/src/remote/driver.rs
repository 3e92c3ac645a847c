//! A stream's own connection, on a single-threaded runtime that the thread calling
//! `step` drives itself.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tokio::runtime::Runtime;
use tonic::transport::Channel as TonicChannel;

use super::targets::{client, Targets};
use crate::error::Error;

/// A stream's own connection, on a single-threaded runtime that the thread calling
/// `step` drives itself: the request is written and the answer read on that thread, with
/// no hand-off to a worker thread and back (two thread wake-ups per round trip on the
/// shared runtime: measured, about half of a loopback round trip on the loaded 2-core
/// machine). Between steps a keeper thread drives the runtime for 2 ms whenever no step
/// has for 200 ms, so that the connection answers the server's keepalive pings (and
/// sends its own) while the caller is busy elsewhere: training, evaluating, saving.
pub(crate) struct Driver {
    pub(crate) rt: Arc<Runtime>,
    /// Per address of the channel, this stream's channel to it (made at first use).
    channels: Vec<Option<ShapingClient<TonicChannel>>>,
    /// When a step last drove the runtime (ms since `epoch`).
    last_step: Arc<AtomicU64>,
    epoch: Instant,
    /// Dropped with the driver: ends the keeper thread.
    _stop: std::sync::mpsc::Sender<()>,
}

/// How often the keeper looks whether the connection needs driving.
const KEEPER_TICK: Duration = Duration::from_millis(200);

impl Driver {
    pub(crate) fn new() -> Result<Driver, Error> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| Error::Runtime(format!("tamrm: cannot start a stream's runtime: {e}")))?;
        let rt = Arc::new(rt);
        let (stop, stopped) = std::sync::mpsc::channel::<()>();
        let last_step = Arc::new(AtomicU64::new(0));
        let epoch = Instant::now();
        let (keeper_rt, keeper_last) = (Arc::downgrade(&rt), last_step.clone());
        std::thread::Builder::new()
            .name("tamrm-keepalive".into())
            .spawn(move || loop {
                match stopped.recv_timeout(KEEPER_TICK) {
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                    _ => return,
                }
                let now = epoch.elapsed().as_millis() as u64;
                let idle = now.saturating_sub(keeper_last.load(Ordering::Relaxed));
                if idle < KEEPER_TICK.as_millis() as u64 {
                    continue; // a step drove the connection meanwhile
                }
                let Some(rt) = keeper_rt.upgrade() else {
                    return;
                };
                // Long enough for the connection task to read a ping and write its ack.
                // (The sleep is made inside: it needs the runtime's timer.)
                rt.block_on(async { tokio::time::sleep(Duration::from_millis(2)).await });
            })
            .map_err(|e| {
                Error::Runtime(format!(
                    "tamrm: cannot start a stream's keepalive thread: {e}"
                ))
            })?;
        Ok(Driver {
            rt,
            channels: Vec::new(),
            last_step,
            epoch,
            _stop: stop,
        })
    }

    /// This stream's client for address `i` of `targets` (its own connection).
    pub(crate) fn client(&mut self, targets: &Targets, i: usize) -> ShapingClient<TonicChannel> {
        let i = i % targets.len();
        if self.channels.len() < targets.len() {
            self.channels.resize(targets.len(), None);
        }
        let rt = &self.rt;
        self.channels[i]
            .get_or_insert_with(|| client(targets.get(i).channel_on(rt)))
            .clone()
    }

    /// Notes that a step is driving the runtime now.
    pub(crate) fn touch(&self) {
        self.last_step
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }
}
