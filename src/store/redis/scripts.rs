//! The Lua scripts that change a task in Redis atomically, each in its `.lua` file beside
//! this one (whose header documents its KEYS, ARGV and answer), and the Rust side of their
//! calling convention: the arguments of a commit and the reading of its answer.

use std::sync::Arc;
use std::time::Duration;

use redis::{Script, ScriptInvocation};

use super::codec::score_text;
use super::keys::{Keys, CHANNEL};
use crate::core::Trajectory;
use crate::store::disk::encode_trajectory;
use crate::store::{Counters, PoolOp};

/// The scripts of a store (sent by their SHA, loaded again when Redis lacks them).
pub(super) struct Scripts {
    /// `create.lua`: creates a task unless one exists.
    pub create: Script,
    /// `delete.lua`: deletes one incarnation of a task.
    pub delete: Script,
    /// `commit.lua`: the §6 update of a commit, with its counters and end records.
    pub commit: Script,
}

impl Scripts {
    /// The scripts, as this build ships them.
    pub fn new() -> Scripts {
        Scripts {
            create: Script::new(include_str!("create.lua")),
            delete: Script::new(include_str!("delete.lua")),
            commit: Script::new(include_str!("commit.lua")),
        }
    }
}

/// One run of `commit.lua`: the operations of a commit on one incarnation of a task.
pub(super) struct CommitCall<'a> {
    /// The task key.
    pub task: &'a str,
    /// The incarnation the commit is for (it changes nothing in another one).
    pub incarnation: &'a str,
    /// The operations, in order.
    pub ops: &'a [PoolOp],
    /// The counter increments since this server last wrote the task's counters.
    pub delta: Counters,
    /// How long a client's end record is kept after its last commit.
    pub ended_ttl: Duration,
}

impl CommitCall<'_> {
    /// The invocation of `script` (`commit.lua`) with this commit's keys and arguments.
    pub fn invocation<'s>(&self, script: &'s Script) -> ScriptInvocation<'s> {
        let keys = Keys::of(self.task);
        // The clients whose end records the commit touches, in order of first mention (a
        // group commit carries the ends of every writer in it).
        let mut clients: Vec<&Arc<str>> = Vec::new();
        for op in self.ops {
            if let PoolOp::Offer { end: Some(e), .. } = op {
                if !clients.contains(&&e.client) {
                    clients.push(&e.client);
                }
            }
        }
        let mut inv = script.prepare_invoke();
        inv.key(&keys.meta).key(&keys.traj).key(&keys.scores);
        for client in &clients {
            inv.key(Keys::ended(self.task, self.incarnation, client));
        }
        inv.arg(self.incarnation)
            .arg(CHANNEL)
            .arg(self.task)
            .arg(self.delta.episodes_completed)
            .arg(self.delta.steps_shaped)
            .arg(self.ended_ttl.as_secs().max(1))
            .arg(self.ops.len());
        for op in self.ops {
            match op {
                PoolOp::Reset => {
                    inv.arg("reset").arg("").arg("").arg("").arg("").arg("");
                }
                PoolOp::Offer {
                    actions,
                    score,
                    end,
                } => {
                    let bytes = encode_trajectory(&Trajectory {
                        actions: actions.clone(),
                        score: *score,
                        seq: 0,
                    });
                    let (env, count, record) = match end {
                        Some(e) => {
                            let record =
                                clients.iter().position(|c| **c == e.client).unwrap_or(0) + 1;
                            (
                                e.env.to_string(),
                                e.episode.saturating_add(1).to_string(),
                                record.to_string(),
                            )
                        }
                        None => (String::new(), String::new(), String::new()),
                    };
                    inv.arg("offer")
                        .arg(score_text(*score))
                        .arg(bytes)
                        .arg(env)
                        .arg(count)
                        .arg(record);
                }
            }
        }
        inv
    }
}

/// The answer of `commit.lua` for a task that exists.
pub(super) struct CommitAnswer {
    /// The pool version before the commit.
    pub before: u64,
    /// The pool version after it.
    pub after: u64,
    /// The next seq before it.
    pub seq_before: u64,
    /// Per op: 1 changed the pool, 0 did not, 2 a re-sent end (not offered).
    pub decided: Vec<u64>,
    /// The offers that were re-sent ends (2 in `decided`).
    pub resent: usize,
}

impl CommitAnswer {
    /// Reads the script's answer; `None` if the task (that incarnation of it) is gone.
    pub fn read(out: &[u64]) -> Option<CommitAnswer> {
        match out {
            [1, before, after, seq_before, decided @ ..] => Some(CommitAnswer {
                before: *before,
                after: *after,
                seq_before: *seq_before,
                resent: decided.iter().filter(|&&c| c == 2).count(),
                decided: decided.to_vec(),
            }),
            _ => None,
        }
    }
}
