"""Identification of a watermark ID: best-matching key, p-values, decisions, confusion."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.core.config import watermark_from_flat as wm_config
from mnerf_jax.reader import identification as V
from mnerf_jax.reader import significance

# ------------------------------------------------------------------------------------------- statistics


@pytest.mark.parametrize("n", [1, 5, 8, 16])
def test_binomial_tail_matches_enumeration(n: int) -> None:
    words = np.array(list(itertools.product([0, 1], repeat=min(n, 12))))
    for k in range(n + 2):
        if n <= 12:
            expected = float((words.sum(1) >= k).mean())
        else:
            expected = sum(math.comb(n, j) for j in range(k, n + 1)) / 2**n
        assert math.isclose(significance.binomial_tail(k, n), expected, rel_tol=1e-12, abs_tol=1e-15)
    assert significance.binomial_tail(0, n) == 1.0 and significance.binomial_tail(n + 1, n) == 0.0


def test_perfect_decodes_are_identified_with_the_right_p_value() -> None:
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2, (4, 16)).astype(np.uint8)
    ident = V.identify(keys, keys, threshold=1e-3)
    np.testing.assert_array_equal(ident.best_id, [0, 1, 2, 3])
    np.testing.assert_allclose(ident.p_value, 2.0**-16)
    np.testing.assert_allclose(ident.p_corrected, 4 * 2.0**-16)
    np.testing.assert_array_equal(ident.decision, [0, 1, 2, 3])
    assert ident.min_attainable_p == pytest.approx(4 / 2**16)


def test_short_messages_cannot_pass_a_strict_threshold() -> None:
    keys = np.array([[0] * 8, [1] * 8], np.uint8)
    ident = V.identify(keys, keys, threshold=1e-3)
    np.testing.assert_array_equal(ident.best_id, [0, 1])  # the best match is still right
    np.testing.assert_array_equal(ident.decision, [-1, -1])  # but 2/256 > 1e-3: not verified
    assert ident.min_attainable_p == pytest.approx(2 / 256)


def test_ties_are_undecided() -> None:
    keys = np.array([[0, 0, 0, 0], [1, 1, 0, 0]], np.uint8)
    decoded = np.array([[1, 0, 0, 0]], np.uint8)  # one bit from each key
    ident = V.identify(decoded, keys, threshold=1.0)
    assert ident.best_id[0] == -1 and ident.decision[0] == -1


def _random_keys_and_bits(num_ids: int, bits: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``num_ids`` random keys and 5 random decoded messages, ``bits`` long (uint8)."""
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 2, (num_ids, bits)).astype(np.uint8)
    return keys, rng.integers(0, 2, (5, bits)).astype(np.uint8)


@settings(max_examples=25, deadline=None)
@given(num_ids=st.integers(1, 6), bits=st.sampled_from([8, 16, 32]), seed=st.integers(0, 10_000))
def test_best_match_maximises_agreement(num_ids: int, bits: int, seed: int) -> None:
    keys, decoded = _random_keys_and_bits(num_ids, bits, seed)
    ident = V.identify(decoded, keys)
    agree = (decoded[:, None] == keys[None]).sum(-1)
    np.testing.assert_array_equal(ident.agreement, agree.max(1))
    for row, best in zip(agree, ident.best_id, strict=True):
        if best >= 0:
            assert row[best] == row.max() and (row == row.max()).sum() == 1
    assert (ident.p_corrected >= ident.p_value).all() and (ident.p_corrected <= 1).all()


def test_false_detections_on_random_bits_stay_below_the_threshold() -> None:
    # Under the null (fair coin bits), the Bonferroni-corrected rule claims at most `threshold` of images.
    rng = np.random.default_rng(1)
    keys = rng.integers(0, 2, (8, 16)).astype(np.uint8)
    decoded = rng.integers(0, 2, (40_000, 16)).astype(np.uint8)
    ident = V.identify(decoded, keys, threshold=0.05)
    rate = V.false_detection_summary(ident)["false_detection_rate"]
    assert 0.0 < rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 40_000)
    assert abs(V.bit_accuracy(decoded, keys[0]).mean() - 0.5) < 0.01


