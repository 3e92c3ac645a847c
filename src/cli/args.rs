//! The flags of the client-side commands: `tamrm tasks`, `tamrm pool`, `tamrm completions`.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::net::parse_addr;
use crate::net::tls::HealthcheckTls;

/// The server a client-side command talks to, and how.
#[derive(Debug, Clone, Args)]
pub struct ServerArgs {
    /// The server, `host:port` (the Python client's variable).
    #[arg(long, env = "TAMRM_ADDRESS", value_name = "ADDR", value_parser = parse_addr, default_value = "127.0.0.1:50051")]
    pub server: SocketAddr,
    /// The API key, for a server with `--api-keys` (sent as `authorization: Bearer KEY`).
    #[arg(
        long,
        env = "TAMRM_API_KEY",
        value_name = "KEY",
        hide_env_values = true
    )]
    pub api_key: Option<String>,
    /// Seconds each call may take.
    #[arg(long, default_value_t = 60, value_name = "SECS")]
    pub timeout_secs: u64,
    /// TLS towards the server: on with --tls-ca (as for `tamrm healthcheck`, whose flags
    /// these are; here no server settings are read, so there is no default CA).
    #[command(flatten)]
    pub tls: HealthcheckTls,
}

/// `tamrm tasks`.
#[derive(Debug, Clone, Args)]
pub struct TasksArgs {
    /// What to show.
    #[command(subcommand)]
    pub command: TasksCommand,
}

/// `tamrm tasks list|get`.
#[derive(Debug, Clone, Subcommand)]
pub enum TasksCommand {
    /// The tasks the caller's tenant holds: id, actions, pool size and capacity, best and
    /// worst score, pool version, episodes, steps, open streams.
    List {
        /// JSON for scripts (`{"tasks": [...]}`, each task as `tamrm tasks get --json`).
        #[arg(long)]
        json: bool,
        /// The server.
        #[command(flatten)]
        server: ServerArgs,
    },
    /// One task: its resolved config and its statistics.
    Get {
        /// The task's id.
        id: String,
        /// JSON for scripts: `{"task_id", "config": {...}, "stats": {...}}`; the scores are
        /// `null` while the pool is empty.
        #[arg(long)]
        json: bool,
        /// The server.
        #[command(flatten)]
        server: ServerArgs,
    },
}

/// `tamrm pool`.
#[derive(Debug, Clone, Args)]
pub struct PoolArgs {
    /// Export or import.
    #[command(subcommand)]
    pub command: PoolCommand,
}

/// `tamrm pool export|import` (the "tamrm-pool" format of docs/storage.md).
#[derive(Debug, Clone, Subcommand)]
pub enum PoolCommand {
    /// Write a task's config and pool as a pool file (JSON Lines).
    Export {
        /// The task's id.
        id: String,
        /// The file to write (whole or not at all: a temporary file beside it, renamed
        /// over it) [default: standard output].
        #[arg(short, long, value_name = "FILE")]
        output: Option<PathBuf>,
        /// The server.
        #[command(flatten)]
        server: ServerArgs,
    },
    /// Restore a pool file into a task: created with the file's config if missing; an
    /// existing one must have the same config and an empty pool unless --replace.
    Import {
        /// The pool file (`-`: standard input). Checked whole before any call.
        file: PathBuf,
        /// The task to import into [default: the file's task_id].
        #[arg(long, value_name = "NEW_ID")]
        task: Option<String>,
        /// Delete and re-create a task of another config, or reset a non-empty pool,
        /// instead of refusing.
        #[arg(long)]
        replace: bool,
        /// The server.
        #[command(flatten)]
        server: ServerArgs,
    },
}

/// `tamrm completions SHELL`.
#[derive(Debug, Clone, Args)]
pub struct CompletionsArgs {
    /// The shell to complete for.
    #[arg(value_enum)]
    pub shell: clap_complete::Shell,
}
