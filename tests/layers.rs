//! The architecture's rules, checked on the source tree (docs/architecture.md):
//! - the layers point one way: core ← store ← registry ← session ← service ← server;
//!   nothing imports a layer above it, the core does no I/O and no async, and nothing but
//!   the service and the server knows of gRPC;
//! - no import circle between the crate's modules; the error type, which nearly every
//!   module uses, uses leaf modules only (modules that use nothing of the crate); nothing
//!   uses the server, only the server uses the settings, the client-side commands
//!   (`cli`) reach a server through its RPCs only, and the Python extension uses the
//!   library's public seams, not the server's internals;
//! - one source per shared fact: the `TaskConfig` fields of the proto are the core's, and
//!   every server limit is documented with its flag and environment variable.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

use prost::Message;
use tamrm::core::TaskConfig;
use tamrm::limits::Limits;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The source of a layer (a module directory or file under `src/`), test modules
/// included: tests obey the rules too, except where a rule says otherwise.
fn layer(name: &str) -> Vec<(PathBuf, String)> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    let dir = src.join(name);
    if dir.is_dir() {
        rust_files(&dir, &mut files);
    } else {
        files.push(src.join(format!("{name}.rs")));
    }
    assert!(!files.is_empty(), "no source for layer {name}");
    files
        .into_iter()
        .map(|p| {
            let text = fs::read_to_string(&p).unwrap();
            (p, text)
        })
        .collect()
}

/// Whether a line of code contains `needle`; a needle `word:NAME` only as a whole
/// identifier (so `word:Episode` is not found in the proto's `EpisodeEnds`).
fn uses(code: &str, needle: &str) -> bool {
    let Some(word) = needle.strip_prefix("word:") else {
        return code.contains(needle);
    };
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    code.match_indices(word).any(|(i, _)| {
        let before = code[..i].chars().next_back();
        let after = code[i + word.len()..].chars().next();
        !before.is_some_and(ident) && !after.is_some_and(ident)
    })
}

#[test]
fn a_word_needle_finds_only_the_whole_identifier() {
    assert!(uses("use crate::core::{Episode, Pool};", "word:Episode"));
    assert!(uses("Episode::new(space)", "word:Episode"));
    assert!(!uses("proto::EpisodeEnds { ends }", "word:Episode"));
    assert!(!uses("let MyEpisode = 1;", "word:Episode"));
    assert!(uses("proto::EpisodeEnds", "Episode"));
}

#[track_caller]
fn forbid(layer_name: &str, needles: &[&str]) {
    for (path, text) in layer(layer_name) {
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for needle in needles {
                assert!(
                    !uses(code, needle),
                    "{}:{}: the {layer_name} layer must not use `{needle}`: {line}",
                    path.display(),
                    n + 1
                );
            }
        }
    }
}

const ABOVE_STORE: [&str; 5] = [
    "crate::registry",
    "crate::session",
    "crate::service",
    "crate::server",
    "crate::settings",
];
const TRANSPORT: [&str; 3] = ["tonic", "crate::proto", "prost"];

#[test]
fn the_core_is_pure() {
    let mut forbidden: Vec<&str> = ABOVE_STORE.to_vec();
    forbidden.extend(["crate::store", "crate::limits", "crate::error"]);
    forbidden.extend(TRANSPORT);
    forbidden.extend([
        "tokio", "async ", "std::fs", "std::net", "std::io", "Mutex", "RwLock",
    ]);
    forbid("core", &forbidden);
}

#[test]
fn the_store_knows_nothing_above_it() {
    let mut forbidden: Vec<&str> = ABOVE_STORE.to_vec();
    forbidden.extend(TRANSPORT);
    forbid("store", &forbidden);
}

#[test]
fn the_registry_and_the_session_are_transport_free() {
    let mut forbidden = vec![
        "crate::service",
        "crate::server",
        "crate::settings",
        "std::fs",
    ];
    forbidden.extend(TRANSPORT);
    forbid("registry", &forbidden);
    forbid("registry", &["crate::session"]);
    forbid("session", &forbidden);
}

