//! [`RedisStore`]: task configs and pools in Redis (or Valkey), shared by any number of
//! servers (SPEC §10). `docs/scaling.md` describes the layout, the guarantees and the
//! staleness bound.
//!
//! Layout, for a task key `K` (see [`crate::task_key`]; `keys.rs`); every key of a task
//! carries the hash tag `{K}`, so a task lives in one Redis Cluster slot:
//! - `tamrm:{K}:meta`, a hash: `config` (JSON), `capacity`, `version`, `next_seq`,
//!   `incarnation` (names this creation of `K`, so that a server holding a deleted task
//!   never writes into a new task of the same id), `episodes_completed`, `steps_shaped`;
//! - `tamrm:{K}:traj`, a hash seq → the trajectory in the disk format's bytes (with seq 0:
//!   the field is its seq), and `tamrm:{K}:scores`, a hash seq → its score, for the update
//!   rule to read without decoding trajectories;
//! - `tamrm:{K}:ended:<incarnation>:<client>`, a hash env → episodes ended: the record of
//!   the no-double-commit rule of SPEC §9, expiring after `ended_ttl` without commits;
//! - `tamrm:tasks`, the set of every task key (the only key outside a task's slot; it is
//!   written before a creation and after a deletion, so a key in it may have no task,
//!   never the reverse);
//! - `tamrm:quota:{tenant}:streams` and `tamrm:quota:{tenant}:steps`, a tenant's stream
//!   leases and steps-per-second bucket, shared by every replica (`ledger.rs`).
//!
//! Every change is one Lua script, atomic in Redis (`*.lua` beside this file, run by
//! `scripts.rs`): the §6 update decided against the pool in Redis, the version bump, the
//! counters, the end record and a `PUBLISH` on `tamrm:changes`. Every server subscribes,
//! and also polls the versions every `poll_interval` as a backstop for notifications lost
//! while disconnected (`watch.rs`).
//!
//! Redis Cluster (`redis-cluster://`): every script and every atomic read touches the keys
//! of one task only, so each runs on the node holding the task's slot; tasks spread over
//! the nodes by their hash tags. `tamrm:tasks` lives in the slot of its own name. Changes
//! are published with the classic `PUBLISH`, which a cluster delivers on every node, so a
//! server subscribes on any one node (the next seed node when that one fails).
//!
//! TLS (`rediss://`, `rediss-cluster://`): every connection, to every node, speaks TLS,
//! verified against the CA file of [`RedisTls`] (else the system's roots), with its client
//! certificate if it has one.
//!
//! The files, one job each: `url.rs` (the URL forms), `tls.rs` (the TLS files), `conn.rs`
//! (the connection and its errors), `keys.rs` (the key layout), `scripts.rs` and `*.lua` (the atomic changes),
//! `ledger.rs` (tenant quotas over every replica), `codec.rs` (a task's hashes to and from the library's types), `store.rs` (the
//! [`Store`](crate::store::Store) methods), `watch.rs` (following other servers).

mod codec;
mod conn;
mod keys;
mod ledger;
mod scripts;
mod store;
mod tls;
mod url;
mod watch;

pub use ledger::RedisLedger;
pub use store::{RedisOptions, RedisStore};
pub use tls::RedisTls;
pub use url::RedisTarget;

#[cfg(test)]
mod tests;
