use super::*;

fn ulps(a: f32, b: f32) -> u32 {
    let (ia, ib) = (a.to_bits() as i32, b.to_bits() as i32);
    if (ia < 0) != (ib < 0) {
        return if a == b { 0 } else { u32::MAX };
    }
    ia.abs_diff(ib)
}

#[test]
fn tanh_is_within_8_ulps_everywhere() {
    let mut worst = (0u32, 0.0f32);
    let mut x = -20.0f32;
    while x <= 20.0 {
        let want = (x as f64).tanh() as f32;
        let d = ulps(tanh(x), want);
        if d > worst.0 {
            worst = (d, x);
        }
        x += 1.0 / 4096.0;
    }
    for &x in &[
        0.0f32,
        -0.0,
        1e-30,
        -1e-30,
        3e-4,
        4e-4,
        1e-3,
        7.9,
        8.0,
        1e30,
        f32::INFINITY,
    ] {
        let want = (x as f64).tanh() as f32;
        assert!(
            ulps(tanh(x), want) <= 4 || tanh(x) == want,
            "tanh({x}) = {}, want {want}",
            tanh(x)
        );
    }
    assert!(worst.0 <= 8, "worst {} ulps at x = {}", worst.0, worst.1);
    assert!(tanh(f32::NAN).is_nan());
    assert_eq!(tanh(f32::NEG_INFINITY), -1.0);
}

/// A xorshift stream of floats uniform in [-scale, scale).
fn uniform(mut seed: u64, scale: f32) -> impl FnMut() -> f32 {
    move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        ((seed >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
    }
}

type Forward = fn(&[f32], &[f32], &[f32], usize, &mut [f32]);

/// Every multiply-add this CPU can run: `forward` with each.
fn variants() -> Vec<(&'static str, Forward)> {
    let mut v: Vec<(&'static str, Forward)> = vec![
        ("separate", forward_with::<Separate>),
        ("dispatch", forward),
    ];
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        v.push(("fused", |x, w, b, n, out| unsafe {
            forward_avx2_fma(x, w, b, n, out)
        }));
    }
    v
}

#[test]
fn forward_equals_the_definition_in_f64_up_to_rounding() {
    // Awkward sizes: a group of 8 outputs plus 3, and inputs of 8 plus a tail of 5.
    let (inputs, outputs, rows) = (13usize, 11usize, 3usize);
    let mut next = uniform(0x2545_f491_4f6c_dd1d, 1.0);
    let x: Vec<f32> = (0..rows * inputs).map(|_| next()).collect();
    let w: Vec<f32> = (0..outputs * inputs).map(|_| next()).collect();
    let b: Vec<f32> = (0..outputs).map(|_| next()).collect();
    for (name, f) in variants() {
        let mut out = vec![0.0; rows * outputs];
        f(&x, &w, &b, inputs, &mut out);
        for r in 0..rows {
            for o in 0..outputs {
                let want: f64 = b[o] as f64
                    + (0..inputs)
                        .map(|i| x[r * inputs + i] as f64 * w[o * inputs + i] as f64)
                        .sum::<f64>();
                let got = out[r * outputs + o] as f64;
                assert!(
                    (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                    "{name}: {got} vs {want}"
                );
            }
        }
        // Grouped or not, an output is the same dot product: the last output alone.
        let mut last = vec![0.0; 1];
        f(
            &x[..inputs],
            &w[(outputs - 1) * inputs..],
            &b[outputs - 1..],
            inputs,
            &mut last,
        );
        assert_eq!(last[0].to_bits(), out[outputs - 1].to_bits(), "{name}");
        // ... and the first eight, as a group of their own.
        let mut eight = vec![0.0; 8];
        f(&x[..inputs], &w[..8 * inputs], &b[..8], inputs, &mut eight);
        assert_eq!(eight, out[..8], "{name}");
        // A row's output does not depend on the other rows.
        let mut one = vec![0.0; outputs];
        f(&x[inputs..2 * inputs], &w, &b, inputs, &mut one);
        assert_eq!(one, out[outputs..2 * outputs], "{name}");
    }
}

/// The AVX2 kernel is `forward_with::<Fused>` bit for bit: the same lanes, the same
/// pairwise order, the same tail and bias, at sizes around every group boundary.
#[cfg(target_arch = "x86_64")]
#[test]
fn the_avx2_kernel_is_the_fused_definition_bit_for_bit() {
    if !(std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")) {
        return;
    }
    let mut next = uniform(0x9e37_79b9_7f4a_7c15, 2.0);
    for inputs in [1usize, 3, 4, 7, 8, 9, 15, 16, 17, 64, 67] {
        for outputs in [1usize, 7, 8, 9, 16, 17, 64] {
            let rows = 5;
            let x: Vec<f32> = (0..rows * inputs).map(|_| next()).collect();
            let w: Vec<f32> = (0..outputs * inputs).map(|_| next()).collect();
            let b: Vec<f32> = (0..outputs).map(|_| next()).collect();
            let mut want = vec![0.0; rows * outputs];
            let mut got = vec![0.0; rows * outputs];
            forward_with::<Fused>(&x, &w, &b, inputs, &mut want);
            // SAFETY: the CPU has the features (checked above).
            unsafe { forward_avx2_fma(&x, &w, &b, inputs, &mut got) };
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits(&got),
                bits(&want),
                "inputs {inputs}, outputs {outputs}"
            );
        }
    }
}

#[test]
fn tanh_of_a_layer_is_tanh_of_each_element() {
    let mut xs: Vec<f32> = (-4000..4000).map(|i| i as f32 / 397.0).collect();
    xs.extend([f32::NAN, f32::INFINITY, -0.0, 1e-5, 20.0]);
    let want: Vec<u32> = xs.iter().map(|&x| tanh(x).to_bits()).collect();
    tanh_all(&mut xs);
    let got: Vec<u32> = xs.iter().map(|x| x.to_bits()).collect();
    assert_eq!(got, want);
}

#[test]
fn relu_keeps_nan_and_zeroes_negatives() {
    let mut xs = [-1.0f32, 0.5, f32::NAN, -0.0];
    Activation::Relu.apply(&mut xs);
    assert_eq!(xs[0], 0.0);
    assert_eq!(xs[1], 0.5);
    assert!(xs[2].is_nan());
}