#[test]
fn the_service_maps_protocols_and_never_touches_files() {
    forbid(
        "service",
        &[
            "std::fs",
            "File::",
            "crate::store::",
            "crate::server",
            // The core's episodes (the proto's EpisodeEnds is protocol, not an episode).
            "word:Episode",
            "Pool::new",
        ],
    );
}

#[test]
fn the_client_commands_are_a_client_like_any_other() {
    // `tamrm tasks` and `tamrm pool` reach a server only through its RPCs.
    forbid(
        "cli",
        &[
            "crate::server",
            "crate::settings",
            "crate::registry",
            "crate::store",
            "crate::session",
            "crate::auth",
        ],
    );
}

#[test]
fn auth_decides_before_the_service_and_knows_no_episode() {
    forbid(
        "auth",
        &[
            "crate::session",
            "crate::service",
            "crate::server",
            "crate::settings",
            "crate::store",
            "std::net",
        ],
    );
}

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every source file under `src/`: its path relative to `src/`, its path and its text.
fn sources() -> Vec<(String, PathBuf, String)> {
    let mut files = Vec::new();
    rust_files(&src(), &mut files);
    files
        .into_iter()
        .map(|file| {
            let rel = file
                .strip_prefix(src())
                .unwrap()
                .to_string_lossy()
                .into_owned();
            let text = fs::read_to_string(&file).unwrap();
            (rel, file, text)
        })
        .collect()
}

/// A file's code without its comments (what follows `//` on a line; doc comments
/// included), lines kept in place.
fn code_of(text: &str) -> String {
    text.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The paths `crate::a::b::…` in `code`, as their segments (a `{` group ends a path).
fn crate_paths(code: &str) -> Vec<Vec<&str>> {
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    code.match_indices("crate::")
        .filter(|(i, _)| !code[..*i].ends_with(|c: char| ident(c) || c == '$'))
        .map(|(i, m)| {
            let rest = &code[i + m.len()..];
            let end = rest
                .find(|c: char| !(ident(c) || c == ':'))
                .unwrap_or(rest.len());
            rest[..end].split("::").filter(|s| !s.is_empty()).collect()
        })
        .collect()
}

/// The top-level modules of the crate whose sources are in `root`: every file and
/// directory there but the crate roots.
fn top_modules_in(root: &Path) -> BTreeSet<String> {
    fs::read_dir(root)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter_map(|p| {
            let name = p.file_stem()?.to_str()?.to_string();
            (p.is_dir() || p.extension().is_some_and(|e| e == "rs")).then_some(name)
        })
        .filter(|n| n != "lib" && n != "main")
        .collect()
}

/// The files of module `segments` (e.g. `["store", "error"]`), each with its depth below
/// the module (0 for the module's own file, 1 for a submodule's, ...); empty if there is
/// no such module.
fn module_files(segments: &[&str]) -> Vec<(PathBuf, usize)> {
    module_files_in(&src(), segments)
}

/// [`module_files`] of the crate whose sources are in `root`.
fn module_files_in(root: &Path, segments: &[&str]) -> Vec<(PathBuf, usize)> {
    let base = segments.iter().fold(root.to_path_buf(), |p, s| p.join(s));
    let mut files = Vec::new();
    let file = base.with_extension("rs");
    if file.is_file() {
        files.push((file, 0));
    }
    if base.is_dir() {
        let mut under = Vec::new();
        rust_files(&base, &mut under);
        for f in under {
            let rel = f.strip_prefix(&base).unwrap();
            let mut depth = rel.components().count();
            if f.file_name().is_some_and(|n| n == "mod.rs") {
                depth -= 1;
            }
            files.push((f, depth));
        }
    }
    files
}

/// The longest prefix of `path` that names a module (the module a `use` of it imports
/// from).
fn module_of<'a>(path: &[&'a str]) -> Vec<&'a str> {
    (1..=path.len())
        .rev()
        .map(|n| path[..n].to_vec())
        .find(|m| !module_files(m).is_empty())
        .unwrap_or_default()
}

