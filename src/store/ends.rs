//! The record of committed episode ends per client (SPEC §9: a re-sent batch must not
//! commit the same episode end twice), as counts: per client id and env, the number of
//! episodes whose end was committed, so episode `count - 1` is the last one. Counts only
//! grow (merging takes the maximum), so records may be merged in any order.
//!
//! One table type for the registry (what a running server remembers) and the disk store
//! (what survives a restart of a `--data-dir` server).

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

/// How many client ids a task remembers for the no-double-commit rule at most; the one
/// that committed least recently is forgotten first.
pub const MAX_REMEMBERED_CLIENTS: usize = 65_536;

/// How many (client, env) counts a task remembers at most (about 20–40 MB), whatever the
/// clients' env counts: past it, the clients that committed least recently are forgotten
/// (the client just recorded never is).
pub const MAX_REMEMBERED_ENDS: usize = 1 << 20;

/// One client's record and when it last committed.
#[derive(Debug, Default, Clone)]
struct ClientEnds {
    /// Per env, the number of episodes whose end was committed.
    envs: HashMap<u32, u64>,
    /// The merge that touched the client last (see `EndedEpisodes::order`).
    stamp: u64,
}

/// Per client id: per env, the number of episodes whose end was committed. Bounded in
/// clients ([`MAX_REMEMBERED_CLIENTS`]) and in counts ([`MAX_REMEMBERED_ENDS`]), the
/// client that committed least recently first out.
#[derive(Debug, Default, Clone)]
pub struct EndedEpisodes {
    by_client: HashMap<Arc<str>, ClientEnds>,
    /// `(stamp, client)` per merge, oldest first; an entry whose stamp is no longer the
    /// client's is stale (the client merged again since) and skipped.
    order: VecDeque<(u64, Arc<str>)>,
    next_stamp: u64,
    /// Σ over clients of their env counts.
    entries: usize,
}

impl EndedEpisodes {
    /// Records that `client` ended episodes up to `count - 1` of `env`, for each
    /// `(env, count)`; a count lower than the one recorded changes nothing.
    pub fn merge(&mut self, client: &str, counts: impl IntoIterator<Item = (u32, u64)>) {
        let stamp = self.next_stamp;
        self.next_stamp += 1;
        let key: Arc<str> = match self.by_client.get_key_value(client) {
            Some((k, _)) => k.clone(),
            None => Arc::from(client),
        };
        let record = self.by_client.entry(key.clone()).or_default();
        record.stamp = stamp;
        for (env, count) in counts {
            let n = record.envs.entry(env).or_insert_with(|| {
                self.entries += 1;
                0
            });
            *n = (*n).max(count);
        }
        self.order.push_back((stamp, key));
        self.forget_least_recent(stamp);
        if self.order.len() > 2 * self.by_client.len() + 64 {
            // Drop the stale entries, so that the queue stays within twice the clients.
            let by_client = &self.by_client;
            self.order
                .retain(|(stamp, c)| by_client.get(c).is_some_and(|r| r.stamp == *stamp));
        }
    }

    /// Forgets the clients that committed least recently while past a bound, but never
    /// the one stamped `keep` (just recorded).
    fn forget_least_recent(&mut self, keep: u64) {
        while self.by_client.len() > MAX_REMEMBERED_CLIENTS || self.entries > MAX_REMEMBERED_ENDS {
            let Some((stamp, client)) = self.order.pop_front() else {
                return;
            };
            if stamp == keep {
                self.order.push_front((stamp, client));
                return;
            }
            if self
                .by_client
                .get(&client)
                .is_some_and(|r| r.stamp == stamp)
            {
                if let Some(r) = self.by_client.remove(&client) {
                    self.entries -= r.envs.len();
                }
            }
        }
    }

    /// Whether episode `number` of `env` of `client` was committed.
    pub fn contains(&self, client: &str, env: u32, number: u64) -> bool {
        self.by_client
            .get(client)
            .and_then(|r| r.envs.get(&env))
            .is_some_and(|&n| n > number)
    }

    /// `client`'s counts, `(env, count)`, in env order.
    pub fn counts(&self, client: &str) -> Vec<(u32, u64)> {
        let mut out: Vec<(u32, u64)> = self
            .by_client
            .get(client)
            .map(|r| r.envs.iter().map(|(&e, &n)| (e, n)).collect())
            .unwrap_or_default();
        out.sort_unstable();
        out
    }

    /// Every client's counts, the client that committed least recently first (merging
    /// them in this order into an empty record rebuilds this one).
    pub fn all(&self) -> impl Iterator<Item = (&str, Vec<(u32, u64)>)> + '_ {
        let mut clients: Vec<(u64, &str)> = self
            .by_client
            .iter()
            .map(|(c, r)| (r.stamp, &**c))
            .collect();
        clients.sort_unstable();
        clients.into_iter().map(|(_, c)| (c, self.counts(c)))
    }

    /// Whether nothing is recorded.
    pub fn is_empty(&self) -> bool {
        self.by_client.is_empty()
    }
}

#[cfg(test)]
mod tests;