@settings(max_examples=25, deadline=None)
@given(num_ids=st.integers(1, 6), bits=st.sampled_from([8, 16, 32]), seed=st.integers(0, 10_000))
def test_soft_identification_of_equal_logits_is_the_hard_one(num_ids: int, bits: int, seed: int) -> None:
    # Logits of equal size carry nothing beyond their signs: the soft match is the agreeing-bits match.
    keys, decoded = _random_keys_and_bits(num_ids, bits, seed)
    hard = V.identify(decoded, keys, threshold=0.05)
    soft = V.identify_logits(3.0 * (2.0 * decoded - 1.0), keys, threshold=0.05)
    for field in ("best_id", "agreement", "p_value", "decision"):
        np.testing.assert_array_equal(getattr(soft, field), getattr(hard, field))


def test_soft_identification_weighs_confident_bits() -> None:
    keys = np.array([[0, 0, 0, 0, 0, 0], [1, 1, 0, 0, 0, 0]], np.uint8)
    # Bits 1 0 0 0 0 0 agree with each key on 5 bits, a tie for hard decisions; the bit on key 1's side is
    # barely positive, the one on key 0's side confident.
    logits = np.array([[0.05, -2.0, -1.0, -1.0, -1.0, -1.0]])
    assert V.identify(V.logits_to_bits(logits), keys, threshold=1.0).best_id[0] == -1
    soft = V.identify_logits(logits, keys, threshold=1.0)
    assert soft.best_id[0] == 0 and soft.agreement[0] == 5  # judged by the chosen key's agreeing bits
    assert soft.p_value[0] == pytest.approx(significance.binomial_tail(5, 6))
    # Soft scores tie only when exactly equal (here: no information at all).
    assert V.identify_logits(np.zeros((1, 6)), keys, threshold=1.0).best_id[0] == -1
    with pytest.raises(ValueError, match="5 bits, the keys 6"):
        V.identify_logits(np.zeros((1, 5)), keys)


def test_soft_identification_is_right_more_often_on_noisy_logits() -> None:
    # Logits as noisy readings of ±1 whose reliability varies from bit to bit, as a decoder's do.
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 2, (16, 16)).astype(np.uint8)
    ids = rng.integers(0, 16, 4_000)
    scale = rng.uniform(0.2, 2.0, (4_000, 16))
    logits = scale * (2.0 * keys[ids] - 1.0) + rng.normal(0.0, 1.0, (4_000, 16))
    hard = V.identify(V.logits_to_bits(logits), keys).best_id == ids
    soft = V.identify_logits(logits, keys).best_id == ids
    assert soft.mean() > hard.mean() + 0.03


def test_soft_identification_keeps_false_detections_below_the_threshold() -> None:
    # The chosen key agrees at most as well as the best-agreeing one, so the corrected p-value still bounds
    # false claims on unwatermarked images (logits of any scale, signs fair coins).
    rng = np.random.default_rng(2)
    keys = rng.integers(0, 2, (8, 16)).astype(np.uint8)
    logits = rng.normal(0.0, 1.0, (12_000, 16)) * rng.uniform(0.1, 3.0, (12_000, 1))
    ident = V.identify_logits(logits, keys, threshold=0.05)
    rate = V.false_detection_summary(ident)["false_detection_rate"]
    assert 0.0 < rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 12_000)


