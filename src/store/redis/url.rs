//! The store's URL: the one place that knows the URL forms (settings check a URL with
//! [`RedisTarget::parse`] too), and how a URL is shown without its password.

/// Where the store's Redis is, parsed from its URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RedisTarget {
    /// `redis://[[user]:password@]host:port[/db]`: one Redis (or Valkey) server.
    Node(String),
    /// `redis-cluster://[[user]:password@]host:port[,host:port...]`: the seed nodes of a
    /// Redis Cluster, each as a `redis://` URL with the credentials.
    Cluster(Vec<String>),
}

impl RedisTarget {
    /// Parses a store URL; errors name the problem and never show a password.
    pub fn parse(url: &str) -> Result<RedisTarget, String> {
        if url.starts_with("rediss://") || url.starts_with("rediss-cluster://") {
            return Err(
                "TLS to Redis (rediss://) is not supported by this build; use redis:// or redis-cluster:// on a private network or through a TLS tunnel (docs/scaling.md)".into(),
            );
        }
        if let Some(rest) = url.strip_prefix("redis://") {
            if rest.is_empty() || rest.starts_with('/') {
                return Err("redis:// needs a host: redis://HOST:PORT[/DB]".into());
            }
            return Ok(RedisTarget::Node(url.to_string()));
        }
        let Some(rest) = url.strip_prefix("redis-cluster://") else {
            return Err(format!(
                "expected a redis:// or redis-cluster:// URL, got {:?}",
                redact(url)
            ));
        };
        let (credentials, hosts) = match rest.rfind('@') {
            Some(at) => rest.split_at(at + 1),
            None => ("", rest),
        };
        let hosts = hosts.strip_suffix('/').unwrap_or(hosts);
        if hosts.contains('/') || hosts.contains('?') {
            return Err(
                "redis-cluster:// takes HOST:PORT[,HOST:PORT...] only: a Redis Cluster has database 0 only and no options here".into(),
            );
        }
        let nodes = hosts
            .split(',')
            .map(|node| {
                let port = node.rsplit_once(':').map(|(host, port)| (host, port.parse::<u16>()));
                match port {
                    Some((host, Ok(_))) if !host.is_empty() => {
                        Ok(format!("redis://{credentials}{node}"))
                    }
                    _ => Err(format!(
                        "redis-cluster://: {node:?} is not HOST:PORT (give every seed node with its port, separated by commas)"
                    )),
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(RedisTarget::Cluster(nodes))
    }
}

/// `url` without its password, for logs and errors.
pub(super) fn redact(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s => format!("{}://***@{}", &url[..s], &url[at + 1..]),
        _ => url.to_string(),
    }
}
