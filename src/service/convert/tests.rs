use super::*;

#[test]
fn every_task_config_field_maps_both_ways() {
    let c = TaskConfig::resolve(&TaskConfigInput {
        action_dim: 3,
        pool_capacity: Some(9),
        k: Some(2),
        start_step: Some(4),
        min_pool_size: Some(5),
        alpha: Some(0.25),
        beta: Some(-1.0),
        gamma: Some(0.5),
        max_trajectory_len: Some(77),
        gate_potential: Some(true),
        require_score_spread: Some(true),
        ..Default::default()
    })
    .unwrap();
    let p = config_proto(&c);
    assert_eq!(TaskConfig::resolve(&config_input(Some(&p))).unwrap(), c);
    assert_eq!(p.gate_potential, Some(true));
    assert_eq!(p.require_score_spread, Some(true));
    assert_eq!(config_input(None), TaskConfigInput::default());
}
