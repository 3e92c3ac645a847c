//! The driver of a local session's Follow stream: one task per store that sends the
//! queued messages, applies the pool's snapshot and updates, hands each ack to the commit
//! waiting for it, keeps a quiet stream open, and re-opens a broken one.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use tamrm::core::Pool;
use tamrm::proto::{self, follow_response};
use tokio::sync::{mpsc, oneshot};
use tonic::Status;

use super::connection::{Connection, Stream};
use super::shared::Shared;
use super::wire::{ends_request, pool_from, updated};
use crate::remote::failure::resumable;

/// How long a follow stream may stay without a message from the learner before the
/// driver sends an empty one (servers close streams idle for `stream_idle_timeout_secs`,
/// 600 s by default).
const KEEPALIVE: Duration = Duration::from_secs(20);

/// What a commit (or a steps report) waits for: the ack and the followed pool then.
pub(crate) type Reply = oneshot::Sender<Result<(proto::EndsAck, Arc<Pool>), Status>>;
/// The receiving end of a [`Reply`].
pub(crate) type Answer = oneshot::Receiver<Result<(proto::EndsAck, Arc<Pool>), Status>>;

/// One message for the server.
pub(crate) struct Outgoing {
    pub(crate) msg: proto::EpisodeEnds,
    /// `None` for a message nobody waits for (a steps report, a keepalive).
    pub(crate) reply: Option<Reply>,
}

/// What ended a connection of the driver.
enum Broke {
    /// The store was dropped and every message answered: done.
    Done,
    /// The stream broke: re-open and re-send.
    Resume(Status),
    /// The server refused the stream or a message for good.
    Fail(Status),
}

/// Runs one connection until it breaks: sends `queued` messages, keeps `pending` (sent,
/// not acknowledged) in order, applies the pool's snapshots and updates.
async fn serve(
    shared: &Shared,
    stream: &mut Stream,
    pending: &mut VecDeque<Outgoing>,
    queued: &mut mpsc::UnboundedReceiver<Outgoing>,
) -> Broke {
    let mut closing = false;
    let mut last_sent = tokio::time::Instant::now();
    loop {
        if closing && pending.is_empty() {
            return Broke::Done;
        }
        let keepalive = tokio::time::sleep_until(last_sent + KEEPALIVE);
        tokio::select! {
            out = queued.recv(), if !closing => match out {
                Some(out) => {
                    last_sent = tokio::time::Instant::now();
                    let sent = stream.tx.send(ends_request(out.msg.clone())).await;
                    pending.push_back(out);
                    if sent.is_err() {
                        return Broke::Resume(Status::unavailable("the follow stream closed"));
                    }
                }
                None => closing = true,
            },
            msg = stream.inbound.message() => {
                let kind = match msg {
                    Ok(Some(proto::FollowResponse { kind: Some(kind) })) => kind,
                    Ok(_) => return Broke::Resume(Status::unavailable("the server ended the follow stream")),
                    Err(s) if resumable(&s) => return Broke::Resume(s),
                    Err(s) => return Broke::Fail(s),
                };
                let applied = match kind {
                    follow_response::Kind::Snapshot(p) => pool_from(&shared.config, p),
                    follow_response::Kind::Update(u) => {
                        let base = shared.pool.lock().clone();
                        updated(&shared.config, &base, u)
                    }
                    follow_response::Kind::Ack(ack) => {
                        let Some(out) = pending.pop_front() else {
                            return Broke::Resume(Status::internal("an ack nobody waits for"));
                        };
                        if let Some(reply) = out.reply {
                            let _ = reply.send(Ok((ack, shared.pool.lock().clone())));
                            shared.answered.notify_waiters();
                        }
                        continue;
                    }
                    follow_response::Kind::Opened(_) => {
                        Err(Status::internal("a second 'opened' on a Follow stream"))
                    }
                };
                match applied {
                    Ok(pool) => shared.set_pool(pool),
                    // A copy that no longer agrees: a new stream brings a snapshot.
                    Err(s) => return Broke::Resume(s),
                }
            }
            _ = keepalive, if !closing => {
                last_sent = tokio::time::Instant::now();
                let out = Outgoing { msg: proto::EpisodeEnds::default(), reply: None };
                let sent = stream.tx.send(ends_request(out.msg.clone())).await;
                pending.push_back(out);
                if sent.is_err() {
                    return Broke::Resume(Status::unavailable("the follow stream closed"));
                }
            }
        }
    }
}

/// The driver: serves connections until the store is dropped or stopped, re-opening
/// broken ones.
pub(crate) async fn drive(
    conn: Arc<Connection>,
    shared: Arc<Shared>,
    first: Stream,
    mut queued: mpsc::UnboundedReceiver<Outgoing>,
) {
    let mut pending = VecDeque::new();
    let mut stream = Some(first);
    loop {
        let mut current = match stream.take() {
            Some(s) => s,
            None => match conn.open().await {
                Ok((s, _, snapshot)) => {
                    match pool_from(&shared.config, snapshot) {
                        Ok(pool) => shared.set_pool(pool),
                        Err(status) => return fail_all(&shared, &mut pending, &mut queued, status),
                    }
                    let mut resent = true;
                    for out in &pending {
                        resent &= s.tx.send(ends_request(out.msg.clone())).await.is_ok();
                    }
                    if !resent {
                        continue;
                    }
                    s
                }
                Err(status) => {
                    // Nobody answered within resume_timeout: fail what waits; a later
                    // commit tries again.
                    fail_waiting(&shared, &mut pending, &mut queued, status);
                    if queued.is_closed() && pending.is_empty() {
                        return;
                    }
                    match queued.recv().await {
                        Some(out) => {
                            pending.push_back(out);
                            continue;
                        }
                        None => return,
                    }
                }
            },
        };
        match serve(&shared, &mut current, &mut pending, &mut queued).await {
            Broke::Done => return,
            Broke::Resume(status) => {
                tracing::debug!(error = %status, "follow stream broke; re-opening it");
            }
            Broke::Fail(status) => return fail_all(&shared, &mut pending, &mut queued, status),
        }
    }
}

/// Answers every waiting message with `status` (the messages are dropped).
fn fail_waiting(
    shared: &Shared,
    pending: &mut VecDeque<Outgoing>,
    queued: &mut mpsc::UnboundedReceiver<Outgoing>,
    status: Status,
) {
    while let Ok(out) = queued.try_recv() {
        pending.push_back(out);
    }
    for out in pending.drain(..) {
        if let Some(reply) = out.reply {
            let _ = reply.send(Err(status.clone()));
        }
    }
    shared.answered.notify_waiters();
}

/// Ends the driver: every message now and later fails with `status`.
fn fail_all(
    shared: &Shared,
    pending: &mut VecDeque<Outgoing>,
    queued: &mut mpsc::UnboundedReceiver<Outgoing>,
    status: Status,
) {
    tracing::debug!(error = %status, "follow stream refused");
    *shared.ended.lock() = Some(status.clone());
    fail_waiting(shared, pending, queued, status.clone());
    queued.close();
    fail_waiting(shared, pending, queued, status);
}
