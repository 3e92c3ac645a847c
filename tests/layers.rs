//! The architecture's rules, checked on the source tree (docs/architecture.md):
//! - the layers point one way: core ← store ← registry ← session ← service ← server;
//!   nothing imports a layer above it, the core does no I/O and no async, and nothing but
//!   the service and the server knows of gRPC;
//! - one source per shared fact: the `TaskConfig` fields of the proto are the core's, and
//!   every server limit is documented with its flag and environment variable.

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
