//! The store's URL: the one place that knows the URL forms (settings check a URL with
//! [`RedisTarget::parse`] too), and how a URL is shown without its password.

/// Where the store's Redis is, parsed from its URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RedisTarget {
    /// `redis://[[user]:password@]host:port[/db]`: one Redis (or Valkey) server;
    /// `rediss://` the same over TLS.
    Node(String),
    /// `redis-cluster://[[user]:password@]host:port[,host:port...]`: the seed nodes of a
    /// Redis Cluster, each as a `redis://` URL with the credentials; from
    /// `rediss-cluster://`, each as a `rediss://` URL (TLS to every node).
    Cluster(Vec<String>),
}

impl RedisTarget {
    /// Parses a store URL; errors name the problem and never show a password.
    pub fn parse(url: &str) -> Result<RedisTarget, String> {
        for scheme in ["redis", "rediss"] {
            if let Some(rest) = url.strip_prefix(&format!("{scheme}://")) {
                if rest.is_empty() || rest.starts_with('/') {
                    return Err(format!(
                        "{scheme}:// needs a host: {scheme}://HOST:PORT[/DB]"
                    ));
                }
                return Ok(RedisTarget::Node(url.to_string()));
            }
        }
        let (node_scheme, rest) = match (
            url.strip_prefix("redis-cluster://"),
            url.strip_prefix("rediss-cluster://"),
        ) {
            (Some(rest), _) => ("redis", rest),
            (_, Some(rest)) => ("rediss", rest),
            _ => {
                return Err(format!(
                    "expected a redis://, rediss://, redis-cluster:// or rediss-cluster:// URL, got {:?}",
                    redact(url)
                ))
            }
        };
        let (credentials, hosts) = match rest.rfind('@') {
            Some(at) => rest.split_at(at + 1),
            None => ("", rest),
        };
        let hosts = hosts.strip_suffix('/').unwrap_or(hosts);
        if hosts.contains('/') || hosts.contains('?') {
            return Err(
                "redis-cluster:// (and rediss-cluster://) takes HOST:PORT[,HOST:PORT...] only: a Redis Cluster has database 0 only and no options here".into(),
            );
        }
        let nodes = hosts
            .split(',')
            .map(|node| {
                let port = node.rsplit_once(':').map(|(host, port)| (host, port.parse::<u16>()));
                match port {
                    Some((host, Ok(_))) if !host.is_empty() => {
                        Ok(format!("{node_scheme}://{credentials}{node}"))
                    }
                    _ => Err(format!(
                        "redis-cluster://: {node:?} is not HOST:PORT (give every seed node with its port, separated by commas)"
                    )),
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(RedisTarget::Cluster(nodes))
    }

    /// Whether the connections speak TLS (`rediss://`, `rediss-cluster://`).
    pub fn tls(&self) -> bool {
        match self {
            RedisTarget::Node(url) => url.starts_with("rediss://"),
            RedisTarget::Cluster(nodes) => nodes.iter().all(|n| n.starts_with("rediss://")),
        }
    }
}

/// `url` without its password, for logs and errors.
pub(super) fn redact(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s => format!("{}://***@{}", &url[..s], &url[at + 1..]),
        _ => url.to_string(),
    }
}
