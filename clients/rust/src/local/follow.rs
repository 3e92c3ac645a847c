//! Local sessions (SPEC §13): the embedded engine's session layer over a [`FollowStore`],
//! a store that follows one task of a server through a `Follow` stream.
//!
//! The learner's steps are shaped in-process, against the followed copy of the pool, by
//! the same `StreamSession` as `tamrm.Engine`'s; only its episode ends cross the network.
//! The store is the seam: a commit sends the ends (with the steps shaped since the last
//! message) and returns the pool the server made of them, exactly as a store shared by
//! several servers does (`RedisStore`), so a learner alone gets the values a `Shape`
//! stream returns, bit for bit; the changes others make arrive as updates, which the
//! registry publishes (`Registry::watch_changes`) so that the next step sees them.
//!
//! One driver task per store owns the stream: it sends the queued messages, applies the
//! snapshot and updates to the followed pool, hands each ack to the commit waiting for
//! it, keeps a quiet stream open, and when the stream breaks it re-opens one (with
//! failover over the channel's addresses and backoff, for up to `resume_timeout_secs`),
//! takes the fresh snapshot, and re-sends every message not acknowledged: the server
//! commits no end twice for the session's client id (SPEC §9). Closing the session ends
//! the stream (as a remote session's `Shape` stream ends); re-opening it (`restart`)
//! follows the task again from a fresh snapshot, with a new driver.

use std::sync::Arc;
use std::time::Duration;

use parking_lot::Mutex;
use tamrm::core::{Pool, TaskConfig};
use tamrm::proto;
use tamrm::service::convert::config_input;
use tamrm::store::{Committed, Counters, PoolChanged, PoolOp, Store, StoreError, StoredTask};
use tokio::sync::{broadcast, mpsc, oneshot};
use tonic::{Code, Status};

use super::connection::Connection;
use super::driver::{drive, Answer, Outgoing};
use super::plans::{Plan, Unsettled};
use super::shared::Shared;
use super::wire::{end_proto, pool_from};

/// A store that follows one task of a server (SPEC §13).
pub(crate) struct FollowStore {
    shared: Arc<Shared>,
    conn: Arc<Connection>,
    /// The driver's queue; `None` while the session is closed ([`FollowStore::stop`]):
    /// the driver then answers what it was sent and ends the stream.
    outgoing: Mutex<Option<mpsc::UnboundedSender<Outgoing>>>,
    /// Steps reported to the server so far (the local task's count at the last message).
    reported: Mutex<u64>,
    /// The ends committed without waiting: the session's steps check their acks, a
    /// commit that could undo one of them waits for them, and so does every call of the
    /// session's client.
    unsettled: Mutex<Unsettled>,
    /// The opened task as the server answered it.
    opened: proto::Task,
    description: String,
}
impl FollowStore {
    /// Opens the Follow stream (on `rt`, the module's runtime) and starts its driver.
    pub(crate) fn open(
        rt: &tokio::runtime::Runtime,
        conn: Connection,
    ) -> Result<FollowStore, Status> {
        let (stream, opened, snapshot) = rt.block_on(conn.open())?;
        let input = config_input(opened.config.as_ref());
        let config = TaskConfig::resolve(&input).map_err(|e| {
            Status::internal(format!(
                "the server sent a task config this client rejects: {e}"
            ))
        })?;
        let pool = pool_from(&config, snapshot)?;
        let (changes, _) = broadcast::channel(64);
        let conn = Arc::new(conn);
        let shared = Arc::new(Shared {
            key: conn.task_id.clone(),
            config,
            pool: Mutex::new(Arc::new(pool)),
            changes,
            failure: Mutex::new(None),
            ended: Mutex::new(None),
            answered: tokio::sync::Notify::new(),
        });
        let (outgoing, queued) = mpsc::unbounded_channel();
        let description = format!(
            "following task {:?} on {}",
            conn.task_id,
            conn.targets.names()
        );
        rt.spawn(drive(conn.clone(), shared.clone(), stream, queued));
        Ok(FollowStore {
            shared,
            conn,
            outgoing: Mutex::new(Some(outgoing)),
            reported: Mutex::new(0),
            unsettled: Mutex::new(Unsettled::default()),
            opened,
            description,
        })
    }

