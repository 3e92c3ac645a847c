//! The `tamrm` binary: `tamrm serve`, `tamrm healthcheck`, `tamrm key`, `tamrm compact`,
//! `tamrm repair`, and the client-side `tamrm tasks`, `tamrm pool` and `tamrm completions`
//! (src/cli/).

use clap::{CommandFactory, Parser};
use tamrm::settings::{Cli, Command, CompactArgs, HealthcheckArgs, KeyArgs, RepairArgs, Settings};
use tracing_subscriber::EnvFilter;

#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: tamrm::ServerAllocator = tamrm::ServerAllocator;

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let args = match cli.command {
        Command::Serve(args) => args,
        Command::Healthcheck(h) => return healthcheck(&h),
        Command::Key(k) => return key(&k),
        Command::Compact(c) => return compact(&c),
        Command::Tasks(t) => return tamrm::cli::tasks(&t),
        Command::Pool(p) => return tamrm::cli::pool(&p),
        Command::Completions(c) => return tamrm::cli::completions(&c, &mut Cli::command()),
        Command::Repair(r) => return repair(&r),
    };
    let settings = match Settings::resolve(&args) {
        Ok(s) => s,
        Err(e) => {
            tracing::error!("{e}");
            return std::process::ExitCode::from(2);
        }
    };
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = settings.worker_threads {
        builder.worker_threads(n);
    }
    let runtime = match builder.enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            tracing::error!("cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    runtime.block_on(async move {
        let server = match tamrm::server::start(&settings).await {
            Ok(s) => s,
            Err(e) => {
                tracing::error!("{e}");
                return if e.is_settings_error() {
                    std::process::ExitCode::from(2)
                } else {
                    std::process::ExitCode::FAILURE
                };
            }
        };
        wait_for_signal().await;
        tracing::info!(
            "shutting down: no new connections; open streams end after their current batch"
        );
        server.shutdown().await;
        tracing::info!("stopped");
        std::process::ExitCode::SUCCESS
    })
}

/// `tamrm healthcheck`: exit 0 when the server serves, 1 otherwise (reason on stderr).
fn healthcheck(args: &HealthcheckArgs) -> std::process::ExitCode {
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let timeout = std::time::Duration::from_secs(args.timeout_secs);
    let target = match args.resolve() {
        Ok(t) => t,
        Err(e) => {
            eprintln!("unhealthy: the server's settings: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let tls = match target.tls.client_config(&target.server_tls) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("unhealthy: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match runtime.block_on(tamrm::server::healthcheck(target.addr, tls, timeout)) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("unhealthy: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// `tamrm key`: a new random key (or the one on standard input) and its key-file entry.
fn key(args: &KeyArgs) -> std::process::ExitCode {
    if let Err(e) = tamrm::auth::check_tenant(&args.tenant) {
        eprintln!("--tenant: {e}");
        return std::process::ExitCode::from(2);
    }
    let key = if args.stdin {
        let mut s = String::new();
        if let Err(e) = std::io::Read::read_to_string(&mut std::io::stdin(), &mut s) {
            eprintln!("cannot read the key from standard input: {e}");
            return std::process::ExitCode::FAILURE;
        }
        s.trim().to_string()
    } else {
        match tamrm::auth::new_key() {
            Ok(k) => k,
            Err(e) => {
                eprintln!("cannot make a random key: {e}");
                return std::process::ExitCode::FAILURE;
            }
        }
    };
    if key.is_empty() {
        eprintln!("the key is empty");
        return std::process::ExitCode::from(2);
    }
    if !args.stdin {
        println!("# key: {key}");
        println!("# (shown once: clients send it as `authorization: Bearer <key>`, e.g. TAMRM_API_KEY; the file below keeps only its SHA-256)");
    }
    println!(
        "[[keys]]\ntenant = \"{}\"\nrole = \"{}\"\nsha256 = \"{}\"",
        args.tenant,
        args.role,
        tamrm::auth::hash_key(key.as_bytes())
    );
    std::process::ExitCode::SUCCESS
}

/// `tamrm compact`: the data dir's commit log folded into its snapshots.
fn compact(args: &CompactArgs) -> std::process::ExitCode {
    let dir = &args.data_dir;
    let done = (|| -> Result<usize, String> {
        let store = tamrm::store::DiskStore::open(dir).map_err(|e| e.to_string())?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .map_err(|e| format!("cannot start the async runtime: {e}"))?;
        runtime
            .block_on(async {
                let tasks = tamrm::store::Store::load(&store).await?.len();
                store.compact().await?;
                tamrm::store::Store::stopped(&store).await.map(|()| tasks)
            })
            .map_err(|e| e.to_string())
    })();
    match done {
        Ok(tasks) => {
            println!(
                "compacted {}: {tasks} task(s), every change in the snapshots, commits.log empty",
                dir.display()
            );
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("cannot compact {}: {e}", dir.display());
            std::process::ExitCode::FAILURE
        }
    }
}

/// `tamrm repair`: what a start of the data dir would lose and, with `--accept-loss`, the
/// log cut to what is valid. Exit 0 when the data dir starts (as it was, or repaired), 1
/// when it would not and nothing was changed, or on an error.
fn repair(args: &RepairArgs) -> std::process::ExitCode {
    let dir = &args.data_dir;
    match tamrm::store::DiskStore::repair(dir, args.accept_loss) {
        Ok(report) => {
            report.lines.iter().for_each(|l| println!("{l}"));
            match report.would_lose {
                true => std::process::ExitCode::FAILURE,
                false => std::process::ExitCode::SUCCESS,
            }
        }
        Err(e) => {
            eprintln!("cannot repair {}: {e}", dir.display());
            eprintln!("(damage in a task's files is not cut away: move that task's directory out of tasks/ to start without it)");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn wait_for_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {},
                    _ = term.recv() => {},
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
