"""Attacks on the model (``watermark.model_attacks``): properties of the parameter transforms, and
``mnerf attack --model-suite`` end to end on the tiny watermarked run (``tiny`` of conftest.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.watermark import model_attacks as M


def _grid(rng: np.random.Generator, ranks: tuple[int, int, int] = (3, 4, 5), size: int = 6) -> dict:
    planes = tuple(rng.normal(size=(size, size + 1, r)).astype(np.float32) for r in ranks)
    lines = tuple(rng.normal(size=(size + 2, r)).astype(np.float32) for r in ranks)
    return {"planes": planes, "lines": lines}


def _params(seed: int = 0) -> dict:
    """A field-shaped params pytree (density, appearance, basis, MLP, the watermark module)."""
    rng = np.random.default_rng(seed)
    return {
        "density": _grid(rng),
        "appearance": _grid(rng, (2, 2, 2)),
        "basis": rng.normal(size=(6, 5)).astype(np.float32),
        "mlp": {"w0": rng.normal(size=(8, 4)).astype(np.float32), "b0": np.zeros(4, np.float32)},
        "wm": {
            "grid": _grid(rng, (1, 2, 1)),
            "mod": {"w": 100.0 * rng.normal(size=(3, 4)).astype(np.float32)},
        },
    }


def _leaves(tree: object) -> list[np.ndarray]:
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


# ------------------------------------------------------------------------------------------ quantisation


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.floats(1e-3, 1e3),
    st.floats(-10, 10),
    st.sampled_from([1, 2, 4, 8]),
)
def test_quantisation_error_is_at_most_half_a_step(seed: int, scale: float, shift: float, bits: int) -> None:
    x = (np.random.default_rng(seed).normal(size=(7, 5, 3)) * scale + shift).astype(np.float32)
    q = M.quantise_array(x, bits)
    step = (float(x.max()) - float(x.min())) / (2**bits - 1)
    assert q.dtype == x.dtype and q.shape == x.shape
    assert np.abs(q - x).max() <= step / 2 + 1e-6 * max(abs(float(x.max())), abs(float(x.min())), 1.0)
    assert len(np.unique(q)) <= 2**bits
    assert q.min() == pytest.approx(x.min(), rel=1e-6) and q.max() == pytest.approx(x.max(), rel=1e-6)


def test_eight_bits_are_closer_than_four_and_only_the_factors_are_quantised() -> None:
    params = _params()
    q8, q4 = M.quantise(params, 8), M.quantise(params, 4)
    for grid_of in (lambda p: p["density"], lambda p: p["appearance"], lambda p: p["wm"]["grid"]):
        for part in ("planes", "lines"):
            for x, a, b in zip(grid_of(params)[part], grid_of(q8)[part], grid_of(q4)[part], strict=True):
                assert np.abs(a - x).max() < np.abs(b - x).max()
                assert len(np.unique(b)) <= 16 and not np.array_equal(a, x)
    assert np.abs(q8["basis"] - params["basis"]).max() < np.abs(q4["basis"] - params["basis"]).max()
    # The MLP and FiLM stay float.
    np.testing.assert_array_equal(q4["mlp"]["w0"], params["mlp"]["w0"])
    np.testing.assert_array_equal(q4["wm"]["mod"]["w"], params["wm"]["mod"]["w"])
    # A constant tensor has nothing to round.
    np.testing.assert_array_equal(M.quantise_array(np.full((3, 2), 0.7, np.float32), 4), np.float32(0.7))
    with pytest.raises(MnerfError, match="bits"):
        M.quantise_array(params["basis"], 0)


# ----------------------------------------------------------------------------------------------- noise


def test_noise_is_scaled_to_each_leafs_std_and_seeded() -> None:
    params = _params()
    for original, same in zip(_leaves(params), _leaves(M.add_noise(params, 0.0, seed=3)), strict=True):
        np.testing.assert_array_equal(original, same)  # strength 0: the identity
    a, b, c = (M.add_noise(params, 0.1, seed=s) for s in (1, 1, 2))
    for x, y in zip(_leaves(a), _leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)  # a seed gives the same noise
    big_plane = params["density"]["planes"][2]  # 6 × 7 × 5 values: an estimate of the std within ±20 %
    for strength in (0.01, 0.1):
        noisy = M.add_noise(params, strength, seed=0)
        change = noisy["density"]["planes"][2] - big_plane
        assert change.std() == pytest.approx(strength * big_plane.std(), rel=0.2)
        # FiLM's weights are 100 × larger: so is their noise (12 values: a loose estimate).
        film = params["wm"]["mod"]["w"]
        ratio = (noisy["wm"]["mod"]["w"] - film).std() / (strength * film.std())
        assert 0.3 < ratio < 2.5
    assert not np.array_equal(_leaves(a)[0], _leaves(c)[0])
    np.testing.assert_array_equal(M.add_noise(params, 0.5)["mlp"]["b0"], 0.0)  # std 0: no noise
    with pytest.raises(MnerfError, match="≥ 0"):
        M.add_noise(params, -0.1)


# ---------------------------------------------------------------------------------------------- pruning


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 0.1, 0.3, 0.5, 1.0]))
def test_pruning_zeroes_the_smallest_components_and_keeps_the_rest(seed: int, fraction: float) -> None:
    grid = _grid(np.random.default_rng(seed))
    pruned = M.prune_grid(grid, fraction)
    norms = np.concatenate(M.component_norms(grid))
    total = norms.size
    count = int(round(fraction * total))
    dropped = np.zeros(total, bool)
    dropped[np.argsort(norms, kind="stable")[:count]] = True
    after = np.concatenate(M.component_norms(pruned))
    assert (after[dropped] == 0).all() and int((after == 0).sum()) == count
    offsets = np.cumsum([0, *(p.shape[-1] for p in grid["planes"])])
    for m in range(3):
        kept = ~dropped[offsets[m] : offsets[m + 1]]
        for part in ("planes", "lines"):
            np.testing.assert_array_equal(pruned[part][m][..., kept], grid[part][m][..., kept])
            assert (pruned[part][m][..., ~kept] == 0).all()
    if count:  # every kept component is at least as large as every dropped one
        assert norms[~dropped].min(initial=np.inf) >= norms[dropped].max()


def test_prune_reaches_every_vm_grid_and_nothing_else() -> None:
    params = _params()
    pruned = M.prune(params, 0.3)
    for name in ("density", "appearance"):
        assert (np.concatenate(M.component_norms(pruned[name])) == 0).sum() == round(
            0.3 * sum(p.shape[-1] for p in params[name]["planes"])
        )
    assert (np.concatenate(M.component_norms(pruned["wm"]["grid"])) == 0).sum() == 1  # round(0.3 × 4)
    np.testing.assert_array_equal(pruned["basis"], params["basis"])
    np.testing.assert_array_equal(pruned["mlp"]["w0"], params["mlp"]["w0"])
    for x, y in zip(_leaves(M.prune(params, 0.0)), _leaves(params), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(MnerfError, match=r"\[0, 1\]"):
        M.prune(params, 1.5)


def test_the_model_suites() -> None:
    names = [a.name for a in M.model_suite("model")]
    assert names == [
        "noise1", "noise5", "noise10", "quant8", "quant4", "prune10", "prune30",
        "finetune100", "finetune500", "finetune2000",
    ]  # fmt: skip
    assert [a.name for a in M.model_suite("finetune", [7, 3, 7])] == ["finetune3", "finetune7"]
    assert {a.family for a in M.model_suite("prune")} == {"prune"}
    with pytest.raises(MnerfError, match="unknown model suite"):
        M.model_suite("blur")
    with pytest.raises(MnerfError, match="≥ 1"):
        M.model_suite("model", [0])
    assert "finetune2000" in M.listing()


# ----------------------------------------------------------------------------------- the command, end to end


@pytest.fixture(scope="module")
def wm_copy(tiny, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the tiny watermarked run (the shared one stays as it is); its source run is tiny's."""
    run = tmp_path_factory.mktemp("model-attacks") / "wm"
    shutil.copytree(tiny.wm, run, ignore=shutil.ignore_patterns("eval-*", "tb", "*.json.tmp*"))
    return run


