use proptest::prelude::*;

use super::*;

#[test]
fn task_keys_round_trip() {
    for (tenant, id) in [
        (DEFAULT_TENANT, "cartpole"),
        ("team-a", "maze/v1:x"),
        ("t.1_x", "a"),
    ] {
        let key = task_key(tenant, id);
        assert_eq!(split_key(&key), (tenant, id));
    }
    assert_eq!(task_key(DEFAULT_TENANT, "legacy"), "legacy");
}

proptest! {
    /// Any tenant name and task id without `@` (neither may contain one) come back from
    /// their key, so two tasks never share a key.
    #[test]
    fn every_key_names_one_task(tenant in "[^@]{1,12}", id in "[^@]{1,20}") {
        let key = task_key(&tenant, &id);
        prop_assert_eq!(split_key(&key), (tenant.as_str(), id.as_str()));
        prop_assert_eq!(key == id, tenant == DEFAULT_TENANT);
    }
}
