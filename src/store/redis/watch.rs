//! Following the other servers: every server subscribes to `tamrm:changes` and also polls
//! the versions of the tasks it holds every `poll_interval`, as a backstop for
//! notifications lost while disconnected, and announces what changed on the store's
//! [`Store::changes`](crate::store::Store::changes) feed.

use std::sync::Arc;
use std::time::Duration;

use dashmap::DashMap;
use futures::StreamExt;
use tokio::sync::broadcast;

use super::conn::Conn;
use super::keys::{Keys, CHANNEL};
use super::store::Held;
use crate::store::PoolChanged;

/// Follows `tamrm:changes` (subscribed on one of `subscribers`, the next one when it
/// fails) and polls every held task's version each `poll`, announcing on `tx` every newer
/// version and every deletion of a held incarnation.
pub(super) async fn watch(
    subscribers: Vec<redis::Client>,
    mut conn: Conn,
    held: Arc<DashMap<String, Held>>,
    tx: broadcast::Sender<PoolChanged>,
    poll: Duration,
) {
    let mut messages = None;
    let mut next = 0;
    let mut tick = tokio::time::interval(poll);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        if messages.is_none() {
            messages = subscribe(&subscribers, &mut next).await;
        }
        let message = async {
            match messages.as_mut() {
                Some(m) => m.next().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            m = message => match m {
                Some(m) => announce(&held, &tx, m.get_payload_bytes()),
                None => messages = None,
            },
            _ = tick.tick() => {
                if let Err(e) = poll_versions(&mut conn, &held, &tx).await {
                    tracing::warn!(error = %e, "could not poll pool versions in Redis");
                    // The subscription may hang on a connection just as dead, silently:
                    // subscribe again.
                    messages = None;
                }
                if messages.is_none() {
                    messages = subscribe(&subscribers, &mut next).await;
                }
            }
        }
    }
}

/// How long a subscription may take before it counts as failed.
const SUBSCRIBE_TIMEOUT: Duration = Duration::from_secs(5);

/// Subscribes on `subscribers[*next]`, moving `next` on to the following one if that
/// fails (a cluster delivers every `PUBLISH` on every node).
async fn subscribe(
    subscribers: &[redis::Client],
    next: &mut usize,
) -> Option<redis::aio::PubSubStream> {
    let client = subscribers.get(*next % subscribers.len().max(1))?;
    let subscribed = async {
        let mut pubsub = client.get_async_pubsub().await?;
        pubsub.subscribe(CHANNEL).await?;
        Ok::<_, redis::RedisError>(pubsub.into_on_message())
    };
    // Bounded: behind a partition a new connection can hang rather than fail.
    let subscribed = tokio::time::timeout(SUBSCRIBE_TIMEOUT, subscribed)
        .await
        .unwrap_or_else(|_| Err(std::io::Error::from(std::io::ErrorKind::TimedOut).into()));
    match subscribed {
        Ok(stream) => Some(stream),
        Err(e) => {
            tracing::warn!(error = %e, "could not subscribe to Redis notifications");
            *next = next.wrapping_add(1);
            None
        }
    }
}

/// Parses `<version|deleted> <incarnation> <task>` and announces it if it concerns a held
/// incarnation.
fn announce(held: &DashMap<String, Held>, tx: &broadcast::Sender<PoolChanged>, payload: &[u8]) {
    let text = String::from_utf8_lossy(payload);
    let mut parts = text.splitn(3, ' ');
    let (Some(what), Some(incarnation), Some(task)) = (parts.next(), parts.next(), parts.next())
    else {
        return;
    };
    let Some(ours) = held.get(task).map(|h| h.incarnation.clone()) else {
        return;
    };
    if what == "deleted" {
        if ours == incarnation {
            held.remove(task);
            let _ = tx.send(deleted(task));
        }
    } else if ours != incarnation {
        // A new task of the same id: the one this server holds was deleted.
        held.remove(task);
        let _ = tx.send(deleted(task));
    } else if let Ok(version) = what.parse() {
        let _ = tx.send(PoolChanged {
            task: task.to_string(),
            version,
            deleted: false,
        });
    }
}

fn deleted(task: &str) -> PoolChanged {
    PoolChanged {
        task: task.to_string(),
        version: 0,
        deleted: true,
    }
}

/// The versions and incarnations of every held task, requested all at once (one round
/// trip on one server; one per node holding them on a cluster, where a pipeline cannot
/// span slots).
async fn poll_versions(
    conn: &mut Conn,
    held: &DashMap<String, Held>,
    tx: &broadcast::Sender<PoolChanged>,
) -> Result<(), redis::RedisError> {
    let tasks: Vec<(String, String)> = held
        .iter()
        .map(|h| (h.key().clone(), h.incarnation.clone()))
        .collect();
    let rows = futures::future::join_all(tasks.iter().map(|(task, _)| {
        let mut conn = conn.clone();
        async move {
            redis::cmd("HMGET")
                .arg(Keys::of(task).meta)
                .arg("version")
                .arg("incarnation")
                .query_async::<(Option<u64>, Option<String>)>(&mut conn)
                .await
        }
    }))
    .await;
    for ((task, ours), row) in tasks.iter().zip(rows) {
        match row? {
            (Some(version), Some(inc)) if &inc == ours => {
                let _ = tx.send(PoolChanged {
                    task: task.clone(),
                    version,
                    deleted: false,
                });
            }
            _ => {
                held.remove(task);
                let _ = tx.send(deleted(task));
            }
        }
    }
    Ok(())
}
