//! The client-side commands of the `tamrm` binary: `tamrm tasks list|get` (a table or
//! text, `--json` for scripts), `tamrm pool export|import` (the pool export format of
//! docs/storage.md, [`pool_file`]) against a running server, over the same RPCs as any
//! client. Above the service: it uses the proto's client, the config checks of the core
//! and the service's config conversions; nothing uses it but the binary and the settings'
//! command line.

pub mod args;
pub mod pool_file;
pub mod remote;
pub mod show;
pub mod transfer;

use std::io::Write;
use std::path::Path;
use std::process::ExitCode;
use std::time::Duration;

pub use args::{CompletionsArgs, PoolArgs, PoolCommand, ServerArgs, TasksArgs, TasksCommand};
use remote::{CallError, Remote, Target};

/// Exit status of a command whose input (a flag, a pool file) was refused.
const BAD_INPUT: u8 = 2;

/// What a command failed with: its message and exit status.
struct Failed(String, u8);

impl From<CallError> for Failed {
    fn from(e: CallError) -> Failed {
        Failed(e.message, 1)
    }
}

fn finish(done: Result<(), Failed>) -> ExitCode {
    match done {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failed(message, code)) => {
            eprintln!("tamrm: {message}");
            ExitCode::from(code)
        }
    }
}

fn target(args: &ServerArgs) -> Result<Target, Failed> {
    let tls = args
        .tls
        .client_config(&crate::net::tls::TlsFiles::default())
        .map_err(|e| Failed(e.to_string(), BAD_INPUT))?;
    Ok(Target {
        addr: args.server,
        tls,
        api_key: args.api_key.clone().filter(|k| !k.trim().is_empty()),
        timeout: Duration::from_secs(args.timeout_secs.max(1)),
    })
}

fn runtime() -> Result<tokio::runtime::Runtime, Failed> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| Failed(format!("cannot start the async runtime: {e}"), 1))
}

fn print(text: &str) -> Result<(), Failed> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())
        .and_then(|()| out.flush())
        .map_err(|e| Failed(format!("cannot write to standard output: {e}"), 1))
}

/// `tamrm tasks list|get`.
pub fn tasks(args: &TasksArgs) -> ExitCode {
    let server = match &args.command {
        TasksCommand::List { server, .. } | TasksCommand::Get { server, .. } => server,
    };
    finish((|| {
        let target = target(server)?;
        runtime()?.block_on(async {
            let mut remote = Remote::connect(&target).await?;
            match &args.command {
                TasksCommand::List { json, .. } => {
                    let mut tasks = Vec::new();
                    for task in remote.list_tasks().await? {
                        let config = transfer::task_config(&task)?;
                        tasks.push((task, config));
                    }
                    if *json {
                        let list: Vec<_> =
                            tasks.iter().map(|(t, c)| show::task_json(t, c)).collect();
                        print(&format!("{}\n", serde_json::json!({ "tasks": list })))
                    } else {
                        print(&show::task_table(&tasks))
                    }
                }
                TasksCommand::Get { id, json, .. } => {
                    let task = remote.get_task(id).await?;
                    let config = transfer::task_config(&task)?;
                    if *json {
                        print(&format!("{}\n", show::task_json(&task, &config)))
                    } else {
                        print(&show::task_text(&task, &config))
                    }
                }
            }
        })
    })())
}

/// Reads a pool file, `-` meaning standard input.
fn read_file(path: &Path) -> Result<pool_file::PoolFile, Failed> {
    let refused = |e: pool_file::PoolFileError| {
        Failed(
            format!("{e} (nothing was imported: the whole file is checked first)"),
            BAD_INPUT,
        )
    };
    if path.as_os_str() == "-" {
        let mut data = Vec::new();
        std::io::Read::read_to_end(&mut std::io::stdin(), &mut data)
            .map_err(|e| Failed(format!("cannot read standard input: {e}"), 1))?;
        return pool_file::read_bytes("<stdin>", &data).map_err(refused);
    }
    pool_file::read(path).map_err(|e| match e {
        pool_file::ReadError::Refused(e) => refused(e),
        e @ pool_file::ReadError::Io(..) => Failed(e.to_string(), 1),
    })
}

/// `tamrm pool export|import`.
pub fn pool(args: &PoolArgs) -> ExitCode {
    let server = match &args.command {
        PoolCommand::Export { server, .. } | PoolCommand::Import { server, .. } => server,
    };
    finish((|| {
        let target = target(server)?;
        match &args.command {
            PoolCommand::Export { id, output, .. } => runtime()?.block_on(async {
                let mut remote = Remote::connect(&target).await?;
                let (task, config, pool) = transfer::export(&mut remote, id).await?;
                match output {
                    Some(path) => {
                        let n = pool_file::write_path(path, &task.task_id, &config, &pool)
                            .map_err(|e| {
                                Failed(format!("cannot write {}: {e}", path.display()), 1)
                            })?;
                        eprintln!(
                            "exported {n} trajectories of task {:?} (pool version {}) to {}",
                            task.task_id,
                            pool.pool_version,
                            path.display()
                        );
                        Ok(())
                    }
                    None => {
                        let out = std::io::stdout().lock();
                        let mut out = std::io::BufWriter::with_capacity(1 << 20, out);
                        pool_file::write_lines(&mut out, &task.task_id, &config, &pool)
                            .map(drop)
                            .map_err(|e| Failed(format!("cannot write to standard output: {e}"), 1))
                    }
                }
            }),
            PoolCommand::Import {
                file,
                task,
                replace,
                ..
            } => {
                let data = read_file(file)?;
                let task_id = task.clone().unwrap_or_else(|| data.task_id.clone());
                runtime()?.block_on(async {
                    let mut remote = Remote::connect(&target).await?;
                    let count = data.trajectories.len();
                    let task = transfer::import(&mut remote, data, &task_id, *replace).await?;
                    let version = task.stats.map_or(0, |s| s.pool_version);
                    eprintln!(
                        "imported {count} trajectories into task {task_id:?} (pool version {version})"
                    );
                    Ok(())
                })
            }
        }
    })())
}

/// `tamrm completions SHELL`: the completion script of `command` on standard output.
pub fn completions(args: &CompletionsArgs, command: &mut clap::Command) -> ExitCode {
    let mut out = Vec::new();
    clap_complete::generate(args.shell, command, "tamrm", &mut out);
    finish(print(&String::from_utf8_lossy(&out)))
}
