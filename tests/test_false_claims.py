"""False claims on clean images and the calibrated threshold: ``reader.calibration`` against scipy,
``evaluation.false_claims``' sources, and ``scripts/false_claims.py`` with ``mnerf extract`` on a copy of the
tiny watermarked run (``tiny`` of conftest.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import load_script
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from mnerf_jax.evaluation import false_claims as F
from mnerf_jax.reader import calibration as C

# ---------------------------------------------------------------------------------------- the calibration


@pytest.mark.parametrize(("named", "images"), [(0, 10), (0, 10_000), (3, 200), (7, 10_000), (49, 50)])
def test_clopper_pearson_bound_is_the_beta_quantile(named: int, images: int) -> None:
    upper = C.clopper_pearson_upper(named, images)
    assert upper == pytest.approx(stats.beta.ppf(0.95, named + 1, images - named), rel=1e-9)
    # Its defining property: seeing `named` or fewer is a 5 % event at that rate.
    assert stats.binom.cdf(named, images, upper) == pytest.approx(0.05, rel=1e-6)
    assert C.clopper_pearson_upper(images, images) == 1.0
    assert C.clopper_pearson_upper(named, images, 0.99) > upper
    with pytest.raises(ValueError):
        C.clopper_pearson_upper(images + 1, images)


def _dist(seed: int, size: int) -> dict:
    """A statistic like a decoder's on clean images: discrete p-values, a few ties, undecided at 1."""
    rng = np.random.default_rng(seed)
    p = np.minimum(1.0, 16 * rng.binomial(16, 0.5, size) / 2**16 + rng.choice([0.0, 1e-4], size))
    p[rng.random(size) < 0.02] = C.NEVER_NAMED
    return C.distribution(p)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1), st.integers(1, 3000), st.lists(st.floats(1e-5, 0.5), min_size=2, max_size=6)
)
def test_the_threshold_for_a_rate_grows_with_the_rate(seed: int, size: int, rates: list[float]) -> None:
    dist = _dist(seed, size)
    entries = [C.threshold_for_rate(dist, r, fallback=1e-3) for r in sorted(rates)]
    for a, b in zip(entries, entries[1:], strict=False):
        assert a["threshold"] <= b["threshold"] and a["named"] <= b["named"]
    for e in entries:
        assert e["images"] == size and C.named_at(dist, e["threshold"]) == e["named"]
        if e["attained"]:
            assert e["rate_upper"] <= e["target_rate"]
            # The largest such threshold: the next value names more, and its bound is over the rate.
            larger = [v for v in dist["values"] if v > e["threshold"]]
            if larger:
                assert C.clopper_pearson_upper(C.named_at(dist, larger[0]), size) > e["target_rate"]
        else:  # too few images: nothing seen is named, and the threshold is no larger than the fallback
            assert e["named"] == 0 and e["threshold"] <= min(dist["values"][0], 1e-3)


def test_a_rate_that_needs_a_threshold_at_the_floor_keeps_the_fallback() -> None:
    """9 of 10,000 clean images read an exact 16-bit key (p at the floor 16 / 2^16): 0.1 % cannot be shown
    above the floor, and a threshold at it would name no image at all, so the nominal one is kept."""
    floor = 16 / 2**16
    dist = C.distribution(np.r_[np.full(9, floor), np.full(40, 0.004), np.ones(9951)])
    plain = C.threshold_for_rate(dist, 1e-3, fallback=1e-3)
    assert plain["threshold"] == floor and plain["named"] == 0 and not plain["at_floor"]
    kept = C.threshold_for_rate(dist, 1e-3, fallback=1e-3, floor=floor)
    assert kept["at_floor"] and not kept["attained"] and kept["threshold"] == 1e-3
    assert kept["named"] == C.named_at(dist, 1e-3) == 9
    assert kept["rate_upper"] == pytest.approx(C.clopper_pearson_upper(9, 10_000))
    assert "names no image" in C.describe(kept) and "nominal threshold is kept" in C.describe(kept)
    # A rate the images can show above the floor is calibrated as before.
    loose = C.threshold_for_rate(dist, 0.01, fallback=1e-3, floor=floor)
    assert loose["attained"] and not loose["at_floor"] and loose["threshold"] > floor


def test_threshold_table_and_distributions() -> None:
    dist = C.distribution([0.5, 0.1, 0.1, 0.01, 1.0, 0.5, 0.5])
    assert dist == {"values": [0.01, 0.1, 0.5, 1.0], "counts": [1, 2, 3, 1]}
    table = C.threshold_table(dist, up_to=3)
    assert [(r["named"], r["threshold"]) for r in table] == [(0, 0.01), (1, 0.1), (3, 0.5)]
    for row in table:
        assert C.named_at(dist, row["threshold"]) == row["named"] == C.named_at(dist, row["threshold"] + 0)
        assert C.threshold_for_named(dist, row["named"]) == row["threshold"]
        assert row["rate_upper"] == pytest.approx(stats.beta.ppf(0.95, row["named"] + 1, 7 - row["named"]))
    assert C.merge(dist, C.distribution([0.1, 0.2])) == {
        "values": [0.01, 0.1, 0.2, 0.5, 1.0],
        "counts": [1, 3, 1, 3, 1],
    }
    assert C.decision_statistic(np.array([0, -1, 2]), np.array([0.01, 0.001, 0.3])).tolist() == [
        0.01,
        1.0,
        0.3,
    ]
    text = C.describe(C.threshold_for_rate(_dist(0, 10_000), 1e-3))
    assert text.startswith("calibrated on 10,000 clean images:") and "at 95 %" in text


