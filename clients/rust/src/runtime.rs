//! The client's tokio runtime, shared by every channel of the process.

use std::sync::Mutex;

struct Runtime {
    pid: u32,
    rt: tokio::runtime::Runtime,
}

static RUNTIME: Mutex<Option<&'static Runtime>> = Mutex::new(None);

/// The client's tokio runtime (two worker threads: the channels' connections, the local
/// sessions' drivers, the disk store's blocking work). A forked child (a process-based
/// vector env started by fork) gets a runtime of its own: the parent's threads do not
/// exist in it.
pub fn runtime() -> std::io::Result<&'static tokio::runtime::Runtime> {
    let mut slot = RUNTIME.lock().unwrap_or_else(|e| e.into_inner());
    let pid = std::process::id();
    if let Some(r) = *slot {
        if r.pid == pid {
            return Ok(&r.rt);
        }
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("tamrm-client")
        .enable_all()
        .build()?;
    // Leaked on purpose: it lives as long as the process (in a forked child the parent's
    // runtime is never dropped either: its threads are not there to stop).
    let r: &'static Runtime = Box::leak(Box::new(Runtime { pid, rt }));
    *slot = Some(r);
    Ok(&r.rt)
}
