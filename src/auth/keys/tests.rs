use super::*;

const H: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

#[test]
fn a_full_file_parses() {
    let f = KeyFile::parse(&format!(
        "[[keys]]\ntenant = \"team-a\"\nrole = \"writer\"\nsha256 = \"{H}\"\nname = \"ci\"\n\
         [tenants.team-a]\nmax_tasks = 3\nmax_steps_per_second = 10\n"
    ))
    .unwrap();
    assert_eq!(f.keys.len(), 1);
    assert_eq!(f.keys[0].role, Role::Writer);
    assert_eq!(f.keys[0].digest[0], 0x9f);
    assert_eq!(f.keys[0].digest[31], 0x08);
    assert_eq!(f.quotas["team-a"].max_tasks, Some(3));
    assert_eq!(f.quotas["team-a"].max_open_streams, None);
}

#[test]
fn mistakes_are_named() {
    let key = |tenant: &str, role: &str, sha: &str| {
        format!("[[keys]]\ntenant = \"{tenant}\"\nrole = \"{role}\"\nsha256 = \"{sha}\"\n")
    };
    let err = |text: String| KeyFile::parse(&text).unwrap_err();
    assert!(err(key("a@b", "reader", H)).contains("keys[0].tenant"));
    assert!(err(key("", "reader", H)).contains("keys[0].tenant"));
    assert!(err(key("a", "root", H)).contains("role"));
    assert!(err(key("a", "reader", "abc")).contains("keys[0].sha256: expected 64"));
    assert!(err(key("a", "reader", &"zz".repeat(32))).contains("not a hex"));
    let twice = key("a", "reader", H) + &key("b", "admin", &H.to_uppercase());
    assert!(err(twice).contains("keys[1].sha256: the same key"));
    assert!(
        err(format!("{}key = \"secret\"\n", key("a", "reader", H))).contains("unknown field `key`")
    );
    assert!(err("[tenants.x]\nmax_steps_per_second = 0\n".into()).contains("must be >= 1"));
    assert!(err("[tenants.x]\nmax_task = 1\n".into()).contains("max_task"));
    assert!(KeyFile::parse("").unwrap().keys.is_empty());
}