/// Why module `segments` is not a leaf (a module that uses nothing of the crate outside
/// itself), `None` if it is one.
fn not_a_leaf(segments: &[&str]) -> Option<String> {
    let files = module_files(segments);
    assert!(!files.is_empty(), "no module {}", segments.join("::"));
    for (file, depth) in files {
        let code = code_of(&fs::read_to_string(&file).unwrap());
        for path in crate_paths(&code) {
            if !path.starts_with(segments) {
                return Some(format!(
                    "{} uses crate::{}",
                    file.display(),
                    path.join("::")
                ));
            }
        }
        // `super::` may climb to the module itself, not out of it.
        for (i, _) in code.match_indices("super::") {
            let supers = code.as_bytes()[i..]
                .chunks(7)
                .take_while(|c| *c == b"super::")
                .count();
            let preceded = code[..i].ends_with("super::");
            if !preceded && supers > depth {
                return Some(format!(
                    "{} climbs out of it ({} × super::)",
                    file.display(),
                    supers
                ));
            }
        }
    }
    None
}

/// The modules that use nothing of the crate; every layer may use them.
const LEAVES: [&str; 6] = ["core", "limits", "net", "quota", "task_key", "store/error"];

#[test]
fn the_leaf_modules_use_nothing_of_the_crate() {
    for leaf in LEAVES {
        let segments: Vec<&str> = leaf.split('/').collect();
        if let Some(why) = not_a_leaf(&segments) {
            panic!("{leaf} is to be a leaf module, but {why}");
        }
    }
    // The check finds a module that is not one.
    assert!(not_a_leaf(&["registry"]).is_some());
    assert!(not_a_leaf(&["store"]).is_some());
}

#[test]
fn the_error_type_uses_leaf_modules_only() {
    let code = code_of(&fs::read_to_string(src().join("error.rs")).unwrap());
    let used = crate_paths(&code);
    assert!(
        !used.is_empty(),
        "error.rs uses no module: is the check blind?"
    );
    for path in used {
        let module = module_of(&path);
        assert!(
            !module.is_empty(),
            "error.rs: crate::{} is no module's",
            path.join("::")
        );
        if let Some(why) = not_a_leaf(&module) {
            panic!(
                "error.rs uses crate::{}, and crate::{} is not a leaf module: {why}",
                path.join("::"),
                module.join("::")
            );
        }
    }
}

/// Which top-level modules each top-level module uses (tests included).
fn module_graph() -> BTreeMap<String, BTreeSet<String>> {
    module_graph_in(&src())
}

/// [`module_graph`] of the crate whose sources are in `root`.
fn module_graph_in(root: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let modules = top_modules_in(root);
    modules
        .iter()
        .map(|m| {
            let mut uses = BTreeSet::new();
            for (file, _) in module_files_in(root, &[m.as_str()]) {
                let code = code_of(&fs::read_to_string(&file).unwrap());
                for path in crate_paths(&code) {
                    if let Some(&top) = path.first() {
                        if top != m && modules.contains(top) {
                            uses.insert(top.to_string());
                        }
                    }
                }
            }
            (m.clone(), uses)
        })
        .collect()
}

/// A circle of `graph`, as the modules along it, if there is one.
fn circle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        graph: &BTreeMap<String, BTreeSet<String>>,
        node: &str,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut circle = path[at..].to_vec();
            circle.push(node.to_string());
            return Some(circle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(c) = visit(graph, next, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(node.to_string());
        None
    }
    let mut done = BTreeSet::new();
    graph
        .keys()
        .find_map(|n| visit(graph, n, &mut Vec::new(), &mut done))
}

