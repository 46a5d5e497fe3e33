"""Evaluation of watermarked runs: report files and a tiny real run (identification: test_identification)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import EVALUATION_KEYS, load_script

from mnerf_jax.evaluation import attacks as wm_attacks
from mnerf_jax.evaluation import plots, report
from mnerf_jax.evaluation import watermarked as V
from mnerf_jax.watermark import decision

# ---------------------------------------------------------------------------------------------- report


def _fake_eval(num_ids: int = 3, bits: int = 8) -> dict:
    per_id = [
        {
            "id": n,
            "message": "01" * (bits // 2),
            "bit_accuracy": 0.6 + 0.1 * n,
            "bit_accuracy_png": 0.55 + 0.1 * n,
            "identification_accuracy": 1.0,
            "psnr": 30.0 - n,
        }
        for n in range(num_ids)
    ]
    return {
        "split": "test",
        "views": 2,
        "num_ids": num_ids,
        "bits": bits,
        "variant": "multinerf",
        "bit_accuracy_mean": 0.7,
        "bit_accuracy_min": 0.6,
        "bit_accuracy_png_mean": 0.65,
        "psnr": 29.5,
        "psnr_clean_model": 35.25,
        "clean_psnr": 30.0,
        "ssim": 0.95,
        "lpips": 0.02,
        "identification_accuracy": 1.0,
        "verified_identification_accuracy": 0.0,
        "clean_bit_accuracy": 0.5,
        "clean_false_detection_rate": 0.0,
        "per_id": per_id,
        "identification": {"threshold": 1e-3, "min_attainable_p": num_ids / 2**bits},
    }


def test_write_report(tmp_path) -> None:
    rng = np.random.default_rng(0)
    clean = rng.uniform(size=(20, 24, 3)).astype(np.float32)
    renders = {n: np.clip(clean + 0.01 * n, 0, 1) for n in range(3)}
    paths = report.write_report(tmp_path / "rep", _fake_eval(), renders, clean)
    assert set(paths) == {"grid", "bars", "markdown"}
    text = paths["markdown"].read_text()
    assert "| PSNR vs clean model's render (dB) | 35.25 |" in text
    assert "| bit accuracy, float render (worst ID) | 60.00% |" in text
    assert "![renders](renders.png)" in text and "![bit accuracy](bit_accuracy.png)" in text
    assert "`01010101`" in text
    # An evaluation written before the wrong-ID rate was reported has no such row; a newer one has both.
    assert "wrong ID named" not in text
    rows = dict(
        report.summary_rows(
            {**_fake_eval(), "misidentification_rate_by_test": {"binomial": 0.01, "sign_flip": 0.25}}
        )
    )
    assert rows["wrong ID named (binomial p < threshold)"] == "1.00%"
    assert rows["wrong ID named (sign-flip p < threshold)"] == "25.00%"
    import imageio.v3 as iio

    grid = iio.imread(paths["grid"])
    bars = iio.imread(paths["bars"])
    assert grid.ndim == 3 and grid.shape[1] > grid.shape[0]  # one column per ID plus the clean render
    assert bars.ndim == 3


def test_per_id_table_names_the_weakest_bit() -> None:
    result = _fake_eval(num_ids=2, bits=4)
    per_bit = [1.0, 0.25, 0.5, 1.0]
    result["per_id"][0] |= {"bit_accuracy_per_bit": per_bit, "verified_identification_accuracy": 0.2}
    text = report.format_table(result)
    row0 = next(line for line in text.splitlines() if line.strip().startswith("0 "))
    assert "b1 25.0%" in row0 and "20.00%" in row0
    row1 = next(line for line in text.splitlines() if line.strip().startswith("1 "))
    assert row1.count("n/a") == 2  # an older evaluation: neither figure
    assert "| b1 25.0% |" in report.markdown(result, None, None)


def test_residual_is_amplified_and_clipped() -> None:
    a = np.zeros((2, 2, 3), np.float32)
    b = np.full((2, 2, 3), 0.03, np.float32)
    np.testing.assert_allclose(plots.residual(b, a), 0.3, atol=1e-6)
    np.testing.assert_allclose(plots.residual(b + 0.5, a), 1.0)


def test_format_table_lists_every_id() -> None:
    text = report.format_table(_fake_eval(num_ids=4, bits=16))
    lines = text.splitlines()
    assert any(line.startswith("PSNR vs ground truth (dB)") and line.endswith("29.50") for line in lines)
    assert sum(1 for line in lines if line.strip().startswith(("0 ", "1 ", "2 ", "3 "))) == 4
    missing = _fake_eval()
    missing["psnr_clean_model"] = None
    assert "n/a" in report.format_table(missing)


def test_report_of_saved_json_round_trips(tmp_path) -> None:
    # The report reads what evaluate_watermarked_run writes (plain JSON).
    result = json.loads(json.dumps(_fake_eval()))
    paths = report.write_report(tmp_path, result, {}, np.zeros((4, 4, 3)))
    assert "grid" not in paths and paths["markdown"].is_file()


# ------------------------------------------------------------------------------------- a tiny real run


@pytest.fixture(scope="session")
def tiny_eval(tiny) -> tuple[object, dict]:
    return tiny, V.evaluate_watermarked_run(tiny.wm, "test", keep_renders=True)


def test_tiny_run_identifies_its_ids(tiny_eval) -> None:
    runs, result = tiny_eval
    saved = json.loads((runs.wm / "eval-test.json").read_text())
    for key in EVALUATION_KEYS:
        assert key in saved, key
    assert saved["num_ids"] == 2 and saved["bits"] == 8 and saved["split"] == "test" and saved["views"] == 6
    # The best-matching key is the ID the view was rendered with (at most one miss in 12); bits above what
    # renders without an ID-dependent watermark can read. The 80-step run's bits move with float rounding
    # alone (its whitened random decoder leaves several logits within ±0.2 of 0, and those flip between CPU
    # kinds), the best match does not: the soft correlation of each view's logits with its own key beat the
    # other key's by 22-32. If both IDs rendered
    # alike (a failed embedding), each view would be named the same ID for both (≤ 6/12 right), and its two
    # IDs' bit accuracies would average ≤ 1 − d/(2L) for keys d bits apart: the two keys differ in ≥ d of the
    # L positions, where one read bit agrees with exactly one key.
    assert saved["identification_accuracy"] >= 11 / 12
    no_watermark_bound = 1 - saved["min_hamming"] / (2 * saved["bits"])  # 0.625 for 8 bits, 6 apart
    assert saved["bit_accuracy_mean"] > no_watermark_bound and saved["bit_accuracy_min"] >= 0.6
    assert saved["bit_accuracy_png_mean"] >= saved["bit_accuracy_mean"] - 0.1
    # Clean renders carry no watermark: by the same count their bits agree with the two keys 0.5 ± d/(2L) on
    # average (d ≥ 4: within [0.25, 0.75]), and no claim is possible at 8 bits × 2 IDs (p ≥ 2/256 > 1e-3).
    assert 0.25 <= saved["clean_bit_accuracy"] <= 0.75
    assert saved["clean_false_detection_rate"] == 0.0 and saved["clean_false_detection_ids"] == [0, 0]
    assert saved["identification"]["min_attainable_p"] == pytest.approx(2 / 256)
    # PNGs of every ID and view were written and decode like the float renders.
    assert len(list((runs.wm / "eval-test").glob("id*/*.png"))) == 2 * 6
    # The watermark costs at most a few dB against the ground truth (a random decoder needs large changes).
    assert saved["psnr"] >= saved["clean_psnr"] - 3.0
    # Per ID: each bit's share of views read right averages to the ID's bit accuracy, and the IDs' named
    # rates to the run's (every ID renders the same views).
    for row in saved["per_id"]:
        assert len(row["bit_accuracy_per_bit"]) == 8
        assert np.mean(row["bit_accuracy_per_bit"]) == pytest.approx(row["bit_accuracy"])
    named = [row["verified_identification_accuracy"] for row in saved["per_id"]]
    assert np.mean(named) == pytest.approx(saved["verified_identification_accuracy"])


def test_identify_images_reads_saved_renders(tiny_eval) -> None:
    runs, _ = tiny_eval
    paths = sorted((runs.wm / "eval-test" / "id1").glob("*.png"))
    records = V.identify_images(runs.wm, paths)
    # At most one miss, as test_tiny_run_identifies_its_ids allows.
    assert sum(r["best_id"] == 1 for r in records) >= len(paths) - 1
    assert all(0 <= r["p_value"] <= r["p_corrected"] <= 1 for r in records)


def test_identify_images_refuses_non_rgb_files(tiny_eval, tmp_path) -> None:
    import imageio.v3 as iio

    from mnerf_jax.core.errors import MnerfError

    runs, _ = tiny_eval
    gray = tmp_path / "gray.png"
    iio.imwrite(gray, np.zeros((32, 32), np.uint8))
    with pytest.raises(MnerfError, match="RGB"):
        V.identify_images(runs.wm, [gray])


def test_report_from_a_real_evaluation(tiny_eval, tmp_path) -> None:
    _, result = tiny_eval
    renders = {n: r[0] for n, r in result["_renders"].items()}
    paths = report.write_report(
        tmp_path, {k: v for k, v in result.items() if not k.startswith("_")}, renders, result["_clean"][0]
    )
    text = paths["markdown"].read_text()
    assert f"{result['bit_accuracy_mean']:.2%}" in text and paths["grid"].is_file()


# --------------------------------------------------------------------------------------------- attacks


def test_attack_scores_count_bits_and_names() -> None:
    messages = np.array([[1, 0, 1, 1, 0, 0, 1, 0], [0, 1, 1, 0, 1, 0, 0, 1]], np.float32)
    logits = np.where(messages[:, None] > 0.5, 3.0, -3.0).repeat(4, axis=1)  # [2 IDs, 4 views, 8 bits]
    logits[1, :, 0] *= -1.0  # ID 1 reads its first bit wrong on every view
    s = wm_attacks.score(logits, messages, threshold=0.5, test="binomial")
    assert s["bit_accuracy_per_id"] == pytest.approx([1.0, 7 / 8])
    assert s["bit_accuracy_mean"] == pytest.approx(15 / 16) and s["bit_accuracy_min"] == pytest.approx(7 / 8)
    assert s["identification_accuracy"] == 1.0


def test_attacks_on_the_saved_renders(tiny_eval, mnerf) -> None:
    runs, _ = tiny_eval
    saved = json.loads((runs.wm / "eval-test.json").read_text())
    result = wm_attacks.evaluate_attacks(runs.wm, "test", "high", ["box_blur", "gaussian_noise"])
    assert list(result["attacks"]) == ["none", "box_blur", "gaussian_noise"]
    assert result["views"] == saved["views"] and result["num_ids"] == 2 and result["bits"] == 8
    # No attack is the evaluation's own PNG figure (the same files, decoded again; at most one bit of 96).
    assert result["attacks"]["none"]["bit_accuracy_mean"] == pytest.approx(
        saved["bit_accuracy_png_mean"], abs=1 / 96
    )
    for s in result["attacks"].values():
        assert 0.0 <= s["bit_accuracy_min"] <= s["bit_accuracy_mean"] <= 1.0
        assert 0.0 <= s["verified_identification_accuracy"] <= s["identification_accuracy"] <= 1.0
    # The attacks' random parameters come from the seed: the same seed scores the same.
    again = wm_attacks.evaluate_attacks(runs.wm, "test", "high", ["gaussian_noise"])
    assert again["attacks"]["gaussian_noise"] == result["attacks"]["gaussian_noise"]
    assert json.loads((runs.wm / "eval-test-attacks.json").read_text())["strength"] == "high"
    # The command line: a table with one row per attack, the plot beside the JSON.
    code, out, _ = mnerf("attack", "--run", runs.wm, "--attacks", "jpeg", "--views", "2", "--quiet")
    assert code == 0 and "jpeg" in out and "mean of attacks" in out
    assert (runs.wm / "eval-test-attacks.png").is_file()
    assert json.loads((runs.wm / "eval-test-attacks.json").read_text())["views"] == 2


def test_attacks_need_an_evaluation(tiny, mnerf) -> None:
    code, _, err = mnerf("attack", "--run", tiny.wm, "--split", "val", "--quiet")
    assert code == 2 and "mnerf evaluate" in err and "eval-val.json" in err
    code, _, err = mnerf("attack", "--run", tiny.wm, "--attacks", "sepia", "--quiet")
    assert code == 2 and "sepia" in err


def test_evaluate_saves_the_clean_renders(tiny_eval) -> None:
    from mnerf_jax.data.images import round_to_8bit
    from mnerf_jax.reader import extract

    runs, result = tiny_eval
    folder = runs.wm / "eval-test" / V.CLEAN_FOLDER
    assert sorted(p.stem for p in folder.glob("*.png")) == sorted(result["view_names"])
    first = extract.load_image(folder / f"{result['view_names'][0]}.png")
    np.testing.assert_array_equal(first, round_to_8bit(result["_clean"][0]))


def test_attack_suite_peers_end_to_end(tiny_eval, mnerf) -> None:
    from mnerf_jax.imaging import attack_suites

    runs, _ = tiny_eval
    code, out, err = mnerf("attack", "--run", runs.wm, "--suite", "peers", "--views", "2", "--quiet")
    assert code == 0, err
    path = runs.wm / "eval-test-attacks-peers.json"
    result = json.loads(path.read_text())
    assert result["suite"] == "peers" and result["views"] == 2 and result["num_ids"] == 2
    assert result["order"] == ["none", *attack_suites.SUITES["peers"]]
    # False claims: the clean model's renders of the same views under the same attacks.
    assert result["false_claims_measured"]
    for name in result["order"]:
        row = result["attacks"][name]
        assert 0.0 <= row["bit_accuracy_min"] <= row["bit_accuracy_mean"] <= 1.0
        assert 0.0 <= row["verified_identification_accuracy"] <= row["identification_accuracy"] <= 1.0
        assert 0.0 <= row["false_claim_rate"] <= 1.0 and len(row["claimed_per_id"]) == 2
        assert sum(row["claimed_per_id"]) == round(row["false_claim_rate"] * 2)
    assert result["attacks"]["crop_random40"]["family"] == "geometric"
    header = out.splitlines()[0]
    assert "suite peers" in header and "false claims" in header
    assert "crop_random40+brightness2+jpeg10" in out and "mean of attacks" in out
    assert path.with_suffix(".png").is_file()


def test_claimed_keys_counts_what_attack_reports(tiny_eval, tmp_path, monkeypatch) -> None:
    # scripts/claimed_keys.py reads the clean renders as `mnerf attack` does: through the run's decoder, one
    # draw of each attack names the same renders as the attack's false claims, key by key. A loose threshold
    # (the tiny run's 8 bits and 2 keys cannot reach 1e-3) so that some are named.
    runs, _ = tiny_eval
    run = tmp_path / "wm"
    shutil.copytree(runs.wm, run, ignore=shutil.ignore_patterns("eval-test-attacks*"))
    loose = 0.3
    rule = decision.decision_rule
    monkeypatch.setattr(
        decision, "decision_rule", lambda run, reading, print_, *_: rule(run, reading, print_, loose)
    )
    attacks = ["gaussian_noise0.1", "brightness2", "jpeg10"]
    scored = wm_attacks.evaluate_attacks(run, "test", suite="peers")
    out = tmp_path / "claimed.json"
    argv = ["--run", str(run), "--attacks", ",".join(attacks), "--seeds", "1", "--threshold", str(loose)]
    assert load_script("claimed_keys").main([*argv, "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert sorted(r["attack"] for r in rows) == sorted(a for a in attacks for _ in range(3))  # suite order
    assert {r["decoder"].split(" (")[0] for r in rows} == {"run", "field end", "shipped"}
    views = scored["views"]
    for row in rows:
        assert row["reads"] == views and sum(row["named_per_key"]) == row["named"] <= views
        assert row["renders_named_more_than_once"] == 0  # one draw
        if row["decoder"] == "run":
            assert row["named_per_key"] == scored["attacks"][row["attack"]]["claimed_per_id"]
    assert any(r["named"] for r in rows if r["decoder"] == "run")
    # An attack the suite does not have: one line, exit 2.
    assert load_script("claimed_keys").main(["--run", str(run), "--attacks", "jpeg3"]) == 2


REGEN_HOOK = """
import numpy as np
def mirror(images):
    assert images.dtype == np.uint8 and images.ndim == 4
    return images[:, :, ::-1].copy()
