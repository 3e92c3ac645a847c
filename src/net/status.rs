//! The text of a failed gRPC call or transport error with the causes tonic keeps in its
//! source chain, for the server's errors, `tamrm healthcheck` and the Python client.

/// An error with its sources, which is where tonic keeps the detail.
pub fn chain(e: &dyn std::error::Error) -> String {
    with_sources(e.to_string(), e.source())
}

/// A failed call's message with the causes tonic keeps in its source chain (for a
/// transport failure, such as a refused client certificate, the message alone is just
/// "transport error").
pub fn status_chain(s: &tonic::Status) -> String {
    with_sources(s.message().to_string(), std::error::Error::source(s))
}

fn with_sources(mut out: String, mut source: Option<&dyn std::error::Error>) -> String {
    while let Some(e) = source {
        let text = e.to_string();
        if !out.contains(&text) {
            out.push_str(": ");
            out.push_str(&text);
        }
        source = e.source();
    }
    out
}