    /// The task as the server answered `open`.
    pub(crate) fn opened(&self) -> &proto::Task {
        &self.opened
    }

    /// Ends the Follow stream (the session closed): the driver answers the messages it
    /// was sent, then ends the stream, so the server no longer counts it open.
    pub(crate) fn stop(&self) {
        self.outgoing.lock().take();
    }

    /// Follows the task again after [`FollowStore::stop`] (the session re-opens): a new
    /// stream and its driver. Answers the pool of its snapshot, for the registry to
    /// publish before the session shapes; `None` if the stream was not stopped.
    pub(crate) fn restart(&self, rt: &tokio::runtime::Runtime) -> Result<Option<Pool>, Status> {
        // (The session's lock serializes restarts; the queue's is not held while the
        // stream opens.)
        if self.outgoing.lock().is_some() {
            return Ok(None);
        }
        let (stream, _, snapshot) = rt.block_on(self.conn.open())?;
        let pool = pool_from(&self.shared.config, snapshot)?;
        *self.shared.ended.lock() = None;
        *self.shared.failure.lock() = None;
        let (sender, queued) = mpsc::unbounded_channel();
        rt.spawn(drive(
            self.conn.clone(),
            self.shared.clone(),
            stream,
            queued,
        ));
        *self.outgoing.lock() = Some(sender);
        self.shared.set_pool(pool.clone());
        Ok(Some(pool))
    }

    /// The status the server failed the last message with, if any (taken).
    pub(crate) fn take_failure(&self) -> Option<Status> {
        self.shared.failure.lock().take()
    }

    /// The message reporting the steps shaped since the last one, with `ends`.
    fn message(&self, ends: Vec<proto::EpisodeEnd>, counters: Counters) -> proto::EpisodeEnds {
        let mut reported = self.reported.lock();
        let steps = counters.steps_shaped.saturating_sub(*reported);
        *reported = (*reported).max(counters.steps_shaped);
        proto::EpisodeEnds { ends, steps }
    }

    /// Sends `msg` and waits for its ack.
    async fn send(
        &self,
        msg: proto::EpisodeEnds,
    ) -> Result<(proto::EndsAck, Arc<Pool>), StoreError> {
        let answer = self.submit(msg)?;
        self.answered(answer).await
    }

    /// Queues `msg` for the server; the receiver gets its ack.
    fn submit(&self, msg: proto::EpisodeEnds) -> Result<Answer, StoreError> {
        let (reply, answer) = oneshot::channel();
        let gone = || StoreError::Unavailable {
            what: self.description.clone(),
            message: "the follow stream has ended".into(),
        };
        let ended = || match self.shared.ended.lock().clone() {
            Some(status) => self.failed(status),
            None => gone(),
        };
        let outgoing = self.outgoing.lock().clone();
        outgoing
            .ok_or_else(gone)?
            .send(Outgoing {
                msg,
                reply: Some(reply),
            })
            .map_err(|_| ended())?;
        Ok(answer)
    }

    /// The ack of a submitted message, or its failure.
    async fn answered(&self, answer: Answer) -> Result<(proto::EndsAck, Arc<Pool>), StoreError> {
        match answer.await {
            Ok(Ok(answer)) => Ok(answer),
            Ok(Err(status)) => Err(self.failed(status)),
            Err(_) => Err(match self.shared.ended.lock().clone() {
                Some(status) => self.failed(status),
                None => StoreError::Unavailable {
                    what: self.description.clone(),
                    message: "the follow stream has ended".into(),
                },
            }),
        }
    }

