use proptest::prelude::*;

use super::*;
use crate::core::StepOutput;
use crate::proto::{shape_response, StepBatch};
use crate::service::convert::shaped_proto;

fn prost_answer(s: &Shaped<'_>) -> Vec<u8> {
    ShapeResponse {
        kind: Some(shape_response::Kind::Shaped(shaped_proto(s))),
    }
    .encode_to_vec()
}

fn request(batch: StepBatch) -> Vec<u8> {
    ShapeRequest {
        kind: Some(shape_request::Kind::Steps(batch)),
    }
    .encode_to_vec()
}

/// What prost decodes from `bytes`, if it is a `StepBatch` request.
fn prost_batch(bytes: &[u8]) -> Option<StepBatch> {
    match ShapeRequest::decode(bytes) {
        Ok(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(b)),
        }) => Some(b),
        _ => None,
    }
}

/// f64s with every bit pattern's kind: signed zeros, NaNs, infinities, subnormals.
fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        any::<f64>(),
        Just(-0.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        (0u64..16).prop_map(f64::from_bits),
        any::<u64>().prop_map(f64::from_bits),
    ]
}

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![any::<f32>(), any::<u32>().prop_map(f32::from_bits)]
}

fn output() -> impl Strategy<Value = StepOutput> {
    (
        any_f64(),
        any_f64(),
        any_f64(),
        prop_oneof![0u64..200, 0u64..100_000, any::<u64>()],
        any::<bool>(),
    )
        .prop_map(
            |(reward, knn_reward, potential, step, knn_active)| StepOutput {
                reward,
                knn_reward,
                potential,
                step,
                knn_active,
            },
        )
}

fn u32s() -> impl Strategy<Value = Vec<u32>> {
    prop::collection::vec(prop_oneof![0u32..4, 0u32..300, any::<u32>()], 0..40)
}

fn f32s() -> impl Strategy<Value = Vec<f32>> {
    prop::collection::vec(any_f32(), 0..40)
}

fn batch() -> impl Strategy<Value = StepBatch> {
    (
        (
            u32s(),
            u32s(),
            f32s(),
            prop::collection::vec(any_f64(), 0..40),
        ),
        (
            prop::collection::vec(any::<bool>(), 0..40),
            prop::collection::vec(any::<bool>(), 0..40),
        ),
        (f32s(), f32s(), f32s(), f32s(), u32s()),
    )
        .prop_map(
            |(
                (env_ids, actions, action_vectors, rewards),
                (terminated, truncated),
                (values, next_values, q_values, next_q_values, abandon),
            )| StepBatch {
                env_ids,
                actions,
                action_vectors,
                rewards,
                terminated,
                truncated,
                values,
                next_values,
                q_values,
                next_q_values,
                abandon,
                ..Default::default()
            },
        )
}