def floats(images):
    return images / 255.0
"""


def test_attack_regen_hook_without_clean_renders_loses_nothing(tiny_eval, mnerf, tmp_path) -> None:
    runs, _ = tiny_eval
    run = tmp_path / "wm"
    shutil.copytree(runs.wm, run, ignore=shutil.ignore_patterns("checkpoints", "tb", "eval-test-attacks*"))
    shutil.rmtree(run / "eval-test" / V.CLEAN_FOLDER)  # as an evaluation written before they were saved
    hook = tmp_path / "hook.py"
    hook.write_text(REGEN_HOOK)
    args = ("attack", "--run", run, "--attacks", "jpeg90", "--views", "2", "--quiet")
    code, out, err = mnerf(*args, "--regen", f"{hook}:mirror")
    assert code == 0, err
    path = run / "eval-test-attacks.json"
    result = json.loads(path.read_text())
    assert result["order"] == ["none", "jpeg90", "regen:hook.py:mirror"]
    assert not result["false_claims_measured"] and "false_claim_rate" not in result["attacks"]["jpeg90"]
    assert "false claims" not in out.splitlines()[0]
    assert sum("false claims left out" in line for line in out.splitlines()) == 1
    # A hook that returns floats is refused in one line, and the scores already written stay as they were.
    before = path.read_bytes()
    code, _, err = mnerf(*args, "--regen", f"{hook}:floats")
    assert code == 2 and "uint8" in err and len(err.strip().splitlines()) == 1
    assert path.read_bytes() == before
    code, _, err = mnerf(*args, "--suite", "peers")
    assert code == 2 and "give one" in err


def test_attack_codec_model_row_from_a_torch_weights_file(tiny_eval, mnerf, tmp_path) -> None:
    from test_compression_models import random_factorized, save_state_dict

    runs, _ = tiny_eval
    run = tmp_path / "wm"
    shutil.copytree(runs.wm, run, ignore=shutil.ignore_patterns("checkpoints", "tb", "eval-test-attacks*"))
    weights = save_state_dict(
        tmp_path / "bmshj2018-factorized-prior-3-5c6f152b.pth.tar",
        random_factorized(np.random.default_rng(0)),
    )
    args = ("attack", "--run", run, "--attacks", "jpeg90", "--views", "2", "--quiet")
    code, out, err = mnerf(*args, "--codec-model", f"bmshj2018-factorized={weights}")
    assert code == 0, err
    result = json.loads((run / "eval-test-attacks.json").read_text())
    assert result["order"] == ["none", "jpeg90", "bmshj2018-factorized-q3"]
    row = result["attacks"]["bmshj2018-factorized-q3"]
    assert (
        row["family"] == "regen" and "N 8, M 12" in row["description"] and 0 <= row["bit_accuracy_mean"] <= 1
    )
    assert "bmshj2018-factorized-q3" in out
    # A weights file of another architecture: one line naming the first missing weight.
    code, _, err = mnerf(*args, "--codec-model", f"cheng2020-anchor={weights}")
    assert code == 2 and "lack g_a.0.conv1.weight" in err and len(err.strip().splitlines()) == 1
    code, out, _ = mnerf("attack", "--list")
    assert code == 0 and "--codec-model" in out