    /// Takes the answers that came for the ends in flight (in order: the acks do): an
    /// ack that differs from its plan marks the copy diverged, a failure is kept for the
    /// session's next step (and diverges the copy too: its change was not made).
    fn reap(&self, u: &mut Unsettled) {
        use tokio::sync::oneshot::error::TryRecvError;
        while let Some(front) = u.in_flight.front_mut() {
            let failure = match front.answer.try_recv() {
                Err(TryRecvError::Empty) => return,
                Ok(Ok((ack, _))) => {
                    u.diverged |= ack.changed != front.changed || ack.pool_version != front.version;
                    None
                }
                Ok(Err(status)) => Some(status),
                Err(TryRecvError::Closed) => {
                    Some(self.shared.ended.lock().clone().unwrap_or_else(|| {
                        Status::unavailable(format!(
                            "{}: the follow stream has ended",
                            self.description
                        ))
                    }))
                }
            };
            u.in_flight.pop_front();
            if let Some(status) = failure {
                u.diverged = true;
                u.failed.get_or_insert(status);
            }
        }
    }

    /// Before a step: the status of an end the server refused since the last step, or the
    /// server's pool when the copy diverged from it and nothing is in flight any more
    /// (the session publishes it; its version is at least the copy's, since a plan never
    /// counts more than one change the server has not answered); `None` when the copy
    /// holds the server's pool as planned. Never waits.
    pub(crate) fn poll(&self) -> Result<Option<Arc<Pool>>, Status> {
        let mut u = self.unsettled.lock();
        if u.in_flight.is_empty() && !u.diverged && u.failed.is_none() {
            return Ok(None);
        }
        self.reap(&mut u);
        if let Some(status) = u.failed.take() {
            return Err(status);
        }
        if u.diverged && u.in_flight.is_empty() {
            u.diverged = false;
            return Ok(Some(self.shared.pool.lock().clone()));
        }
        Ok(None)
    }

    /// Waits until every end committed without waiting is acknowledged (or failed): a
    /// call of the session's client then sees them at the server ("read your writes").
    pub(crate) async fn wait_acks(&self) {
        loop {
            let answered = self.shared.answered.notified();
            tokio::pin!(answered);
            answered.as_mut().enable();
            {
                let mut u = self.unsettled.lock();
                self.reap(&mut u);
                if u.in_flight.is_empty() {
                    return;
                }
            }
            // (A driver that ended dropped its replies: the tick notices.)
            let _ = tokio::time::timeout(Duration::from_millis(50), answered).await;
        }
    }

    /// A failure as the store reports it; the status itself is kept for the session.
    fn failed(&self, status: Status) -> StoreError {
        let e = match status.code() {
            Code::NotFound => StoreError::Gone {
                task: self.shared.key.clone(),
            },
            Code::Unavailable => StoreError::Unavailable {
                what: self.description.clone(),
                message: status.message().to_string(),
            },
            _ => StoreError::Io {
                path: self.description.clone().into(),
                message: status.message().to_string(),
            },
        };
        *self.shared.failure.lock() = Some(status);
        e
    }

    fn refused(&self, what: &str) -> StoreError {
        StoreError::Io {
            path: self.description.clone().into(),
            message: format!("{what} is not done through a local session: call the server"),
        }
    }

    fn stored(&self) -> StoredTask {
        StoredTask {
            id: self.shared.key.clone(),
            config: self.shared.config,
            pool: (**self.shared.pool.lock()).clone(),
            counters: Counters::default(),
        }
    }
}