def test_quotas_and_sources() -> None:
    assert F.quotas(10_000, F.SOURCES, 50_000) == {"clean": 3334, "photos": 3333, "procedural": 3333}
    assert F.quotas(10_000, F.SOURCES, 1000) == {"clean": 1000, "photos": 4500, "procedural": 4500}
    assert F.quotas(7, ["clean"], 3) == {"clean": 3}
    with pytest.raises(F.MnerfError, match="unknown image source"):
        F.check_sources(["photos", "web"])
    rng = np.random.default_rng(0)
    photo = np.random.default_rng(1).random((50, 80, 3)).astype(np.float32)
    assert F.photo_crop(rng, photo, 24, 40).shape == (24, 40, 3)
    groups = list(F.procedural_batches(9, 20, 30, seed=0, batch=5))
    assert {g for g, _ in groups} == {"texture", "scene"}
    assert sum(len(x) for _, x in groups) == 9 and all(x.shape[1:] == (20, 30, 3) for _, x in groups)
    assert all(x.dtype == np.uint8 for _, x in groups)


# --------------------------------------------------------------------------------- the script, end to end


def test_false_claims_script_calibrates_what_extract_prints(tiny, tmp_path: Path, capsys, mnerf) -> None:
    run = tmp_path / "wm"
    shutil.copytree(tiny.wm, run, ignore=shutil.ignore_patterns("eval-*", "tb", "checkpoints"))
    image = tmp_path / "noise.png"
    import imageio.v3 as iio

    iio.imwrite(image, (np.random.default_rng(0).random((32, 32, 3)) * 255).astype(np.uint8))
    code, out, _ = mnerf("extract", "--run", run, image)
    assert code == 0 and "uncalibrated: scripts/false_claims.py" in out.splitlines()[-1]

    script = load_script("false_claims")
    argv = ["--run", str(run), "--images", "200", "--suite", "codecs", "--views", "2", "--quiet"]
    assert script.main(argv) == 0
    printed = capsys.readouterr().out
    result = json.loads((run / F.FALSE_CLAIMS_FILE).read_text())
    assert result["images"] == 200 and result["requested"] == 200 and result["size"] == [32, 32]
    # Clean renders: the source run's 2 views × (no attack + the codecs suite), the rest shared.
    clean = result["sources"]["clean"]
    assert clean["images"] == 2 * (1 + len(clean["groups"]) - 1) and "rendered from" in clean["note"]
    assert sum(s["images"] for s in result["sources"].values()) == 200
    assert (
        result["sources"]["photos"]["images"] + result["sources"]["procedural"]["images"]
        == 200 - clean["images"]
    )
    for test in ("binomial", "sign_flip"):
        assert sum(result["distribution"][test]["counts"]) == 200
        assert result["named"][test] == sum(s["named"][test] for s in result["sources"].values())
        assert result["named"][test] == C.named_at(result["distribution"][test], result["threshold"])
    # 200 images cannot show 0.1 %: said so, and nothing seen is named at the threshold kept.
    entry = result["calibration"]["binomial"]
    assert not entry["attained"] and entry["named"] == 0 and entry["threshold"] <= 1e-3
    assert "too few images" in printed and "clean" in printed

    code, out, _ = mnerf("extract", "--run", run, image)
    assert code == 0 and "calibrated on 200 clean images: 0 named, rate ≤ 1.5 % at 95 %" in out
    # Calibrated again at a looser rate, from the saved distribution: the threshold can only grow.
    assert script.main(["--run", str(run), "--recalibrate", "--rate", "0.05"]) == 0
    loose = json.loads((run / "calibration.json").read_text())["tests"]["binomial"]
    assert loose["threshold"] >= entry["threshold"] and loose["rate_upper"] <= 0.05 and loose["attained"]
    code, out, _ = mnerf("extract", "--run", run, image, "--json")
    record = json.loads(out.splitlines()[0])
    assert record["threshold"] == loose["threshold"] and record["threshold_source"] == "calibrated"
    # Read another way, the calibration does not apply; --threshold overrides it.
    code, out, _ = mnerf("extract", "--run", run, image, "--read-jitter", "1")
    assert "uncalibrated: calibration.json was measured reading with jitter 0 (now 1)" in out
    code, out, _ = mnerf("extract", "--run", run, image, "--threshold", "0.5")
    assert "threshold 0.5 (binomial test; set by --threshold, uncalibrated" in out

    # Bad input: one line, exit 2, the files as they were.
    before = (run / F.FALSE_CLAIMS_FILE).read_bytes()
    for bad in (["--sources", "web"], ["--rate", "2"], ["--images", "0"]):
        assert script.main(["--run", str(run), "--quiet", *bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("false_claims: error:") and len(err.strip().splitlines()) == 1
    assert (run / F.FALSE_CLAIMS_FILE).read_bytes() == before