#[test]
fn no_modules_import_each_other_in_a_circle() {
    let graph = module_graph();
    assert!(
        graph["registry"].contains("store") && graph["server"].contains("settings"),
        "the graph misses known edges: {graph:?}"
    );
    if let Some(c) = circle(&graph) {
        panic!("an import circle: {}", c.join(" → "));
    }
    // The check finds one.
    let mut with_circle = graph.clone();
    with_circle
        .get_mut("store")
        .unwrap()
        .insert("registry".to_string());
    assert!(circle(&with_circle).is_some());
}

#[test]
fn nothing_uses_the_server_and_only_the_server_uses_the_settings() {
    for (module, uses) in module_graph() {
        assert!(
            !uses.contains("server"),
            "src/{module} uses crate::server: what it needs belongs below the server (e.g. net/)"
        );
        assert!(
            module == "server" || !uses.contains("settings"),
            "src/{module} uses crate::settings: the server hands each part what it needs"
        );
    }
}

/// What the client crates (the Rust client and the Python extension built on it) may use
/// of the service: the in-process `ShapingService` and these conversions. The rest of the service, the
/// server and the settings are the server's internals.
const NATIVE_SERVICE_SEAMS: [&str; 3] = [
    "ShapingService",
    "convert::task_proto",
    "convert::config_input",
];

/// The paths a `use`-like `head::{a, b::{c, d}}` or `head::a::b` names after `head::`.
fn paths_after(code: &str, head: &str) -> Vec<String> {
    fn expand(prefix: &str, tree: &str, out: &mut Vec<String>) {
        let tree = tree.trim();
        if let Some(inner) = tree.strip_prefix('{').and_then(|t| t.strip_suffix('}')) {
            let (mut depth, mut start) = (0, 0);
            for (i, c) in inner.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(prefix, &inner[start..i], out);
                        start = i + 1;
                    }
                    _ => {}
                }
            }
            expand(prefix, &inner[start..], out);
        } else if let Some((first, rest)) = tree.split_once("::") {
            expand(&format!("{prefix}{first}::"), rest, out);
        } else if !tree.is_empty() {
            out.push(format!("{prefix}{tree}"));
        }
    }
    let mut out = Vec::new();
    for (i, m) in code.match_indices(head) {
        let rest = &code[i + m.len()..];
        let Some(rest) = rest.strip_prefix("::") else {
            out.push(String::new()); // the module itself
            continue;
        };
        let end = if rest.starts_with('{') {
            let mut depth = 0;
            rest.char_indices()
                .find(|&(_, c)| {
                    depth += match c {
                        '{' => 1,
                        '}' => -1,
                        _ => 0,
                    };
                    depth == 0
                })
                .map_or(rest.len(), |(i, _)| i + 1)
        } else {
            rest.find(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
                .unwrap_or(rest.len())
        };
        expand("", &rest[..end], &mut out);
    }
    out
}

#[test]
fn a_use_tree_is_read_path_by_path() {
    assert_eq!(
        paths_after(
            "use tamrm::service::{convert::{a, b}, ShapingService};\nx(tamrm::service::c::d(1));",
            "tamrm::service"
        ),
        ["convert::a", "convert::b", "ShapingService", "c::d"]
    );
    assert_eq!(paths_after("use tamrm::service;", "tamrm::service"), [""]);
}

