use super::*;

#[test]
fn state_values() {
    let v = Values::State {
        value: 1.5,
        next_value: 2.0,
    };
    assert_eq!(potential(v, 0.9, false), 0.9 * 2.0 - 1.5);
    assert_eq!(potential(v, 0.9, true), -1.5);
    assert_eq!(potential(Values::None, 0.9, false), 0.0);
}

#[test]
fn q_values_use_the_max() {
    let v = Values::Q {
        q: &[1.0, 3.0, -2.0],
        next_q: &[0.5, -1.0, 4.0],
    };
    assert_eq!(potential(v, 0.5, false), 0.5 * 4.0 - 3.0);
    assert_eq!(potential(v, 0.5, true), -3.0);
}

#[test]
fn values_are_widened_from_f32() {
    let v = Values::State {
        value: 0.1,
        next_value: 0.0,
    };
    assert_eq!(potential(v, 1.0, false), -f64::from(0.1f32));
}
