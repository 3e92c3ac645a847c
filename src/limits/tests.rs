use super::*;

#[test]
fn a_layer_overrides_only_what_it_sets() {
    let mut l = Limits::default();
    l.apply(&LimitsLayer {
        max_tasks: Some(3),
        ..Default::default()
    });
    assert_eq!(l.max_tasks, 3);
    assert_eq!(l.max_batch_entries, Limits::default().max_batch_entries);
    let file: LimitsLayer = toml::from_str("max_pool_capacity = 7").unwrap();
    l.apply(&file);
    assert_eq!((l.max_tasks, l.max_pool_capacity), (3, 7));
    assert!(toml::from_str::<LimitsLayer>("max_taks = 1").is_err());
}