def test_confusion_matrix_and_summary() -> None:
    keys = np.array([[0] * 16, [1] * 16, [0, 1] * 8], np.uint8)
    decoded = np.concatenate([keys, keys[[1]], np.array([[0, 0, 1, 1] * 4], np.uint8)])
    true = [0, 1, 2, 0, 2]
    ident = V.identify(decoded, keys, threshold=1e-2)
    summary = V.identification_summary(true, ident)
    conf = np.array(summary["confusion_best_match"])
    assert conf.shape == (3, 4) and conf.sum() == 5
    assert conf[0, 0] == 1 and conf[0, 1] == 1 and conf[1, 1] == 1 and conf[2, 2] == 1
    assert summary["identification_accuracy"] == pytest.approx(3 / 5)
    # The last decode agrees with each key on 8 of 16 bits: a tie, and no evidence of a watermark anyway.
    assert np.array(summary["confusion_decision"])[2, 3] == 1
    # The fourth render (ID 0) reads ID 1's key in full: named, but as the wrong ID.
    assert summary["misidentification_rate"] == pytest.approx(1 / 5)
    assert summary["misidentification_rate_by_test"] == {
        "binomial": pytest.approx(1 / 5),
        "sign_flip": pytest.approx(1 / 5),
    }


def test_sign_flip_decision_names_matches_wrong_only_in_doubtful_bits() -> None:
    rng = np.random.default_rng(4)
    keys = rng.integers(0, 2, (16, 16)).astype(np.uint8)
    logits = np.tile(np.linspace(1.0, 4.0, 16), (2, 1)) * (2.0 * keys[[3, 7]] - 1.0)
    logits[0, 0] *= -1  # ID 3 with its least confident bit wrong
    logits[1, -1] *= -1  # ID 7 with its most confident bit wrong
    binomial = V.identify_logits(logits, keys, threshold=1e-3)
    flip = V.identify_logits(logits, keys, threshold=1e-3, test="sign_flip")
    np.testing.assert_array_equal(binomial.best_id, [3, 7])
    np.testing.assert_array_equal(binomial.p_value, flip.p_value)  # both tests are always reported
    np.testing.assert_array_equal(binomial.decision, [-1, -1])  # 16 · 17/2^16 = 4.2e-3
    np.testing.assert_array_equal(flip.decision, [3, -1])  # 16 · 2/2^16 = 4.9e-4
    np.testing.assert_array_equal(binomial.decision_by("sign_flip"), flip.decision)
    np.testing.assert_array_equal(flip.decision_by("binomial"), binomial.decision)
    summary = V.identification_summary([3, 7], flip)
    assert summary["verified_identification_accuracy"] == 0.5 and summary["test"] == "sign_flip"
    assert summary["verified_identification_accuracy_by_test"] == {"binomial": 0.0, "sign_flip": 0.5}
    with pytest.raises(ValueError, match="unknown identification test"):
        V.identify_logits(logits, keys, test="exact")


@settings(max_examples=10, deadline=None)
@given(num_ids=st.integers(1, 6), bits=st.sampled_from([8, 16]), seed=st.integers(0, 10_000))
def test_hard_decisions_give_both_tests_the_same_p_value(num_ids: int, bits: int, seed: int) -> None:
    keys, decoded = _random_keys_and_bits(num_ids, bits, seed)
    ident = V.identify(decoded, keys, test="sign_flip")
    np.testing.assert_allclose(ident.p_value_sign_flip, ident.p_value, rtol=1e-12)


def test_sign_flip_keeps_false_detections_below_the_threshold() -> None:
    rng = np.random.default_rng(5)
    keys = rng.integers(0, 2, (8, 16)).astype(np.uint8)
    logits = rng.normal(0.0, 1.0, (6_000, 16)) * rng.uniform(0.1, 3.0, (6_000, 1))
    ident = V.identify_logits(logits, keys, threshold=0.05, test="sign_flip")
    summary = V.false_detection_summary(ident, 8)
    assert 0.0 < summary["false_detection_rate"] <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 6_000)
    assert summary["false_detection_rate_by_test"]["sign_flip"] == summary["false_detection_rate"]


def test_config_refuses_an_unknown_test() -> None:
    from mnerf_jax.core.errors import MnerfError

    wm_config(id_test="sign_flip")
    with pytest.raises(MnerfError, match="watermark.reading.id_test.*binomial, sign_flip"):
        wm_config(id_test="fisher")
