//! One shaping session: the episode state the client keeps ([`Tracker`]) and the
//! transport its steps go over ([`Transport`]: a `Shape` stream to a server, or the
//! session layer in-process).

use tamrm::proto;
use tamrm::session::Batch;
use tonic::{Code, Status};

use crate::answer::Answer;
use crate::error::Error;
use crate::tracker::Tracker;

/// Where a session's steps go. The session keeps the episode state ([`Tracker`]); a
/// transport that resumes a broken stream reads it (SPEC §9).
pub trait Transport: Send {
    /// Shapes one batch. A rejected batch (INVALID_ARGUMENT) changed nothing: a transport
    /// with a stream re-opens it with every episode of `tracker` resumed before it
    /// returns the error.
    fn step(&mut self, batch: &Batch<'_>, tracker: &Tracker) -> Result<Answer, Error>;

    /// Ends the session: its episodes in progress are discarded.
    fn close(&mut self);

    /// (Re-)opens the session with the episodes of `tracker` (none after a close).
    fn reopen(&mut self, tracker: &Tracker) -> Result<(), Status>;

    /// Whether the transport is gone (a failed re-open after a rejected batch).
    fn broken(&self) -> bool {
        false
    }

    /// Whether the transport resumes episodes on a new stream (the tracker then keeps
    /// their actions).
    fn resumes(&self) -> bool {
        false
    }
}

/// An open session on one task for a fixed number of environments.
pub struct Session {
    transport: Box<dyn Transport>,
    tracker: Tracker,
    closed: bool,
    /// The pool version after the last answered batch (or at open).
    pool_version: u64,
    /// The task as `Open` answered it.
    opened: proto::Task,
    /// The abandons sent with the batch in flight.
    abandon: Vec<u32>,
}

fn closed_error() -> Status {
    Status::cancelled("the session is closed")
}

impl Session {
    /// A session over `transport`, opened on `task` (the answer to `Open`, whichever
    /// transport gave it: its config tells the action space, its stats the pool version).
    pub fn new(transport: Box<dyn Transport>, task: proto::Task, num_envs: usize) -> Session {
        let config = task.config.unwrap_or_default();
        let action_dim = if config.num_actions > 0 {
            0
        } else {
            config.action_dim as usize
        };
        let keep = transport.resumes();
        Session {
            tracker: Tracker::new(num_envs, action_dim, keep),
            transport,
            closed: false,
            pool_version: task.stats.map_or(0, |s| s.pool_version),
            opened: task,
            abandon: Vec::new(),
        }
    }

    /// The task as the server answered `Open`.
    pub fn opened(&self) -> &proto::Task {
        &self.opened
    }

    /// The environments of the session.
    pub fn num_envs(&self) -> usize {
        self.tracker.num_envs()
    }

    /// Whether the session is closed (by [`Session::close`] or a failure).
    pub fn closed(&self) -> bool {
        self.closed
    }

    /// The task's pool version after the last answered batch (or at open).
    pub fn pool_version(&self) -> u64 {
        self.pool_version
    }

    /// Per env: the steps sent in its current episode.
    pub fn episode_steps(&self) -> &[u64] {
        self.tracker.steps()
    }

    /// Shapes one step. `batch.abandon` is ignored: the abandons of
    /// [`Session::abandon`] travel with the next batch that has entries. An empty batch
    /// sends nothing. A rejected batch (INVALID_ARGUMENT) changed nothing and the session
    /// goes on; after any other failure the session is closed, its episodes discarded.
    pub fn step(&mut self, batch: &Batch<'_>) -> Result<Answer, Error> {
        if self.closed {
            return Err(closed_error().into());
        }
        let b = batch.len();
        if b == 0 {
            // Nothing is sent; pending abandons wait for a batch with entries.
            return Ok(Answer::default());
        }
        self.tracker.take_abandons(&mut self.abandon);
        let batch = Batch {
            abandon: &self.abandon,
            ..*batch
        };
        let answer = match self.transport.step(&batch, &self.tracker) {
            Ok(answer) => answer,
            Err(Error::Status(err)) if err.code() == Code::InvalidArgument => {
                // Rejected, nothing applied: the stream goes on (re-opened if remote);
                // the abandons travel with the next batch.
                self.tracker.restore_abandons(&self.abandon);
                if self.transport.broken() {
                    self.closed = true;
                    self.tracker.discard_episodes();
                }
                return Err(err.into());
            }
            Err(Error::Interrupted(interrupt)) => {
                self.closed = true;
                self.tracker.discard_episodes();
                return Err(Error::Interrupted(interrupt));
            }
            Err(other) => {
                self.closed = true;
                self.transport.close();
                self.tracker.discard_episodes();
                return Err(other);
            }
        };
        if answer.consistent_len() != Some(b) {
            self.closed = true;
            self.transport.close();
            return Err(Status::internal(format!(
                "the server answered {} entries for a batch of {b}",
                answer.rewards.len()
            ))
            .into());
        }
        if let Some((env, step)) = self.tracker.ignored_abandon(&batch, &answer) {
            self.closed = true;
            self.transport.close();
            return Err(Status::unimplemented(format!(
                "the server ignored StepBatch.abandon (SPEC v1.1 §12): env {env} went on \
                 with its abandoned episode at step {step}; upgrade the server"
            ))
            .into());
        }
        self.tracker.record(&batch, &answer);
        self.pool_version = answer.pool_version;
        Ok(answer)
    }

    /// Drops the current episodes of `envs` (sent with the next batch that has entries).
    pub fn abandon(&mut self, envs: &[u32]) -> Result<(), Error> {
        if self.closed {
            return Err(closed_error().into());
        }
        let n = self.tracker.num_envs();
        for (i, &e) in envs.iter().enumerate() {
            if e as usize >= n {
                return Err(Error::Invalid(format!(
                    "abandon: env id {e} is not in 0..{} (num_envs={n})",
                    n - 1
                )));
            }
            if envs[..i].contains(&e) {
                return Err(Error::Invalid(format!("abandon: env {e} is listed twice")));
            }
        }
        self.tracker.abandon(envs);
        Ok(())
    }

    /// Ends the session (idempotent); episodes in progress are discarded.
    pub fn close(&mut self) {
        if self.closed {
            return;
        }
        self.closed = true;
        self.tracker.discard_episodes();
        self.transport.close();
    }

    /// Re-opens a closed session on the same task (new episodes everywhere).
    pub fn reopen(&mut self) -> Result<(), Error> {
        self.tracker.discard_episodes();
        self.transport.reopen(&self.tracker)?;
        self.tracker.reopened();
        self.closed = false;
        Ok(())
    }
}