#[test]
fn the_python_extension_uses_public_seams_not_the_servers_internals() {
    let mut files = Vec::new();
    for (_, root) in CLIENT_CRATES {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(root);
        let before = files.len();
        rust_files(&dir, &mut files);
        assert!(files.len() > before, "no source in {}", dir.display());
    }
    let mut seen = BTreeSet::new();
    for file in files {
        let code = code_of(&fs::read_to_string(&file).unwrap());
        for internal in ["tamrm::server", "tamrm::settings"] {
            assert!(
                !code.contains(internal),
                "{}: the extension must not use {internal} (what it needs belongs in a leaf module such as tamrm::net)",
                file.display()
            );
        }
        let mut used = paths_after(&code, "tamrm::service");
        // A module imported by name is used as `convert::item`.
        if used.iter().any(|p| p == "convert") {
            used.retain(|p| p != "convert");
            used.extend(
                paths_after(&code, "convert")
                    .into_iter()
                    .filter(|p| !p.is_empty())
                    .map(|p| format!("convert::{p}")),
            );
        }
        for path in used {
            assert!(
                NATIVE_SERVICE_SEAMS.contains(&path.as_str()),
                "{}: the extension uses tamrm::service::{path}; it may use {NATIVE_SERVICE_SEAMS:?} of the service (add a public seam, not an internal)",
                file.display()
            );
            seen.insert(path);
        }
    }
    assert!(
        seen.contains("ShapingService"),
        "the check found no use of the service: is it blind?"
    );
}

/// Each line of code (comments cut) of the crate in `root`, with where it is.
fn code_lines(root: &str) -> Vec<(String, String)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(root);
    let mut files = Vec::new();
    rust_files(&dir, &mut files);
    assert!(!files.is_empty(), "no source in {}", dir.display());
    let mut out = Vec::new();
    for file in files {
        let text = fs::read_to_string(&file).unwrap();
        for (n, line) in code_of(&text).lines().enumerate() {
            out.push((format!("{}:{}", file.display(), n + 1), line.to_string()));
        }
    }
    out
}

#[test]
fn the_client_crates_modules_do_not_import_each_other_in_a_circle() {
    for (name, root) in CLIENT_CRATES {
        let graph = module_graph_in(&Path::new(env!("CARGO_MANIFEST_DIR")).join(root));
        if let Some(c) = circle(&graph) {
            panic!("an import circle in {name}: {}", c.join(" → "));
        }
    }
    // The checks see the known edges.
    let client = module_graph_in(&Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/rust/src"));
    assert!(
        client["channel"].contains("remote") && client["channel"].contains("local"),
        "the graph misses known edges: {client:?}"
    );
    let native =
        module_graph_in(&Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/native/src"));
    assert!(
        native["channel"].contains("stream") && native["engine"].contains("stream"),
        "the graph misses known edges: {native:?}"
    );
}

/// The session and its episode state know no transport: the [`Transport`] trait is the
/// seam, so that the remote and the in-process transports depend on the session and not
/// the other way round.
#[test]
fn the_clients_session_knows_no_transport() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/rust/src");
    for module in [
        "session", "tracker", "answer", "error", "options", "runtime", "rpc",
    ] {
        for (file, _) in module_files_in(&root, &[module]) {
            let code = code_of(&fs::read_to_string(&file).unwrap());
            for path in crate_paths(&code) {
                let top = path.first().copied().unwrap_or_default();
                assert!(
                    !["remote", "local", "channel"].contains(&top),
                    "{}: {module} uses crate::{}: it must not know the transports",
                    file.display(),
                    path.join("::")
                );
            }
        }
    }
    // The remote transport knows nothing of local sessions.
    for (file, _) in module_files_in(&root, &["remote"]) {
        let code = code_of(&fs::read_to_string(&file).unwrap());
        assert!(
            !code.contains("crate::local") && !code.contains("crate::channel"),
            "{}: the remote transport must not use local sessions or the channel",
            file.display()
        );
    }
}

/// The one gRPC client of the tree is `tamrm-client`: the Python extension reaches tonic
/// only through it (`tamrm_client::tonic` for its `Code` and `Status`) and makes no client
/// of its own; the Rust client has nothing of Python.
#[test]
fn the_python_extension_leaves_grpc_to_the_client() {
    let mut seen = 0;
    for (at, line) in code_lines("clients/python/native/src") {
        for (i, _) in line.match_indices("tonic") {
            let ok = line[..i].ends_with("tamrm_client::");
            assert!(ok, "{at}: the extension uses tonic directly: {line}");
            seen += 1;
        }
        for needle in ["shaping_client", "tonic_health", "Endpoint", "ShapeRequest"] {
            assert!(
                !line.contains(needle),
                "{at}: `{needle}` is the client's: use tamrm_client ({line})"
            );
        }
    }
    assert!(
        seen > 0,
        "the check found no use of tamrm_client::tonic: is it blind?"
    );
    let manifest = fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/native/Cargo.toml"),
    )
    .unwrap();
    assert!(
        !manifest.lines().any(|l| l.starts_with("tonic")),
        "clients/python/native/Cargo.toml depends on tonic: the client crate is the one gRPC client"
    );
    for (at, line) in code_lines("clients/rust/src") {
        for needle in ["pyo3", "numpy", "Python"] {
            assert!(
                !line.contains(needle),
                "{at}: the Rust client uses {needle}: {line}"
            );
        }
    }
}

