//! The connection to Redis: one server or a cluster behind one type, opened from the
//! store's URL, and Redis errors turned into the store's (unavailable or not).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use parking_lot::Mutex;
use redis::aio::{ConnectionLike, ConnectionManager, ConnectionManagerConfig};
use redis::cluster_async::ClusterConnection;
use redis::{Cmd, Pipeline, RedisFuture, Value};

use super::tls::RedisTls;
use super::url::RedisTarget;
use crate::store::StoreError;

/// A connection to one server or to a cluster; both multiplex requests and reconnect by
/// themselves.
#[derive(Clone)]
pub(super) enum Conn {
    Node(NodeConn),
    Cluster(ClusterConnection),
}

/// The multiplexed connection to one Redis server. The manager reconnects after a
/// dropped connection, but not after a response timeout: a connection that went silent
/// (a network partition that drops packets rather than resetting connections) would be
/// waited on forever. So a timeout replaces the manager with a new one, in the
/// background; requests in flight finish (or time out) on the old one.
#[derive(Clone)]
pub(super) struct NodeConn(Arc<Node>);

struct Node {
    client: redis::Client,
    config: ConnectionManagerConfig,
    current: Mutex<ConnectionManager>,
    replacing: AtomicBool,
}

impl NodeConn {
    async fn open(
        client: redis::Client,
        config: ConnectionManagerConfig,
    ) -> redis::RedisResult<Self> {
        let current = client
            .get_connection_manager_with_config(config.clone())
            .await?;
        Ok(NodeConn(Arc::new(Node {
            client,
            config,
            current: Mutex::new(current),
            replacing: AtomicBool::new(false),
        })))
    }

    /// Sends with the current manager; after a timeout, starts replacing it.
    fn send<'a, T: Send + 'a>(
        &self,
        call: impl FnOnce(ConnectionManager) -> RedisFuture<'a, T>,
    ) -> RedisFuture<'a, T> {
        let this = self.clone();
        let pending = call(self.0.current.lock().clone());
        Box::pin(async move {
            let result = pending.await;
            if matches!(&result, Err(e) if e.is_timeout()) {
                this.replace();
            }
            result
        })
    }

    fn replace(&self) {
        if self.0.replacing.swap(true, Ordering::AcqRel) {
            return;
        }
        let node = self.0.clone();
        tokio::spawn(async move {
            match node
                .client
                .get_connection_manager_with_config(node.config.clone())
                .await
            {
                Ok(fresh) => {
                    *node.current.lock() = fresh;
                    tracing::warn!("replaced a Redis connection that stopped answering");
                }
                Err(e) => {
                    tracing::warn!(error = %e, "could not replace a Redis connection that stopped answering");
                }
            }
            node.replacing.store(false, Ordering::Release);
        });
    }
}

impl ConnectionLike for Conn {
    fn req_packed_command<'a>(&'a mut self, cmd: &'a Cmd) -> RedisFuture<'a, Value> {
        match self {
            Conn::Node(c) => {
                c.send(|mut m| Box::pin(async move { m.req_packed_command(cmd).await }))
            }
            Conn::Cluster(c) => c.req_packed_command(cmd),
        }
    }

    fn req_packed_commands<'a>(
        &'a mut self,
        pipeline: &'a Pipeline,
        offset: usize,
        count: usize,
    ) -> RedisFuture<'a, Vec<Value>> {
        match self {
            Conn::Node(c) => c.send(|mut m| {
                Box::pin(async move { m.req_packed_commands(pipeline, offset, count).await })
            }),
            Conn::Cluster(c) => c.req_packed_commands(pipeline, offset, count),
        }
    }

    fn get_db(&self) -> i64 {
        match self {
            Conn::Node(c) => c.0.current.lock().get_db(),
            Conn::Cluster(c) => c.get_db(),
        }
    }
}

/// Connects to the Redis of `url` (failing if it does not answer a `PING`), over TLS
/// with `tls`'s files for a `rediss://` URL: the connection, and a client per node to
/// subscribe to notifications on (one for a single server, every seed node of a
/// cluster). `what` names the store in errors.
pub(super) async fn connect(
    what: &str,
    url: &str,
    tls: &RedisTls,
) -> Result<(Conn, Vec<redis::Client>), StoreError> {
    let bad_url = |message: String| StoreError::Io {
        path: what.into(),
        message,
    };
    let target = RedisTarget::parse(url).map_err(bad_url)?;
    tls.check(target.tls()).map_err(bad_url)?;
    let certs = match target.tls() {
        true => Some(tls.certificates().map_err(|e| bad_url(e.to_string()))?),
        false => None,
    };
    let open_client = |url: &str| {
        match &certs {
            Some(c) => redis::Client::build_with_tls(url, c.clone()),
            None => redis::Client::open(url),
        }
        .map_err(|e| bad_url(format!("not a Redis URL: {e}")))
    };
    let (connect, timeout) = (Duration::from_secs(5), Duration::from_secs(10));
    let (mut conn, subscribers) = match target {
        RedisTarget::Node(url) => {
            let client = open_client(&url)?;
            let config = ConnectionManagerConfig::new()
                .set_connection_timeout(Some(connect))
                .set_response_timeout(Some(timeout))
                .set_max_delay(Duration::from_secs(2));
            let conn = NodeConn::open(client.clone(), config)
                .await
                .map_err(|e| unavailable(what, "connecting", e))?;
            (Conn::Node(conn), vec![client])
        }
        RedisTarget::Cluster(nodes) => {
            let mut builder = redis::cluster::ClusterClientBuilder::new(nodes.clone())
                .connection_timeout(connect)
                .response_timeout(timeout);
            if let Some(c) = &certs {
                builder = builder.certs(c.clone());
            }
            let conn = builder
                .build()
                .map_err(|e| bad_url(format!("not a Redis Cluster URL: {e}")))?
                .get_async_connection()
                .await
                .map_err(|e| unavailable(what, "connecting", e))?;
            let subscribers = nodes
                .iter()
                .map(|n| open_client(n))
                .collect::<Result<Vec<_>, _>>()?;
            (Conn::Cluster(conn), subscribers)
        }
    };
    let _: Value = redis::cmd("PING")
        .query_async(&mut conn)
        .await
        .map_err(|e| unavailable(what, "connecting", e))?;
    Ok((conn, subscribers))
}

/// The store's error for a failed Redis call: [`StoreError::Unavailable`] when Redis (or
/// the cluster) cannot be reached or cannot serve now, [`StoreError::Io`] otherwise.
pub(super) fn unavailable(what: &str, doing: &str, e: redis::RedisError) -> StoreError {
    let message = e.to_string();
    let down = matches!(
        e.kind(),
        redis::ErrorKind::ClusterConnectionNotFound
            | redis::ErrorKind::Server(
                redis::ServerErrorKind::ClusterDown
                    | redis::ServerErrorKind::TryAgain
                    | redis::ServerErrorKind::MasterDown
                    | redis::ServerErrorKind::BusyLoading
            )
    );
    if down
        || e.is_io_error()
        || e.is_connection_refusal()
        || e.is_timeout()
        || e.is_connection_dropped()
    {
        StoreError::Unavailable {
            what: format!("{what} ({doing})"),
            message,
        }
    } else {
        StoreError::Io {
            path: what.into(),
            message: format!("{doing}: {message}"),
        }
    }
}
