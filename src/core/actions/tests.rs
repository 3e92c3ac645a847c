use super::*;

#[test]
fn one_hot_distance_is_zero_or_two() {
    assert_eq!(delta(ActionRef::Discrete(3), ActionRef::Discrete(3)), 0.0);
    assert_eq!(delta(ActionRef::Discrete(0), ActionRef::Discrete(3)), 2.0);
}

#[test]
fn continuous_distance_is_squared_euclidean() {
    let d = delta(
        ActionRef::Continuous(&[1.0, -2.0]),
        ActionRef::Continuous(&[0.5, 1.0]),
    );
    assert_eq!(d, 0.25 + 9.0);
}

#[test]
fn one_validator_for_every_column_pair() {
    let d = ActionSpace::Discrete { num_actions: 3 };
    let c = ActionSpace::Continuous { action_dim: 2 };
    let n = ActionCount::Exactly(2, "len(rewards)");
    assert_eq!(d.check_actions(&[0, 2], &[], n), Ok(2));
    let e = d.check_actions(&[0, 3], &[], n).unwrap_err();
    assert_eq!(e.field("steps."), "steps.actions[1]");
    assert!(e.message.contains("out of range for num_actions 3"), "{e}");
    assert_eq!(
        d.check_actions(&[0], &[], n).unwrap_err().field(""),
        "actions"
    );
    assert_eq!(
        d.check_actions(&[0, 1], &[1.0], n).unwrap_err().field(""),
        "action_vectors"
    );
    assert_eq!(c.check_actions(&[], &[0.0; 4], n), Ok(2));
    assert_eq!(
        c.check_actions(&[], &[0.0, f32::NAN, 0.0, 0.0], n)
            .unwrap_err()
            .field(""),
        "action_vectors[1]"
    );
    assert_eq!(
        c.check_actions(&[1], &[0.0; 4], n).unwrap_err().field(""),
        "actions"
    );
    assert!(c
        .check_actions(&[], &[0.0; 3], ActionCount::Any)
        .unwrap_err()
        .message
        .contains("not a multiple of action_dim 2"));
    assert_eq!(c.check_actions(&[], &[], ActionCount::Any), Ok(0));
    assert!(d.to_seq(vec![], vec![], ActionCount::AtLeastOne).is_err());
    assert_eq!(
        c.to_seq(vec![], vec![1.0, 2.0], ActionCount::AtLeastOne),
        Ok(ActionSeq::Continuous {
            dim: 2,
            data: vec![1.0, 2.0]
        })
    );
}

#[test]
fn sequences_push_get_truncate() {
    let mut s = ActionSeq::empty(ActionSpace::Continuous { action_dim: 2 });
    s.push(ActionRef::Continuous(&[1.0, 2.0]));
    s.push(ActionRef::Continuous(&[3.0, 4.0]));
    assert_eq!(s.len(), 2);
    assert_eq!(s.get(1), ActionRef::Continuous(&[3.0, 4.0]));
    s.truncate(1);
    assert_eq!(s.len(), 1);
    let mut d = ActionSeq::empty(ActionSpace::Discrete { num_actions: 9 });
    d.push(ActionRef::Discrete(5));
    assert_eq!(d.get(0), ActionRef::Discrete(5));
}
