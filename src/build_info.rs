//! What this build is: reported by `tamrm --version`, the server's start log and the
//! `tamrm_build_info` metric, from one source each (the workspace's version in
//! `Cargo.toml`, the newest proto baseline, the data dir's format, the commit).

/// The version of the workspace (`[workspace.package]` in `Cargo.toml`).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The commit built (`unknown` for a build outside git without `TAMRM_COMMIT`).
pub const COMMIT: &str = env!("TAMRM_COMMIT");

/// The API version of `tamrm.v1` (the newest baseline in `proto/compat/`).
pub const PROTO: &str = env!("TAMRM_PROTO_VERSION");

/// The format a data dir is written in ([`crate::store::FORMAT_VERSION`]).
pub const DATA_DIR_FORMAT: u32 = crate::store::FORMAT_VERSION;

/// `0.1.0 (commit 0123456789ab, proto 1.3, data dir format 3)`: the text of `--version`
/// and of the start log.
pub fn describe() -> &'static str {
    static TEXT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    TEXT.get_or_init(|| {
        format!("{VERSION} (commit {COMMIT}, proto {PROTO}, data dir format {DATA_DIR_FORMAT})")
    })
}