#[async_trait::async_trait]
impl Store for FollowStore {
    fn describe(&self) -> String {
        self.description.clone()
    }

    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        Ok(vec![self.stored()])
    }

    async fn create_task(&self, _: &str, _: &TaskConfig) -> Result<Option<TaskConfig>, StoreError> {
        Err(self.refused("creating a task"))
    }

    async fn delete_task(&self, _: &str) -> Result<(), StoreError> {
        Err(self.refused("deleting a task"))
    }

    /// Sends the ends and the steps shaped since the last message.
    ///
    /// The ends are sent at once. When [`Unsettled::may_plan`] allows (at most one
    /// planned change unanswered, only inserts into a pool with room, or changes that
    /// outlast as many changes of others as are unanswered), it answers their plan
    /// without waiting: the learner shapes on against it while the ack travels, and the
    /// server's version after these ends is never below the plan's. On the same pool the
    /// server decides the same, so a learner alone shapes as a `Shape` stream, bit for
    /// bit. An ack that differs from its plan marks the copy diverged; the session then
    /// takes the server's pool once nothing is in flight ([`FollowStore::poll`]).
    /// Otherwise ends planned while others are in flight wait for those acks (already on
    /// their way), not for their own: if they match their plans, the pool these were
    /// planned against is the server's, and the rule is asked again with nothing in
    /// flight. Anything else (changes that may be refused, a diverged copy) waits for the
    /// pool the server made of these ends, with every change made before, by anyone,
    /// and the registry publishes that.
    async fn commit(
        &self,
        _: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError> {
        let plan = Plan::new(base, &ops);
        let ends = ops
            .into_iter()
            .map(end_proto)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|s| self.failed(s))?;
        let msg = self.message(ends, counters);
        let answer = self.submit(msg)?;
        let certify = {
            let mut u = self.unsettled.lock();
            self.reap(&mut u);
            if u.may_plan(&plan) {
                return Ok(u.plan(answer, plan));
            }
            !u.diverged && !u.in_flight.is_empty()
        };
        if certify {
            // Others in flight: their acks, on their way, certify the pool these ends
            // were planned against (or refute it).
            self.wait_acks().await;
            let mut u = self.unsettled.lock();
            self.reap(&mut u);
            if u.may_plan(&plan) {
                return Ok(u.plan(answer, plan));
            }
        }
        let (ack, pool) = self.answered(answer).await?;
        // The acks come in order: every end sent before is answered too, and `pool` is the
        // server's with all of them, which replaces whatever this copy planned.
        {
            let mut u = self.unsettled.lock();
            self.reap(&mut u);
            u.diverged = false;
        }
        Ok(Committed {
            pool,
            // A re-sent end (the stream broke before its ack) is the learner's own
            // change, already in the pool: nothing to resume at the learner.
            changed: ack.changed,
            version: ack.pool_version,
            resent: 0,
        })
    }

    /// Reports the steps shaped since the last message and waits for the ack.
    async fn save_counters(
        &self,
        _: &str,
        _: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError> {
        self.send(self.message(Vec::new(), counters))
            .await
            .map(drop)
    }

    /// The followed pool, or `None` while it is behind an unanswered end's plan (the
    /// previous end's update coming after the next end was planned, a re-opened stream's
    /// snapshot without the re-sent end): no news, nor a server that lost changes. The
    /// acks settle the plan ([`FollowStore::poll`]).
    async fn load_pool(&self, _: &str) -> Result<Option<Pool>, StoreError> {
        let mut u = self.unsettled.lock();
        self.reap(&mut u);
        let pool = self.shared.pool.lock().clone();
        let behind = u.in_flight.iter().any(|f| f.version > pool.version());
        Ok((!behind).then(|| (*pool).clone()))
    }

    fn changes(&self) -> Option<broadcast::Receiver<PoolChanged>> {
        Some(self.shared.changes.subscribe())
    }

    /// Shared with the server: the registry reports steps every so often
    /// (`sync_counters`) and takes the followed pool's updates.
    fn is_shared(&self) -> bool {
        true
    }

    async fn load_task(&self, id: &str) -> Result<Option<StoredTask>, StoreError> {
        Ok((id == self.shared.key).then(|| self.stored()))
    }

    async fn task_ids(&self) -> Result<Option<Vec<String>>, StoreError> {
        Ok(Some(vec![self.shared.key.clone()]))
    }

    /// Reports the steps shaped since the last message, without waiting.
    async fn sync_counters(
        &self,
        _: &str,
        counters: Counters,
    ) -> Result<Option<Counters>, StoreError> {
        let msg = self.message(Vec::new(), counters);
        if msg.steps > 0 {
            if let Some(outgoing) = &*self.outgoing.lock() {
                let _ = outgoing.send(Outgoing { msg, reply: None });
            }
        }
        Ok(None)
    }
}
