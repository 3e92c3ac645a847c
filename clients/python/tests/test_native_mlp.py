"""``tamrm._native.Mlp``: the bound critic's arithmetic against a float64 reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tamrm import _native


def _reference(x: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray, str]]) -> np.ndarray:
    out = x.astype(np.float64)
    for w, b, act in layers:
        out = out @ w.astype(np.float64).T + b.astype(np.float64)
        if act == "tanh":
            out = np.tanh(out)
        elif act == "relu":
            out = np.maximum(out, 0.0)
    return out


@settings(max_examples=60, deadline=None)
@given(
    widths=st.lists(st.integers(1, 40), min_size=2, max_size=4),
    rows=st.integers(1, 9),
    acts=st.lists(st.sampled_from(["", "tanh", "relu"]), min_size=3, max_size=3),
    seed=st.integers(0, 2**32 - 1),
)
def test_equals_a_float64_reference_up_to_float32_rounding(
    widths: list[int], rows: int, acts: list[str], seed: int
) -> None:
    rng = np.random.default_rng(seed)
    layers = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(widths)):
        w = rng.normal(scale=1.0 / np.sqrt(n_in), size=(n_out, n_in)).astype(np.float32)
        b = rng.normal(scale=0.1, size=n_out).astype(np.float32)
        layers.append((w, b, acts[i]))
    x = rng.normal(size=(rows, widths[0])).astype(np.float32)
    mlp = _native.Mlp(layers)
    assert mlp.inputs == widths[0]
    got = mlp(x)
    assert got.dtype == np.float32 and got.shape == (rows, widths[-1])
    want = _reference(x, layers)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)
    # A row's output depends on that row only: the same alone as in the batch.
    np.testing.assert_array_equal(mlp(np.ascontiguousarray(x[-1:])), got[-1:])


def test_reads_the_weights_at_each_call() -> None:
    w = np.ones((3, 2), dtype=np.float32)
    b = np.zeros(3, dtype=np.float32)
    mlp = _native.Mlp([(w, b, "")])
    x = np.array([[1.0, 2.0]], dtype=np.float32)
    np.testing.assert_array_equal(mlp(x), [[3.0, 3.0, 3.0]])
    w[1] = 2.0  # updated in place, as an optimizer step updates a torch parameter
    b[2] = 0.5
    np.testing.assert_array_equal(mlp(x), [[3.0, 6.0, 3.5]])


def test_bad_layers_and_inputs_are_refused() -> None:
    w = np.ones((3, 2), dtype=np.float32)
    b = np.zeros(3, dtype=np.float32)
    with pytest.raises(ValueError, match="no layers"):
        _native.Mlp([])
    with pytest.raises(ValueError, match='unknown activation "gelu"'):
        _native.Mlp([(w, b, "gelu")])
    with pytest.raises(ValueError, match="bias of shape"):
        _native.Mlp([(w, np.zeros(2, dtype=np.float32), "")])
    with pytest.raises(ValueError, match="layer 1 takes 4 inputs, the layer before gives 3"):
        _native.Mlp(
            [(w, b, "tanh"), (np.ones((1, 4), dtype=np.float32), np.zeros(1, np.float32), "")]
        )
    with pytest.raises(ValueError, match="not C-contiguous"):
        _native.Mlp([(np.ones((2, 3), dtype=np.float32).T, b, "")])
    with pytest.raises(TypeError):
        _native.Mlp([(w.astype(np.float64), b, "")])
    mlp = _native.Mlp([(w, b, "relu")])
    with pytest.raises(ValueError, match="takes 2 inputs"):
        mlp(np.ones((4, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="C-contiguous"):
        mlp(np.ones((2, 4), dtype=np.float32)[:, ::2])