def test_model_suite_end_to_end(wm_copy: Path, mnerf) -> None:
    args = ("attack", "--run", wm_copy, "--model-suite", "model", "--views", "2", "--quiet")
    code, out, err = mnerf(*args, "--finetune-steps", "2,1")
    assert code == 0, err
    path = wm_copy / "eval-test-model-attacks-model.json"
    result = json.loads(path.read_text())
    assert result["model"] and result["suite"] == "model" and result["finetune_steps"] == [1, 2]
    assert result["order"] == ["none", *(a.name for a in M.model_suite("model", [1, 2]))]
    assert result["views"] == 2 and result["order"][-2:] == ["finetune1", "finetune2"]
    assert result["num_ids"] == 2 and result["bits"] == 8 and result["held_id"] == 0
    # No evaluation was saved: the clean model's renders came from the source run, once.
    assert result["false_claims_measured"] and result["clean_source"] == "rendered"
    assert result["threshold_source"] == "config"
    for name in result["order"]:
        row = result["attacks"][name]
        assert 0.0 <= row["bit_accuracy_min"] <= row["bit_accuracy_mean"] <= 1.0
        assert 0.0 <= row["verified_identification_accuracy"] <= row["identification_accuracy"] <= 1.0
        assert (
            row["false_claim_rate"] == result["attacks"]["none"]["false_claim_rate"]
        )  # one set of negatives
        assert len(row["bit_accuracy_per_id"]) == 2
    # The unattacked field reads its IDs (the tiny run's best match is right on nearly every view), and the
    # mildest attacks leave at most a bit or two of its 32 (2 IDs × 2 views × 8 bits) changed.
    rows = result["attacks"]
    assert rows["none"]["identification_accuracy"] >= 0.75
    for mild in ("quant8", "noise1"):
        assert abs(rows[mild]["bit_accuracy_mean"] - rows["none"]["bit_accuracy_mean"]) <= 2 / 32
    assert result["attacks"]["finetune2"]["family"] == "finetune"
    assert np.isfinite(result["attacks"]["finetune2"]["train_psnr"])
    lines = out.splitlines()
    assert "model suite model" in lines[0] and "false claims" in lines[0]
    assert any(line.startswith("finetune2") for line in lines) and path.with_suffix(".png").is_file()


def test_model_suite_bad_input_is_one_line_and_writes_nothing(wm_copy: Path, tiny, mnerf) -> None:
    cases = [
        (("--model-suite", "blur"), "unknown model suite"),
        (("--model-suite", "noise", "--suite", "codecs"), "drop --suite"),
        (("--model-suite", "finetune", "--finetune-steps", "0"), "≥ 1"),
        (("--model-suite", "finetune", "--finetune-id", "5"), "outside [0, 2)"),
        (("--model-suite", "noise", "--split", "nope"), "nope"),
    ]
    before = sorted(p.name for p in wm_copy.iterdir())
    for argv, needle in cases:
        code, _, err = mnerf("attack", "--run", wm_copy, "--quiet", *argv)
        assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert sorted(p.name for p in wm_copy.iterdir()) == before
    code, _, err = mnerf("attack", "--run", tiny.fit, "--model-suite", "noise", "--quiet")
    assert code == 2 and "without watermarks" in err
    code, out, _ = mnerf("attack", "--list")
    assert code == 0 and "--model-suite model" in out and "quant4" in out
