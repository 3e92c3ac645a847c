use super::*;

fn discrete(n: u32) -> TaskConfigInput {
    TaskConfigInput {
        num_actions: n,
        ..Default::default()
    }
}

#[test]
fn defaults_follow_the_spec() {
    let c = TaskConfig::resolve(&discrete(4)).unwrap();
    assert_eq!(c.pool_capacity, 20);
    assert_eq!(c.k, 20);
    assert_eq!(c.min_pool_size, 20);
    assert_eq!(c.start_step, 10);
    assert_eq!((c.alpha, c.beta, c.gamma), (0.8, 0.8, 0.99));
    assert_eq!(c.max_trajectory_len, 100_000);
    assert!(!c.gate_potential);
    assert!(!c.require_score_spread);
    let c = TaskConfig::resolve(&TaskConfigInput {
        pool_capacity: Some(7),
        ..discrete(2)
    })
    .unwrap();
    assert_eq!((c.k, c.min_pool_size), (7, 7));
    assert_eq!(TaskConfig::resolve(&c.to_input()).unwrap(), c);
}

#[test]
fn same_as_and_diff_see_every_field() {
    let base = TaskConfig::resolve(&discrete(4)).unwrap();
    let mut other = base;
    other.gate_potential = true;
    other.alpha = 0.5;
    assert!(!base.same_as(&other));
    assert_eq!(
        base.diff(&other, &other.to_input()),
        vec![
            "alpha: existing 0.8, requested 0.5".to_string(),
            "gate_potential: existing false, requested true".to_string()
        ]
    );
    let mut spread = base;
    spread.require_score_spread = true;
    assert!(!base.same_as(&spread));
    assert_eq!(
        base.diff(&spread, &TaskConfigInput::default()),
        vec![
            "require_score_spread: existing false, requested true (not sent: the default)"
                .to_string()
        ]
    );
    // -0.0 and 0.0 are different configs (bit-exact idempotency).
    let mut z = base;
    z.beta = 0.0;
    let mut nz = base;
    nz.beta = -0.0;
    assert!(!z.same_as(&nz));
    assert!(base.same_as(&TaskConfig::resolve(&base.to_input()).unwrap()));
}

/// Stored data written before a field existed (v1.1's `gate_potential`, v1.3's
/// `require_score_spread`) reads it as its default, false; data that has it keeps it.
#[test]
fn older_stored_configs_read_added_fields_as_false() {
    let c = TaskConfig::resolve(&discrete(3)).unwrap();
    for added in [
        &["gate_potential"][..],
        &["require_score_spread"],
        &["gate_potential", "require_score_spread"],
    ] {
        let mut json = serde_json::to_value(c).unwrap();
        for name in added {
            assert!(
                json.as_object_mut().unwrap().remove(*name).is_some(),
                "{name}"
            );
        }
        let back: TaskConfig = serde_json::from_value(json).unwrap();
        assert_eq!(back, c, "{added:?}");
    }
    let set = TaskConfig {
        gate_potential: true,
        require_score_spread: true,
        ..c
    };
    let back: TaskConfig = serde_json::from_value(serde_json::to_value(set).unwrap()).unwrap();
    assert_eq!(back, set);
}

#[test]
fn each_out_of_range_value_names_its_field() {
    let cases: Vec<(TaskConfigInput, &str)> = vec![
        (TaskConfigInput::default(), "num_actions"),
        (
            TaskConfigInput {
                num_actions: 2,
                action_dim: 3,
                ..Default::default()
            },
            "action_dim",
        ),
        (
            TaskConfigInput {
                pool_capacity: Some(0),
                ..discrete(2)
            },
            "pool_capacity",
        ),
        (
            TaskConfigInput {
                k: Some(0),
                ..discrete(2)
            },
            "k",
        ),
        (
            TaskConfigInput {
                pool_capacity: Some(3),
                k: Some(4),
                ..discrete(2)
            },
            "k",
        ),
        (
            TaskConfigInput {
                min_pool_size: Some(0),
                ..discrete(2)
            },
            "min_pool_size",
        ),
        (
            TaskConfigInput {
                min_pool_size: Some(21),
                ..discrete(2)
            },
            "min_pool_size",
        ),
        (
            TaskConfigInput {
                alpha: Some(f64::NAN),
                ..discrete(2)
            },
            "alpha",
        ),
        (
            TaskConfigInput {
                beta: Some(f64::INFINITY),
                ..discrete(2)
            },
            "beta",
        ),
        (
            TaskConfigInput {
                gamma: Some(1.5),
                ..discrete(2)
            },
            "gamma",
        ),
        (
            TaskConfigInput {
                gamma: Some(-0.1),
                ..discrete(2)
            },
            "gamma",
        ),
        (
            TaskConfigInput {
                gamma: Some(f64::NAN),
                ..discrete(2)
            },
            "gamma",
        ),
        (
            TaskConfigInput {
                max_trajectory_len: Some(0),
                ..discrete(2)
            },
            "max_trajectory_len",
        ),
    ];
    for (input, field) in cases {
        let err = TaskConfig::resolve(&input).unwrap_err();
        assert_eq!(err.field, field, "{input:?} -> {err}");
    }
}
