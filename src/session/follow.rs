//! The transport-free Follow stream (SPEC §13): a learner shapes its steps in its own
//! process against a copy of a task's pool and sends only its episode ends.
//!
//! A [`FollowSession`] tells its transport what the learner must be sent to hold the
//! latest published pool ([`FollowSession::news`]: a snapshot first, then updates that
//! never leave a gap), wakes it when the pool changes ([`FollowSession::changed`]), and
//! decides the learner's episode ends exactly as a `Shape` stream decides the ends of one
//! batch ([`FollowSession::ends`]): against the planned pool under the task's writer lock,
//! in order, at most once per (client, env, episode), committed with one commit for the
//! message (shared with the other streams' changes queued at the same time).

use std::collections::HashSet;
use std::sync::Arc;

use crate::core::{ActionCount, Pool, Trajectory};
use crate::error::Error;
use crate::registry::{Registry, StreamBytes, StreamGuard, TaskHandle, DEFAULT_TENANT};
use crate::store::{EndMark, PoolOp};

use super::check_open;

/// Most steps one message may report: far more than a learner shapes between two of its
/// messages, far below what could overflow the task's counter.
pub const MAX_REPORTED_STEPS: u64 = u32::MAX as u64;

/// What opens a Follow stream (the proto's `FollowOpen`).
#[derive(Debug, Clone, Copy)]
pub struct FollowRequest<'a> {
    /// The tenant of the caller (SPEC §11).
    pub tenant: &'a str,
    /// The task to follow.
    pub task_id: &'a str,
    /// Environments whose ends the stream reports, numbered `0..num_envs`.
    pub num_envs: u32,
    /// Names the client across its streams; empty for none.
    pub client_id: &'a str,
    /// Bytes the transport holds for the stream (its receive window), counted against
    /// `max_total_stream_bytes`.
    pub transport_bytes: u64,
}

impl Default for FollowRequest<'_> {
    /// The default tenant's task `""`, no env, no client id.
    fn default() -> Self {
        FollowRequest {
            tenant: DEFAULT_TENANT,
            task_id: "",
            num_envs: 0,
            client_id: "",
            transport_bytes: 0,
        }
    }
}

/// One finished episode shaped at the learner (the proto's `EpisodeEnd`).
#[derive(Debug, Clone, Copy, Default)]
pub struct EndInput<'a> {
    /// The environment, `< num_envs`.
    pub env_id: u32,
    /// Episodes the environment ended before this one.
    pub episode: u64,
    /// Discrete tasks: the actions.
    pub actions: &'a [u32],
    /// Continuous tasks: L × action_dim floats.
    pub action_vectors: &'a [f32],
    /// The client's score, if it sent one.
    pub score: Option<f64>,
    /// Σ R of the episode: the score when `score` is `None`.
    pub reward_sum: f64,
}

/// What the learner must be sent to hold the latest published pool.
#[derive(Debug, Clone)]
pub enum PoolNews {
    /// The whole pool: the learner replaces its copy.
    Snapshot(Arc<Pool>),
    /// The net change from the version the learner holds (`base`) to `pool`.
    Update {
        /// The version the learner holds.
        base: u64,
        /// The pool after the update (its version and next seq).
        pool: Arc<Pool>,
        /// Seqs removed.
        removed: Vec<u64>,
        /// Trajectories added, by seq.
        added: Vec<Arc<Trajectory>>,
    },
}

/// The answer to one message of ends (the proto's `EndsAck`), per end in request order.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Ack {
    /// Whether the end changed the pool.
    pub changed: Vec<bool>,
    /// The pool version right after the end was decided.
    pub versions: Vec<u64>,
    /// Whether the end had been committed before (not offered again).
    pub resent: Vec<bool>,
    /// The pool version after the message.
    pub pool_version: u64,
}

/// One open Follow stream on one task.
pub struct FollowSession {
    task: Arc<TaskHandle>,
    _guard: StreamGuard,
    _memory: StreamBytes,
    num_envs: u32,
    client_id: Option<Arc<str>>,
    /// The pool the learner holds (`None` before the first snapshot).
    sent: Option<Arc<Pool>>,
    changes: tokio::sync::watch::Receiver<u64>,
}

impl FollowSession {
    /// Opens a Follow stream on `req.task_id` (SPEC §13).
    pub async fn open(registry: &Registry, req: &FollowRequest<'_>) -> Result<Self, Error> {
        check_open(registry, req.task_id, req.num_envs)?;
        let task = registry.lookup(req.tenant, req.task_id).await?;
        // The first snapshot holds every change acknowledged anywhere (SPEC §13: a
        // learner's own ends are applied before its next step, even after a failover).
        task.catch_up_with_store().await;
        // The episodes live at the learner: the stream holds its window and a pool copy
        // it shares with the task.
        let memory = registry.reserve_stream_bytes(req.transport_bytes)?;
        if !req.client_id.is_empty() {
            // What the store committed for this client before (another server, a
            // restart) must not be committed again (SPEC §9).
            task.learn_ended(req.client_id).await?;
        }
        let changes = task.subscribe();
        let guard = task.open_stream()?;
        Ok(FollowSession {
            task,
            _guard: guard,
            _memory: memory,
            num_envs: req.num_envs,
            client_id: (!req.client_id.is_empty()).then(|| Arc::from(req.client_id)),
            sent: None,
            changes,
        })
    }

    /// The task followed.
    pub fn task(&self) -> &Arc<TaskHandle> {
        &self.task
    }

