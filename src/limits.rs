//! The server's limits, each declared once: its name, type, default and documentation
//! generate [`Limits`] (the resolved values), [`LimitsLayer`] (one settings layer: the
//! config file's `[limits]` table, or the flags and environment variables of
//! `tamrm serve`) and the layering between them. Requests past a limit are answered
//! `RESOURCE_EXHAUSTED`.

use serde::{Deserialize, Serialize};

macro_rules! limits {
    ($($(#[doc = $doc:literal])* $name:ident : $ty:ty = $default:expr, env $env:literal;)*) => {
        /// Server limits (resolved).
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
        pub struct Limits {
            $($(#[doc = $doc])* pub $name: $ty,)*
        }

        impl Default for Limits {
            fn default() -> Limits {
                Limits { $($name: $default,)* }
            }
        }

        /// One layer of limit settings: every limit optional. The same struct is the
        /// config file's `[limits]` table (serde) and the flags and environment variables
        /// of `tamrm serve` (clap).
        #[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize, clap::Args)]
        #[serde(deny_unknown_fields)]
        pub struct LimitsLayer {
            $(
                $(#[doc = $doc])*
                #[arg(long, env = $env)]
                pub $name: Option<$ty>,
            )*
        }

        impl Limits {
            /// Every limit's name, for the docs test and error messages.
            pub const NAMES: &'static [&'static str] = &[$(stringify!($name)),*];

            /// Overlays the limits `layer` sets.
            pub fn apply(&mut self, layer: &LimitsLayer) {
                $(if let Some(v) = layer.$name {
                    self.$name = v;
                })*
            }
        }
    };
}

limits! {
    /// Tasks the server holds at most [default: 10000].
    max_tasks: usize = 10_000, env "TAMRM_MAX_TASKS";
    /// Environments (`num_envs`) of one Shape stream at most [default: 4096].
    max_envs_per_stream: u32 = 4_096, env "TAMRM_MAX_ENVS_PER_STREAM";
    /// Entries of one StepBatch at most [default: 65536].
    max_batch_entries: usize = 65_536, env "TAMRM_MAX_BATCH_ENTRIES";
    /// Size of one gRPC message at most, in bytes, either direction [default: 67108864].
    max_message_bytes: usize = 64 * 1024 * 1024, env "TAMRM_MAX_MESSAGE_BYTES";
    /// `pool_capacity` a task may ask for at most [default: 10000].
    max_pool_capacity: u32 = 10_000, env "TAMRM_MAX_POOL_CAPACITY";
    /// Bytes of actions one task's pool may hold at most, `pool_capacity ×
    /// max_trajectory_len × 4 × max(1, action_dim)`: CreateTask refuses a config past it
    /// [default: 4294967296].
    max_pool_bytes: u64 = 4 << 30, env "TAMRM_MAX_POOL_BYTES";
    /// Bytes one Shape stream may hold at most, `num_envs × (max_trajectory_len × 4 ×
    /// max(1, action_dim) + pool_capacity × 24)`: Open refuses a stream past it
    /// [default: 4294967296].
    max_stream_bytes: u64 = 4 << 30, env "TAMRM_MAX_STREAM_BYTES";
    /// Bytes every open Shape stream together may hold at most (the sum of their
    /// max_stream_bytes reckonings): Open refuses a stream that would pass it
    /// [default: 17179869184].
    max_total_stream_bytes: u64 = 16 << 30, env "TAMRM_MAX_TOTAL_STREAM_BYTES";
    /// Seconds a Shape stream may go without a client message (before its `Open`
    /// included) before the server ends it with UNAVAILABLE; 0 never [default: 600].
    stream_idle_timeout_secs: u64 = 600, env "TAMRM_STREAM_IDLE_TIMEOUT_SECS";
    /// Seconds between HTTP/2 keepalive pings to each client, a connection that does not
    /// answer within keepalive_timeout_secs is closed; 0 disables them [default: 30].
    keepalive_secs: u64 = 30, env "TAMRM_KEEPALIVE_SECS";
    /// Seconds a client has to answer a keepalive ping before its connection is closed
    /// (at least 1) [default: 20].
    keepalive_timeout_secs: u64 = 20, env "TAMRM_KEEPALIVE_TIMEOUT_SECS";
}

#[cfg(test)]
mod tests;
