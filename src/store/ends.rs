//! The record of committed episode ends per client (SPEC §9: a re-sent batch must not
//! commit the same episode end twice), as counts: per client id and env, the number of
//! episodes whose end was committed, so episode `count - 1` is the last one. Counts only
//! grow (merging takes the maximum), so records may be merged in any order.
//!
//! One table type for the registry (what a running server remembers) and the disk store
//! (what survives a restart of a `--data-dir` server).

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

/// How many client ids a task remembers for the no-double-commit rule at most; the
/// oldest is forgotten first.
pub const MAX_REMEMBERED_CLIENTS: usize = 65_536;

/// Per client id: per env, the number of episodes whose end was committed. Bounded in
/// clients ([`MAX_REMEMBERED_CLIENTS`], the oldest first out).
#[derive(Debug, Default, Clone)]
pub struct EndedEpisodes {
    by_client: HashMap<Arc<str>, HashMap<u32, u64>>,
    order: VecDeque<Arc<str>>,
}

impl EndedEpisodes {
    /// Records that `client` ended episodes up to `count - 1` of `env`, for each
    /// `(env, count)`; a count lower than the one recorded changes nothing.
    pub fn merge(&mut self, client: &str, counts: impl IntoIterator<Item = (u32, u64)>) {
        if !self.by_client.contains_key(client) {
            if self.order.len() >= MAX_REMEMBERED_CLIENTS {
                if let Some(old) = self.order.pop_front() {
                    self.by_client.remove(&old);
                }
            }
            let key: Arc<str> = Arc::from(client);
            self.order.push_back(key.clone());
            self.by_client.insert(key, HashMap::new());
        }
        if let Some(envs) = self.by_client.get_mut(client) {
            for (env, count) in counts {
                let n = envs.entry(env).or_insert(0);
                *n = (*n).max(count);
            }
        }
    }

    /// Whether episode `number` of `env` of `client` was committed.
    pub fn contains(&self, client: &str, env: u32, number: u64) -> bool {
        self.by_client
            .get(client)
            .and_then(|envs| envs.get(&env))
            .is_some_and(|&n| n > number)
    }

    /// `client`'s counts, `(env, count)`, in env order.
    pub fn counts(&self, client: &str) -> Vec<(u32, u64)> {
        let mut out: Vec<(u32, u64)> = self
            .by_client
            .get(client)
            .map(|envs| envs.iter().map(|(&e, &n)| (e, n)).collect())
            .unwrap_or_default();
        out.sort_unstable();
        out
    }

    /// Every client's counts, oldest client first.
    pub fn all(&self) -> impl Iterator<Item = (&str, Vec<(u32, u64)>)> + '_ {
        self.order.iter().map(|c| (&**c, self.counts(c)))
    }

    /// Whether nothing is recorded.
    pub fn is_empty(&self) -> bool {
        self.by_client.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_only_grow_and_clients_are_separate() {
        let mut t = EndedEpisodes::default();
        t.merge("a", [(0, 3), (2, 1)]);
        t.merge("a", [(0, 2), (2, 4)]);
        t.merge("b", [(0, 1)]);
        assert_eq!(t.counts("a"), vec![(0, 3), (2, 4)]);
        assert!(t.contains("a", 0, 2) && !t.contains("a", 0, 3));
        assert!(t.contains("b", 0, 0) && !t.contains("b", 1, 0) && !t.contains("c", 0, 0));
        let all: Vec<_> = t.all().map(|(c, v)| (c.to_string(), v)).collect();
        assert_eq!(all[1], ("b".to_string(), vec![(0, 1)]));
    }

    #[test]
    fn the_oldest_client_is_forgotten_first() {
        let mut t = EndedEpisodes::default();
        for i in 0..=MAX_REMEMBERED_CLIENTS {
            t.merge(&i.to_string(), [(0, 1)]);
        }
        assert!(!t.contains("0", 0, 0));
        assert!(t.contains("1", 0, 0));
        assert!(t.contains(&MAX_REMEMBERED_CLIENTS.to_string(), 0, 0));
    }
}