    /// What the learner must be sent now to hold the latest published pool, `None` if it
    /// holds it. The first call answers a snapshot; later ones the net update since the
    /// last answer, or a snapshot when the update would replace everything (a reset).
    pub fn news(&mut self) -> Option<PoolNews> {
        let latest = self.task.snapshot();
        let news = match &self.sent {
            None => PoolNews::Snapshot(latest.clone()),
            Some(sent) if sent.version() == latest.version() => return None,
            // The task's store went back (it lost changes): the learner starts over.
            Some(sent) if sent.version() > latest.version() => PoolNews::Snapshot(latest.clone()),
            Some(sent) => {
                let (removed, added) = sent.diff(&latest);
                if removed.len() == sent.len() && added.len() == latest.len() {
                    PoolNews::Snapshot(latest.clone())
                } else {
                    PoolNews::Update {
                        base: sent.version(),
                        pool: latest.clone(),
                        removed,
                        added,
                    }
                }
            }
        };
        self.sent = Some(latest);
        Some(news)
    }

    /// Waits until the task publishes a pool (possibly the one already sent), or fails
    /// with `NOT_FOUND` once the task is deleted.
    pub async fn changed(&mut self) -> Result<(), Error> {
        self.task.check_live()?;
        if self.changes.changed().await.is_err() {
            // The task handle is gone: it was dropped from the registry.
            return Err(Error::not_found(self.task.id()));
        }
        self.task.check_live()
    }

    /// Decides the learner's episode ends as the ends of one `Shape` batch are decided
    /// (SPEC §6, §9), in one commit, and counts `steps` shaped steps. The message is
    /// validated whole first (SPEC §8): a rejected one commits and counts nothing.
    pub async fn ends(&mut self, ends: &[EndInput<'_>], steps: u64) -> Result<Ack, Error> {
        let config = *self.task.config();
        if steps > MAX_REPORTED_STEPS {
            return Err(Error::invalid(
                "ends.steps",
                format!("at most {MAX_REPORTED_STEPS} steps per message, got {steps}"),
            ));
        }
        let mut offers = Vec::with_capacity(ends.len());
        let mut seen = HashSet::with_capacity(ends.len());
        for (i, e) in ends.iter().enumerate() {
            let field = format!("ends.ends[{i}].");
            if e.env_id >= self.num_envs {
                return Err(Error::invalid(
                    format!("{field}env_id"),
                    format!(
                        "env {} out of range: num_envs = {}",
                        e.env_id, self.num_envs
                    ),
                ));
            }
            if !seen.insert((e.env_id, e.episode)) {
                return Err(Error::invalid(
                    format!("{field}episode"),
                    format!("env {} episode {} is listed twice", e.env_id, e.episode),
                ));
            }
            let mut actions = config
                .action_space
                .to_seq(
                    e.actions.to_vec(),
                    e.action_vectors.to_vec(),
                    ActionCount::AtLeastOne,
                )
                .map_err(|err| Error::invalid(err.field(&field), err.message))?;
            actions.truncate(config.max_trajectory_len as usize);
            for (name, v) in [("reward_sum", Some(e.reward_sum)), ("score", e.score)] {
                if let Some(v) = v.filter(|v| !v.is_finite()) {
                    return Err(Error::invalid(
                        format!("{field}{name}"),
                        format!("must be finite, got {v}"),
                    ));
                }
            }
            offers.push((actions, e.score.unwrap_or(e.reward_sum)));
        }
        self.task.check_live()?;
        if offers.is_empty() {
            self.task.count_steps(steps as usize);
            return Ok(Ack {
                pool_version: self.task.published_version(),
                ..Ack::default()
            });
        }
        let writer = self.task.writer().await?;
        let mut resent = Vec::with_capacity(ends.len());
        let mut ops = Vec::with_capacity(ends.len());
        let mut marks = Vec::new();
        for (e, (actions, score)) in ends.iter().zip(offers) {
            let client = self.client_id.as_ref();
            if client.is_some_and(|c| self.task.already_ended(c, e.env_id, e.episode)) {
                resent.push(true);
                continue;
            }
            resent.push(false);
            if client.is_some() {
                marks.push((e.env_id, e.episode));
            }
            self.task.count_episode();
            ops.push(PoolOp::Offer {
                actions,
                score,
                end: client.map(|c| EndMark {
                    client: c.clone(),
                    env: e.env_id,
                    episode: e.episode,
                }),
            });
        }
        self.task.count_steps(steps as usize);
        let client = self.client_id.as_deref();
        let committed = self
            .task
            .commit_ends(writer, ops, client.map(|c| (c, marks.as_slice())))
            .await?;
        if committed.resent > 0 {
            // Another server committed some of these ends after this stream learnt the
            // client's record (SPEC §9): the store did not offer them again, but the ack
            // cannot tell which they were. The others are committed; a new stream learns
            // the record and answers the re-sent message with them resent.
            return Err(Error::ResumeNeeded(format!(
                "{} episode end(s) of this message were committed meanwhile by another \
                 server for client {:?}: open a new stream and re-send the message",
                committed.resent,
                client.unwrap_or_default()
            )));
        }
        // The version after each offer: the commit's own changes end at `version`.
        let made = committed.changed.iter().filter(|&&c| c).count() as u64;
        let mut version = committed.version.saturating_sub(made);
        let mut changed = committed.changed.iter();
        let mut ack = Ack {
            pool_version: committed.version,
            ..Ack::default()
        };
        for was_resent in resent {
            let c = !was_resent && changed.next().copied().unwrap_or(false);
            version += u64::from(c);
            ack.changed.push(c);
            ack.versions.push(version);
            ack.resent.push(was_resent);
        }
        Ok(ack)
    }
}
