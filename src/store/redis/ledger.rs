//! [`RedisLedger`]: the [`QuotaLedger`] of the tenants of a Redis store, shared by every
//! replica using it (docs/deployment.md, "Quotas with replicas").
//!
//! - **Stream leases**: a tenant's open streams are a sorted set
//!   (`tamrm:quota:{tenant}:streams`, lease id → expiry in ms of Redis's clock).
//!   `lease.lua` drops the expired leases, counts the rest and adds one unless the tenant
//!   holds `max`, in one step. A replica renews its live leases every third of the lease
//!   time (`renew.lua`) and removes a lease when its stream ends; the leases of a replica
//!   that dies expire within one lease time.
//! - **Steps**: a token bucket per tenant (`tamrm:quota:{tenant}:steps`) refilled by
//!   Redis's clock, from which replicas take blocks (`steps.lua`; the local side is
//!   [`crate::quota::StepBlocks`]).
//! - **Tasks**: `reserve.lua` adds a new task's key to the task index only while its
//!   tenant holds fewer than `max_tasks` keys there ([`reserve_task`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use dashmap::DashMap;
use redis::{AsyncCommands, Script};
use tokio::sync::mpsc;

use super::conn::{unavailable, Conn};
use super::keys::{QuotaKeys, TASKS};
use crate::quota::{LedgerError, QuotaLedger, StreamLease};
use crate::task_key::task_key;

/// The scripts of the ledger (sent by their SHA, loaded again when Redis lacks them).
struct Scripts {
    lease: Script,
    renew: Script,
    steps: Script,
}

/// A lease on a tenant's open stream that this replica holds: lease id → tenant.
type Live = DashMap<String, String>;

/// Tenant quotas in Redis, shared by every replica of the store; see the
/// [module documentation](self).
pub struct RedisLedger {
    what: String,
    conn: Conn,
    scripts: Arc<Scripts>,
    lease: Duration,
    /// Names this process in lease ids.
    replica: String,
    next: AtomicU64,
    live: Arc<Live>,
    ended: mpsc::UnboundedSender<(String, String)>,
    upkeep: tokio::task::JoinHandle<()>,
}

impl Drop for RedisLedger {
    fn drop(&mut self) {
        self.upkeep.abort();
    }
}

impl RedisLedger {
    /// The ledger on `conn` (of the store `what`), with leases of `lease`; starts renewing
    /// and giving back this replica's leases.
    pub(super) fn new(what: String, conn: Conn, lease: Duration) -> RedisLedger {
        let scripts = Arc::new(Scripts {
            lease: Script::new(include_str!("lease.lua")),
            renew: Script::new(include_str!("renew.lua")),
            steps: Script::new(include_str!("steps.lua")),
        });
        let live = Arc::new(Live::new());
        let (ended, rx) = mpsc::unbounded_channel();
        let upkeep = tokio::spawn(upkeep(
            what.clone(),
            conn.clone(),
            scripts.clone(),
            live.clone(),
            rx,
            lease,
        ));
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        RedisLedger {
            what,
            conn,
            scripts,
            lease,
            replica: format!("{nanos:x}-{:x}", std::process::id()),
            next: AtomicU64::new(0),
            live,
            ended,
            upkeep,
        }
    }

    fn fail(&self, doing: &str, e: redis::RedisError) -> LedgerError {
        LedgerError(unavailable(&self.what, doing, e).to_string())
    }
}

/// A lease this replica holds; its drop gives it back (through the upkeep task).
struct Held {
    tenant: String,
    id: String,
    live: Arc<Live>,
    ended: mpsc::UnboundedSender<(String, String)>,
}

impl Drop for Held {
    fn drop(&mut self) {
        self.live.remove(&self.id);
        let _ = self.ended.send((
            std::mem::take(&mut self.tenant),
            std::mem::take(&mut self.id),
        ));
    }
}

