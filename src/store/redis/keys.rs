//! The key layout of a task in Redis (see the module documentation of
//! [`super`](crate::store::redis)): every key of task `K` carries the hash tag `{K}`, so a
//! task lives in one Redis Cluster slot.

/// The set of every task key (the only key outside a task's slot).
pub(super) const TASKS: &str = "tamrm:tasks";
/// The channel of pool changes and deletions.
pub(super) const CHANNEL: &str = "tamrm:changes";

/// The keys of one task.
pub(super) struct Keys {
    /// The hash of config, capacity, version, next seq, incarnation and counters.
    pub meta: String,
    /// The hash seq → trajectory bytes.
    pub traj: String,
    /// The hash seq → score.
    pub scores: String,
}

impl Keys {
    /// The keys of task `task` (a registry task key).
    pub fn of(task: &str) -> Keys {
        Keys {
            meta: format!("tamrm:{{{task}}}:meta"),
            traj: format!("tamrm:{{{task}}}:traj"),
            scores: format!("tamrm:{{{task}}}:scores"),
        }
    }

    /// The end record (SPEC §9) of `client` on this creation of `task`.
    pub fn ended(task: &str, incarnation: &str, client: &str) -> String {
        format!("tamrm:{{{task}}}:ended:{incarnation}:{client}")
    }
}

/// The keys of a tenant's quota usage shared by every replica (`ledger.rs`); both carry the
/// hash tag `{tenant}`.
pub(super) struct QuotaKeys {
    /// The sorted set of the tenant's stream leases (lease id → expiry, ms).
    pub leases: String,
    /// The hash of the tenant's steps-per-second bucket.
    pub steps: String,
}

impl QuotaKeys {
    /// The keys of tenant `tenant`.
    pub fn of(tenant: &str) -> QuotaKeys {
        QuotaKeys {
            leases: format!("tamrm:quota:{{{tenant}}}:streams"),
            steps: format!("tamrm:quota:{{{tenant}}}:steps"),
        }
    }
}
