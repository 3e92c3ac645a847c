use super::*;
use crate::core::TaskConfigInput;

fn cfg(num_actions: u32, action_dim: u32) -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions,
        action_dim,
        ..Default::default()
    })
    .unwrap()
}

fn field_of(r: Result<Entries<'_>, Error>) -> String {
    match r {
        Err(Error::InvalidArgument { field, .. }) => field,
        Err(e) => format!("other error: {e}"),
        Ok(_) => "ok".into(),
    }
}

#[test]
fn a_valid_batch_becomes_its_entries_in_order() {
    let c = cfg(3, 0);
    let b = Batch {
        env_ids: &[1, 0, 1],
        actions: &[2, 0, 1],
        rewards: &[1.0, 2.0, 3.0],
        terminated: &[false, true, false],
        q_values: &[1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
        next_q_values: &[0.0; 9],
        episode_scores: &[(1, 7.5)],
        ..Default::default()
    };
    let e = b.validate(&c, 2, &Limits::default()).unwrap();
    assert_eq!(e.len(), 3);
    assert_eq!(e[0].0, 1);
    assert_eq!(e[1].0, 0);
    assert_eq!(e[1].1.score, Some(7.5));
    assert!(e[1].1.terminated);
    assert_eq!(e[0].1.action, ActionRef::Discrete(2));
    assert!(matches!(
        e[0].1.values,
        Values::Q {
            q: &[1.0, 2.0, 3.0],
            ..
        }
    ));
    assert_eq!(e[2].1.score, None);
}

#[test]
fn each_rule_names_its_field() {
    type Edit = fn(&mut Batch<'static>);
    let d = cfg(2, 0);
    let c = cfg(0, 2);
    // Each case edits a valid two-entry batch of the discrete task (or, marked `c`,
    // of the continuous one) and names the field the answer must name.
    let cases: &[(bool, Edit, &str)] = &[
        (false, |b| b.actions = &[0, 2], "steps.actions[1]"),
        (false, |b| b.actions = &[0], "steps.actions"),
        (false, |b| b.rewards = &[0.0, f64::NAN], "steps.rewards[1]"),
        (false, |b| b.env_ids = &[0], "steps.env_ids"),
        (false, |b| b.env_ids = &[0, 5], "steps.env_ids[1]"),
        (false, |b| b.terminated = &[true], "steps.terminated"),
        (false, |b| b.values = &[0.0, 0.0], "steps.next_values"),
        (
            false,
            |b| {
                b.values = &[0.0, 0.0];
                b.next_values = &[0.0, f32::INFINITY];
            },
            "steps.next_values[1]",
        ),
        (
            false,
            |b| {
                b.values = &[0.0; 2];
                b.next_values = &[0.0; 2];
                b.q_values = &[0.0; 4];
            },
            "steps.q_values",
        ),
        (
            false,
            |b| b.episode_scores = &[(0, 1.0)],
            "steps.episode_scores[0]",
        ),
        (
            false,
            |b| {
                b.terminated = &[true, true];
                b.episode_scores = &[(2, 1.0)];
            },
            "steps.episode_scores[2]",
        ),
        (
            false,
            |b| {
                b.terminated = &[true, true];
                b.episode_scores = &[(1, f64::NAN)];
            },
            "steps.episode_scores[1]",
        ),
        (
            false,
            |b| {
                b.terminated = &[true, true];
                b.episode_scores = &[(1, 1.0), (1, 2.0)];
            },
            "steps.episode_scores[1]",
        ),
        (false, |b| b.abandon = &[2], "steps.abandon[0]"),
        (false, |b| b.abandon = &[1, 1], "steps.abandon[1]"),
        (
            false,
            |b| {
                b.actions = &[0, 0, 0];
                b.rewards = &[0.0; 3];
            },
            "steps.env_ids",
        ),
        (
            true,
            |b| b.action_vectors = &[0.0; 3],
            "steps.action_vectors",
        ),
        (
            true,
            |b| b.action_vectors = &[0.0, 0.0, f32::NAN, 0.0],
            "steps.action_vectors[2]",
        ),
        (
            true,
            |b| {
                b.q_values = &[0.0; 4];
                b.next_q_values = &[0.0; 4];
            },
            "steps.q_values",
        ),
        (true, |b| b.actions = &[0, 0], "steps.actions"),
    ];
    for (i, (continuous, edit, field)) in cases.iter().enumerate() {
        let mut b = if *continuous {
            Batch {
                action_vectors: &[0.0; 4],
                rewards: &[0.0, 0.0],
                ..Default::default()
            }
        } else {
            Batch {
                actions: &[0, 0],
                rewards: &[0.0, 0.0],
                ..Default::default()
            }
        };
        assert!(b
            .validate(if *continuous { &c } else { &d }, 2, &Limits::default())
            .is_ok());
        edit(&mut b);
        let config = if *continuous { &c } else { &d };
        assert_eq!(
            field_of(b.validate(config, 2, &Limits::default())),
            *field,
            "case {i}"
        );
    }
}

#[test]
fn limits_are_resource_exhausted() {
    let d = cfg(2, 0);
    let l = Limits {
        max_batch_entries: 1,
        ..Limits::default()
    };
    let b = Batch {
        actions: &[0, 0],
        rewards: &[0.0, 0.0],
        ..Default::default()
    };
    assert!(matches!(
        b.validate(&d, 2, &l),
        Err(Error::ResourceExhausted(m)) if m.contains("max_batch_entries")
    ));
    let l = Limits {
        max_message_bytes: 100,
        ..Limits::default()
    };
    assert!(matches!(
        b.validate(&d, 2, &l),
        Err(Error::ResourceExhausted(m)) if m.contains("max_message_bytes")
    ));
}