/// Where a test module declared in `file` (`mod name;`) lives: Rust's default path.
fn test_module_file(file: &Path, name: &str) -> PathBuf {
    let dir = file.parent().unwrap();
    if file
        .file_name()
        .is_some_and(|n| n == "mod.rs" || n == "lib.rs")
    {
        dir.join(format!("{name}.rs"))
    } else {
        dir.join(file.file_stem().unwrap())
            .join(format!("{name}.rs"))
    }
}

/// The one style of the crate's unit tests (CONTRIBUTING.md, "Tests in the Rust crate"):
/// `#[cfg(test)] mod tests;` at the end of the module, its body in a file of its own at
/// Rust's default path; no inline test module, no `#[path]`.
#[test]
fn unit_tests_live_in_a_file_of_their_own() {
    let mut declared = 0;
    for (rel, file, text) in sources() {
        let lines: Vec<&str> = text.lines().map(str::trim).collect();
        for (n, line) in lines.iter().enumerate() {
            let at = format!("src/{rel}:{}", n + 1);
            assert!(
                !line.starts_with("#[path"),
                "{at}: no #[path]: put the module at Rust's default path"
            );
            if *line != "#[cfg(test)]" {
                continue;
            }
            // The item the attribute gates, past any further attributes.
            let Some(item) = lines[n + 1..].iter().find(|l| !l.starts_with("#[")) else {
                continue;
            };
            let Some(decl) = item
                .strip_prefix("mod ")
                .or_else(|| item.strip_prefix("pub(crate) mod "))
            else {
                continue;
            };
            let name = decl.strip_suffix(';').unwrap_or_else(|| {
                panic!(
                    "{at}: `{item}`: move the test module into a file of its own (`mod {};`)",
                    decl.trim_end_matches([' ', '{'])
                )
            });
            assert!(
                test_module_file(&file, name).is_file(),
                "{at}: `{item}` is not at {}",
                test_module_file(&file, name).display()
            );
            declared += 1;
        }
    }
    assert!(
        declared > 20,
        "found {declared} test modules: is the check blind?"
    );
}

/// The client crates, by name and source directory: the Rust client and the Python
/// client's native extension built on it.
const CLIENT_CRATES: [(&str, &str); 2] = [
    ("tamrm-client", "clients/rust/src"),
    ("tamrm-native", "clients/python/native/src"),
];

/// How many lines a source file may have before it must say, at its top, why it is one
/// file (a line `//! Long file: <why>` within its first 40 lines): past that a file
/// usually holds several jobs, each of which reads better on its own.
const LONG_FILE: usize = 500;