#[async_trait::async_trait]
impl QuotaLedger for RedisLedger {
    fn describe(&self) -> String {
        format!(
            "tenant quotas shared in {} (stream leases of {} ms)",
            self.what,
            self.lease.as_millis()
        )
    }

    async fn open_stream(
        &self,
        tenant: &str,
        max: usize,
    ) -> Result<Option<StreamLease>, LedgerError> {
        let id = format!(
            "{}:{}",
            self.replica,
            self.next.fetch_add(1, Ordering::Relaxed)
        );
        let took: u8 = self
            .scripts
            .lease
            .key(QuotaKeys::of(tenant).leases)
            .arg(&id)
            .arg(max)
            .arg(lease_ms(self.lease))
            .invoke_async(&mut self.conn.clone())
            .await
            .map_err(|e| self.fail("taking a stream lease", e))?;
        if took == 0 {
            return Ok(None);
        }
        self.live.insert(id.clone(), tenant.to_string());
        Ok(Some(StreamLease::new(Held {
            tenant: tenant.to_string(),
            id,
            live: self.live.clone(),
            ended: self.ended.clone(),
        })))
    }

    async fn take_steps(
        &self,
        tenant: &str,
        rate: u64,
        need: u64,
        want: u64,
    ) -> Result<u64, LedgerError> {
        self.scripts
            .steps
            .key(QuotaKeys::of(tenant).steps)
            .arg(rate)
            .arg(need)
            .arg(want)
            .invoke_async(&mut self.conn.clone())
            .await
            .map_err(|e| self.fail("taking step tokens", e))
    }
}

/// Adds task `id` of `tenant` to the index of every task (`tamrm:tasks`) if it is there
/// already or the tenant holds fewer than `max` tasks there, in one step: whether it is
/// there now.
pub(super) async fn reserve_task(
    conn: &mut Conn,
    id: &str,
    tenant: &str,
    max: usize,
) -> Result<bool, redis::RedisError> {
    let taken: u8 = Script::new(include_str!("reserve.lua"))
        .key(TASKS)
        .arg(id)
        .arg(task_key(tenant, "")) // the prefix of the tenant's keys
        .arg(max)
        .invoke_async(conn)
        .await?;
    Ok(taken == 1)
}

fn lease_ms(lease: Duration) -> u64 {
    u64::try_from(lease.as_millis()).unwrap_or(u64::MAX).max(1)
}

/// Gives back the leases whose streams ended (as `ended` reports them) and renews the
/// live ones every third of `lease`, until the ledger is dropped.
async fn upkeep(
    what: String,
    mut conn: Conn,
    scripts: Arc<Scripts>,
    live: Arc<Live>,
    mut ended: mpsc::UnboundedReceiver<(String, String)>,
    lease: Duration,
) {
    let mut tick = tokio::time::interval((lease / 3).max(Duration::from_millis(1)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            gone = ended.recv() => {
                let Some((tenant, id)) = gone else { return };
                let removed: Result<i64, _> = conn.zrem(QuotaKeys::of(&tenant).leases, &id).await;
                if let Err(e) = removed {
                    tracing::warn!(tenant, error = %unavailable(&what, "giving a stream lease back", e), "the lease expires by itself");
                }
            }
            _ = tick.tick() => {
                let mut by_tenant: HashMap<String, Vec<String>> = HashMap::new();
                for lease in live.iter() {
                    by_tenant.entry(lease.value().clone()).or_default().push(lease.key().clone());
                }
                for (tenant, ids) in by_tenant {
                    let mut call = scripts.renew.key(QuotaKeys::of(&tenant).leases);
                    call.arg(lease_ms(lease));
                    for id in &ids {
                        call.arg(id);
                    }
                    let renewed: Result<u64, _> = call.invoke_async(&mut conn).await;
                    if let Err(e) = renewed {
                        tracing::warn!(tenant, streams = ids.len(), error = %unavailable(&what, "renewing stream leases", e), "stream leases not renewed");
                    }
                }
            }
        }
    }
}
