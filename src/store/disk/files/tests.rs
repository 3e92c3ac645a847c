use super::*;

#[test]
fn directory_names_are_safe_and_distinct() {
    let a = dir_name("maze/v1:seed-0");
    assert!(!a.contains('/') && !a.contains(':'));
    assert_ne!(dir_name("a/b"), dir_name("a:b"));
    assert!(dir_name(&"x".repeat(128)).len() < 100);
}

#[test]
fn atomic_writes_replace_and_leave_no_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("f.json");
    let syncs = Syncs::default();
    write_atomic(&p, b"{\"a\": 1}", &syncs).unwrap();
    write_atomic(&p, b"{\"a\": 2}", &syncs).unwrap();
    assert_eq!(syncs.get(), 4, "file and directory, twice");
    let v: serde_json::Value = read_json(&p).unwrap();
    assert_eq!(v["a"], 2);
    std::fs::write(dir.path().join("x.tmp"), b"half").unwrap();
    remove_tmp_files(dir.path()).unwrap();
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 1);
    std::fs::write(&p, b"{\"a\": ").unwrap();
    let e = read_json::<serde_json::Value>(&p).unwrap_err();
    assert!(e.to_string().contains("corrupt or truncated"), "{e}");
}
