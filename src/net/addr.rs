//! The address a server listens on or a client reaches, as `host:port`.

use std::net::SocketAddr;

/// Parses `host:port`, resolving a host name (`localhost:50051`); an IPv4 address is
/// preferred when the name has several.
pub fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    use std::net::ToSocketAddrs;
    let s = s.trim();
    if let Ok(a) = s.parse() {
        return Ok(a);
    }
    if s.contains("://") {
        return Err(format!(
            "expected host:port, got {s:?} (no scheme such as http://)"
        ));
    }
    let addrs: Vec<SocketAddr> = s
        .to_socket_addrs()
        .map_err(|e| format!("expected host:port, got {s:?}: {e}"))?
        .collect();
    addrs
        .iter()
        .find(|a| a.is_ipv4())
        .or(addrs.first())
        .copied()
        .ok_or_else(|| format!("{s:?} resolves to no address"))
}