#[test]
fn a_long_source_file_says_why_it_is_one_file() {
    let mut longest = 0;
    let mut all = sources();
    for (name, root) in CLIENT_CRATES {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join(root);
        let mut files = Vec::new();
        rust_files(&root, &mut files);
        assert!(
            !files.is_empty(),
            "no source of {name} in {}",
            root.display()
        );
        for file in files {
            let rel = file.strip_prefix(&root).unwrap().to_string_lossy();
            let text = fs::read_to_string(&file).unwrap();
            all.push((format!("({name}) {rel}"), file, text));
        }
    }
    for (rel, _, text) in all {
        let lines = text.lines().count();
        longest = longest.max(lines);
        if lines <= LONG_FILE {
            continue;
        }
        let reason = text.lines().take(40).find_map(|l| {
            l.trim_start()
                .strip_prefix("//! Long file:")
                .map(str::trim)
                .filter(|why| !why.is_empty())
        });
        assert!(
            reason.is_some(),
            "src/{rel} has {lines} lines (more than {LONG_FILE}): split it by job, or say why it is one file in a line `//! Long file: <why>` at its top"
        );
    }
    assert!(
        longest > 100,
        "the longest file has {longest} lines: is the check blind?"
    );
}

/// Every RPC of `tamrm.v1.Shaping` has its role in the one table (SPEC §11), and the
/// table names no RPC the proto lacks.
/// The descriptors of `proto/`, as the server embeds them.
fn descriptors() -> prost_types::FileDescriptorSet {
    prost_types::FileDescriptorSet::decode(tamrm::proto::FILE_DESCRIPTOR_SET).unwrap()
}

#[test]
fn every_rpc_has_a_role() {
    let fds = descriptors();
    let service = fds
        .file
        .iter()
        .flat_map(|f| &f.service)
        .find(|s| s.name() == "Shaping")
        .expect("Shaping in the descriptor set");
    let mut rpcs: Vec<&str> = service.method.iter().map(|m| m.name()).collect();
    let mut table: Vec<&str> = tamrm::auth::SHAPING_ROLES.iter().map(|(m, _)| *m).collect();
    rpcs.sort_unstable();
    table.sort_unstable();
    assert_eq!(rpcs, table, "add the RPC's role to auth::SHAPING_ROLES");
}

#[test]
fn task_config_fields_are_the_protos() {
    let fds = descriptors();
    let msg = fds
        .file
        .iter()
        .flat_map(|f| &f.message_type)
        .find(|m| m.name() == "TaskConfig")
        .expect("TaskConfig in the descriptor set");
    let mut fields: Vec<_> = msg.field.iter().collect();
    fields.sort_by_key(|f| f.number());
    let names: Vec<&str> = fields.iter().map(|f| f.name()).collect();
    assert_eq!(
        names,
        TaskConfig::FIELD_NAMES,
        "proto TaskConfig and core::TaskConfig differ: add the field to `task_config_fields!`"
    );
    // Every optional field of the proto is one of the list's optional fields.
    for f in &fields[2..] {
        assert!(
            f.proto3_optional(),
            "TaskConfig.{} should be proto3 optional",
            f.name()
        );
    }
}

#[test]
fn every_limit_is_documented_with_its_flag_and_variable() {
    let doc =
        fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/configuration.md"))
            .unwrap();
    for name in Limits::NAMES {
        let flag = format!("--{}", name.replace('_', "-"));
        let env = format!("TAMRM_{}", name.to_uppercase());
        for needle in [name.to_string(), flag, env] {
            assert!(
                doc.contains(&needle),
                "docs/configuration.md does not mention {needle}"
            );
        }
    }
}

#[test]
fn every_flag_of_serve_and_healthcheck_is_documented_with_its_variable() {
    use clap::CommandFactory;
    let doc =
        fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/configuration.md"))
            .unwrap();
    let cli = tamrm::settings::Cli::command();
    for sub in ["serve", "healthcheck"] {
        let command = cli.find_subcommand(sub).unwrap();
        for arg in command.get_arguments() {
            let Some(long) = arg.get_long() else { continue };
            if long == "help" || long == "version" {
                continue;
            }
            let mut needles = vec![format!("--{long}")];
            if let Some(env) = arg.get_env() {
                needles.push(env.to_string_lossy().into_owned());
            }
            for needle in needles {
                assert!(
                    doc.contains(&needle),
                    "docs/configuration.md does not mention {needle} (tamrm {sub})"
                );
            }
        }
    }
}