/// Compares NaN payloads too.
fn same(a: &StepBatch, b: &StepBatch) -> bool {
    let f64s = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    let f32s = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    a.env_ids == b.env_ids
        && a.actions == b.actions
        && f32s(&a.action_vectors) == f32s(&b.action_vectors)
        && f64s(&a.rewards) == f64s(&b.rewards)
        && a.terminated == b.terminated
        && a.truncated == b.truncated
        && f32s(&a.values) == f32s(&b.values)
        && f32s(&a.next_values) == f32s(&b.next_values)
        && f32s(&a.q_values) == f32s(&b.q_values)
        && f32s(&a.next_q_values) == f32s(&b.next_q_values)
        && a.episode_scores == b.episode_scores
        && a.abandon == b.abandon
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn answers_are_the_bytes_prost_writes(
        outputs in prop::collection::vec(output(), 0..300),
        pool_version in prop_oneof![Just(0u64), 0u64..1000, any::<u64>()],
    ) {
        let s = Shaped { outputs: &outputs, pool_version, episodes_ended: 0 };
        let mut out = BytesMut::from(&b"before"[..]);
        encode_shaped(&s, &mut out);
        prop_assert_eq!(&out[..6], b"before");
        let want = prost_answer(&s);
        prop_assert_eq!(&out[6..], want.as_slice());
    }

    #[test]
    fn packed_batches_decode_as_prost_decodes_them(b in batch()) {
        let bytes = request(b.clone());
        let fast = step_batch_request(&bytes);
        prop_assert!(fast.is_some(), "a batch of packed columns takes the fast path");
        let fast = fast.unwrap();
        prop_assert!(same(&fast, &b));
        prop_assert!(same(&fast, &prost_batch(&bytes).unwrap()));
    }

    #[test]
    fn split_columns_are_appended_as_prost_appends_them(a in batch(), b in batch()) {
        // Two encodings of a batch's fields one after the other: repeated fields are
        // concatenated.
        let body = [a.encode_to_vec(), b.encode_to_vec()].concat();
        let mut bytes = vec![2 << 3 | 2];
        prost::encoding::encode_varint(body.len() as u64, &mut bytes);
        bytes.extend_from_slice(&body);
        let fast = step_batch_request(&bytes).unwrap();
        prop_assert!(same(&fast, &prost_batch(&bytes).unwrap()));
    }

    #[test]
    fn anything_else_is_left_to_prost(
        b in batch(),
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>(), 0u8..3), 1..6),
        scores in prop::collection::btree_map(0u32..40, any_f64(), 0..3),
    ) {
        // Damaged encodings (bytes changed, inserted, dropped) and batches with scores:
        // whatever the fast path accepts, prost decodes to the same batch.
        let mut with_scores = b.clone();
        with_scores.episode_scores = scores.into_iter().collect();
        let mut bytes = request(with_scores.clone());
        for (at, byte, how) in edits {
            let i = at.index(bytes.len() + 1);
            match how {
                0 if i < bytes.len() => bytes[i] = byte,
                1 => bytes.insert(i, byte),
                _ if i < bytes.len() => { bytes.remove(i); }
                _ => {}
            }
        }
        if let Some(fast) = step_batch_request(&bytes) {
            let slow = prost_batch(&bytes);
            prop_assert!(slow.is_some(), "prost rejects what the fast path accepted");
            prop_assert!(same(&fast, &slow.unwrap()));
        }
        if !with_scores.episode_scores.is_empty() {
            prop_assert!(step_batch_request(&request(with_scores)).is_none());
        }
    }

    #[test]
    fn random_bytes_never_decode_differently(bytes in prop::collection::vec(any::<u8>(), 0..64)) {
        let mut framed = vec![2 << 3 | 2];
        prost::encoding::encode_varint(bytes.len() as u64, &mut framed);
        framed.extend_from_slice(&bytes);
        for candidate in [&bytes, &framed] {
            if let Some(fast) = step_batch_request(candidate) {
                prop_assert!(same(&fast, &prost_batch(candidate).unwrap()));
            }
        }
    }
}

#[test]
fn the_decoder_leaves_open_and_long_varints_to_prost() {
    let open = ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: "t".into(),
            num_envs: 1,
            ..Default::default()
        })),
    }
    .encode_to_vec();
    assert!(step_batch_request(&open).is_none());
    // An action as a 6-byte varint (prost reads it, truncated to u32).
    let mut body = vec![2 << 3 | 2, 6, 0x80, 0x80, 0x80, 0x80, 0x80, 0x01];
    let mut bytes = vec![2 << 3 | 2, body.len() as u8];
    bytes.append(&mut body);
    assert!(step_batch_request(&bytes).is_none());
    assert_eq!(prost_batch(&bytes).unwrap().actions, vec![0]);
    // Booleans written as other varints (2, 128), a non-minimal length and a 5-byte
    // action: read as prost reads them.
    let body = [
        5 << 3 | 2,
        3,
        2,
        0x80,
        0x01,
        2 << 3 | 2,
        0x85,
        0x00,
        0xff,
        0xff,
        0xff,
        0xff,
        0x7f,
    ];
    let mut bytes = vec![2 << 3 | 2, body.len() as u8];
    bytes.extend_from_slice(&body);
    let fast = step_batch_request(&bytes).unwrap();
    assert_eq!(fast.terminated, vec![true, true]);
    assert_eq!(fast.actions, vec![u32::MAX]);
    assert!(same(&fast, &prost_batch(&bytes).unwrap()));
    // An empty request is an empty message for prost, not a batch.
    assert!(step_batch_request(&[]).is_none());
}
