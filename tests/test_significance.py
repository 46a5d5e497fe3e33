"""The sign-flip test of a decoded message's agreement with a key: exact, valid, and the binomial test
when every bit counts alike."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.reader import significance as S


def _enumerated_tail(weights: np.ndarray, observed: int) -> float:
    signs = np.array(list(itertools.product([-1, 1], repeat=len(weights))))
    return float(((signs @ weights) >= observed).mean())


@settings(max_examples=40, deadline=None)
@given(weights=st.lists(st.integers(0, 40), min_size=1, max_size=10), data=st.data())
def test_sign_flip_tail_matches_enumeration(weights: list[int], data: st.DataObject) -> None:
    w = np.array(weights, np.int64)
    total = int(w.sum())
    observed = data.draw(st.integers(-total - 2, total + 2))
    assert S.sign_flip_tail(w, observed) == pytest.approx(_enumerated_tail(w, observed), abs=1e-15)


@settings(max_examples=25, deadline=None)
@given(bits=st.integers(1, 24), weight=st.integers(1, 50), data=st.data())
def test_equal_weights_give_the_binomial_test(bits: int, weight: int, data: st.DataObject) -> None:
    agreeing = data.draw(st.integers(0, bits))
    observed = weight * (2 * agreeing - bits)
    assert S.sign_flip_tail(np.full(bits, weight), observed) == pytest.approx(
        S.binomial_tail(agreeing, bits), rel=1e-12
    )
    # Any threshold, reachable or not, and zero weights mixed in (equal weights take a shortcut).
    small = min(bits, 10)
    w = np.concatenate([np.full(small, weight), np.zeros(data.draw(st.integers(0, 3)), np.int64)])
    any_observed = data.draw(st.integers(-weight * small - 3, weight * small + 3))
    assert S.sign_flip_tail(w, any_observed) == pytest.approx(_enumerated_tail(w, any_observed), abs=1e-15)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.01, 100.0))
def test_sign_flip_p_value_is_exact_over_random_keys(seed: int, scale: float) -> None:
    # For an unwatermarked image the logits are fixed and the key is what is random: over all 2^L keys, the
    # fraction whose p-value is ≤ α must be ≤ α (validity), whatever the logits.
    rng = np.random.default_rng(seed)
    bits = 10
    logits = rng.normal(0.0, scale, bits) * rng.uniform(0.0, 2.0, bits)
    keys = np.array(list(itertools.product([0, 1], repeat=bits)), np.uint8)
    agree = (logits > 0)[None, :] == keys.astype(bool)
    p = S.sign_flip_p_values(np.repeat(logits[None], len(keys), axis=0), agree)
    for alpha in (1 / 1024, 0.005, 0.01, 0.05, 0.2, 0.5):
        assert (p <= alpha).mean() <= alpha + 1e-12


def test_doubtful_wrong_bits_cost_less_than_confident_ones() -> None:
    # 15 of 16 bits agree: the count alone gives 17/2^16 whichever bit is wrong; weighted by confidence, a
    # wrong bit the decoder barely believed costs almost nothing, a confident one as much as the count says.
    logits = np.linspace(1.0, 4.0, 16)[None]
    weakest_wrong = np.ones((1, 16), bool)
    weakest_wrong[0, 0] = False
    strongest_wrong = np.ones((1, 16), bool)
    strongest_wrong[0, -1] = False
    p_weak = S.sign_flip_p_values(logits, weakest_wrong)[0]
    p_strong = S.sign_flip_p_values(logits, strongest_wrong)[0]
    assert p_weak == pytest.approx(2 / 2**16)  # only "all agree" and itself score as high
    assert S.binomial_tail(15, 16) == pytest.approx(17 / 2**16)
    assert p_weak < S.binomial_tail(15, 16) < p_strong
    assert S.sign_flip_p_values(logits, np.ones((1, 16), bool))[0] == pytest.approx(2.0**-16)


def test_weights_and_bad_input() -> None:
    w = S.sign_flip_weights(np.array([[0.0, -1.0, 2.0, 0.5], [0.0, 0.0, 0.0, 0.0]]))
    assert w.dtype == np.int64 and w[0].max() == S.MAX_TOTAL_WEIGHT // 4
    np.testing.assert_array_equal(w[0] * 4, [0, w[0, 2] * 2, w[0, 2] * 4, w[0, 2]])
    np.testing.assert_array_equal(w[1], 0)
    assert S.sign_flip_tail(np.zeros(5, np.int64), 0) == 1.0  # no confidence at all: no evidence
    with pytest.raises(ValueError, match="≥ 0"):
        S.sign_flip_tail(np.array([1, -1]), 0)
    with pytest.raises(ValueError, match="does not match"):
        S.sign_flip_p_values(np.zeros((2, 4)), np.zeros((2, 5), bool))
    with pytest.raises(ValueError, match="unknown identification test"):
        S.check_test("fisher")
