"""The commands on watermarked runs (the `tiny` fixture of conftest.py): ``load_run`` from a fresh process,
``render --id``, ``evaluate``, ``extract --run`` and the whole demo on the tiny fitted run."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import imageio.v3 as iio
import numpy as np
import pytest
from conftest import EVALUATION_KEYS

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import camera_path
from mnerf_jax.data.images import round_to_8bit
from mnerf_jax.reader import extract as extract_lib
from mnerf_jax.tensorf import run as tensorf_runs

if TYPE_CHECKING:
    from conftest import TinyRuns


def _one_error_line(err: str, needle: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("mnerf: error:") and needle in lines[0], err


@pytest.fixture(scope="module")
def id_renders(tiny: TinyRuns, tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """``mnerf render --run WMRUN --id K --views 2`` for both IDs: ``{K: folder of PNGs}``."""
    from mnerf_jax import cli

    root = tmp_path_factory.mktemp("renders")
    for k in (0, 1):
        code = cli.main(
            [
                "render",
                "--run",
                str(tiny.wm),
                "--id",
                str(k),
                "--views",
                "2",
                "--out",
                str(root / f"id{k}"),
                "--quiet",
            ]
        )
        assert code == 0
    return {k: root / f"id{k}" for k in (0, 1)}


def test_load_run_loads_either_kind_from_a_fresh_process(tiny: TinyRuns) -> None:
    # watermark.run.load_run dispatches on run.json's kind: a fitted TensoRF and a watermarked run.
    script = (
        "import sys\n"
        "from mnerf_jax.watermark import run\n"
        "for path in sys.argv[1:]:\n"
        "    loaded = run.load_run(path)\n"
        "    print(loaded.kind, loaded.step, loaded.extras.get('num_ids'), loaded.extras.get('id'))\n"
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-c", script, str(tiny.wm), str(tiny.fit)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].split() == ["multinerf", "80", "2", "0"]
    assert lines[1].split()[0] == "tensorf" and lines[1].split()[2:] == ["None", "None"]


def test_render_with_id(tiny: TinyRuns, id_renders: dict[int, Path], tmp_path: Path, mnerf) -> None:
    from mnerf_jax.watermark import run as wm_run

    names = sorted(p.name for p in id_renders[1].iterdir())
    assert names == ["r_0.png", "r_5.png"]
    a, b = (iio.imread(id_renders[k] / "r_0.png").astype(int) for k in (0, 1))
    assert np.abs(a - b).max() > 2  # the IDs render differently
    # The PNG is the library's render of that ID, rounded to 8 bits.
    loaded = wm_run.load_run(tiny.wm)
    cameras = loaded.load_scene(splits=("test",)).split("test").cameras
    expected = wm_run.render_with_id(loaded, 1, cameras, [0])[0]
    assert np.abs(b - np.round(np.clip(expected, 0, 1) * 255)).max() <= 1
    # Without --id a watermarked run renders ID 0, and says so.
    code, out, _ = mnerf("render", "--run", tiny.wm, "--views", "1", "--out", tmp_path / "default", "--quiet")
    assert code == 0 and "watermark ID 0" in out
    np.testing.assert_array_equal(iio.imread(tmp_path / "default" / "r_0.png"), a)


def test_render_id_errors_are_one_line_and_write_nothing(tiny: TinyRuns, tmp_path: Path, mnerf) -> None:
    cases = [
        (tiny.wm, "2", "outside [0, 2)"),
        (tiny.wm, "-1", "outside [0, 2)"),
        (tiny.fit, "0", "not a watermarked run"),
    ]
    for i, (run_dir, k, message) in enumerate(cases):
        out = tmp_path / f"o{i}"
        code, _, err = mnerf("render", "--run", run_dir, "--id", k, "--out", out, "--quiet")
        assert code == 2, err
        _one_error_line(err, message)
        assert not out.exists()


def test_evaluate_watermarked_run(tiny: TinyRuns, tmp_path: Path, mnerf) -> None:
    wm = tmp_path / "wm"  # a copy without earlier evaluations: the evaluation writes into the run
    shutil.copytree(tiny.wm, wm, ignore=shutil.ignore_patterns("eval-*"))
    code, _, err = mnerf("evaluate", "--run", wm, "--views", "2", "--quiet", "--read-jitter", "-1")
    assert code != 0 and "radius" in err and not (wm / "eval-test.json").exists()
    code, out, _ = mnerf("evaluate", "--run", wm, "--views", "2", "--quiet", "--read-jitter", "1")
    assert code == 0
    saved = json.loads((wm / "eval-test.json").read_text())
    assert saved["read_jitter"] == 1  # recorded (this tiny run reads whole images, which do not move)
    for key in EVALUATION_KEYS:
        assert key in saved, key
    assert saved["views"] == 2 and saved["num_ids"] == 2 and saved["bits"] == 8 and saved["split"] == "test"
    assert saved["psnr_clean_model"] is not None and 0.0 <= saved["bit_accuracy_min"] <= 1.0
    # The table of report.format_table, then where the file went.
    assert "bit accuracy, float render (mean over IDs)" in out and "IDs × bits" in out
    assert f"{saved['psnr']:.2f}" in out and str(wm / "eval-test.json") in out
    assert len(list((wm / "eval-test").glob("id*/*.png"))) == 2 * 2


def test_evaluate_along_the_render_path(tiny: TinyRuns, tmp_path: Path, mnerf) -> None:
    """``--split path``: novel views along the render path, read for every ID; they have no ground truth, so
    quality is against the clean model's renders, which are those of ``mnerf render --split path``."""
    code, _, err = mnerf("evaluate", "--run", tiny.fit, "--split", "path", "--quiet")
    assert code == 2
    _one_error_line(err, "no ground truth")
    wm = tmp_path / "wm"
    shutil.copytree(tiny.wm, wm, ignore=shutil.ignore_patterns("eval-*"))
    code, out, err = mnerf("evaluate", "--run", wm, "--split", "path", "--views", "3", "--quiet")
    assert code == 0, err
    saved = json.loads((wm / "eval-path.json").read_text())
    assert saved["split"] == "path" and saved["views"] == 3 and saved["num_ids"] == 2
    assert saved["view_names"] == ["frame_0000", "frame_0001", "frame_0002"]
    assert saved["psnr"] is None and saved["clean_psnr"] is None
    assert all(row["psnr"] is None for row in saved["per_id"])
    assert saved["psnr_clean_model"] > 0 and 0.0 <= saved["bit_accuracy_min"] <= 1.0
    assert len(list((wm / "eval-path").glob("id*/*.png"))) == 2 * 3 and str(wm / "eval-path.json") in out
    clean = tensorf_runs.load_tensorf_run(tiny.fit)
    cameras = camera_path(clean.load_scene(splits=("train",)), 3)
    expected = round_to_8bit(np.asarray(tensorf_runs.render_views(clean, cameras, [1])[0]))
    saved_clean = extract_lib.load_image(wm / "eval-path" / "clean" / "frame_0001.png")
    np.testing.assert_array_equal(saved_clean, expected)


def _binomial_tail(k: int, bits: int) -> float:
    """P[Bin(bits, 1/2) >= k], by hand (the library's significance module is what is checked)."""
    return sum(math.comb(bits, j) for j in range(k, bits + 1)) / 2**bits


def test_extract_identifies_the_id_of_rendered_images(
    tiny: TinyRuns, id_renders: dict[int, Path], tmp_path: Path, mnerf
) -> None:
    """``extract --run`` reports, per image, the bits the run's decoder reads, the key of highest soft
    correlation with its logits, that key's agreement and p-values, and the decision at the threshold.

    What the tiny 2-ID × 8-bit run's renders read is left to chance (float rounding differs between CPU
    kinds, and the run's whitened random decoder turns that into other bits): every figure below is either
    computed here from the same logits, or forced by keys written to match them.
    """
    from mnerf_jax.cli.extract import identification_line
    from mnerf_jax.core import rundir
    from mnerf_jax.evaluation import watermarked as wm_eval
    from mnerf_jax.reader import extract, read_window
    from mnerf_jax.reader import keys as keys_lib
    from mnerf_jax.watermark import run as wm_run

    paths = sorted(id_renders[1].glob("*.png")) + sorted(id_renders[0].glob("*.png"))
    code, out, _ = mnerf("extract", "--run", tiny.wm, *paths, "--json")
    assert code == 0
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["image"] for r in records] == [str(p) for p in paths]
    assert all(r["run"] == str(tiny.wm) for r in records)
    library = wm_eval.identify_images(tiny.wm, paths)
    assert [{k: v for k, v in r.items() if k != "run"} for r in records] == library
    # The same files decoded directly with the run's decoder and read window, matched to its keys by hand.
    keys, decoder = wm_run.load_keys_and_decoder(tiny.wm)
    read = read_window.of_config(rundir.read_run_config(tiny.wm).watermark.reading)
    logits = extract.decode_paths(decoder.variables, paths, decoder.wavelet, 32, read).astype(np.float64)
    signs = 2.0 * keys.messages.astype(np.float64) - 1.0
    for r, row in zip(records, logits, strict=True):
        bits = (row > 0).astype(np.uint8)
        assert r["bits"] == "".join(map(str, bits))
        scores = signs @ row  # soft correlation with each key
        near_top = np.flatnonzero(scores >= scores.max() - 1e-9 * max(1.0, np.abs(scores).max()))
        if len(near_top) == 1:
            assert r["best_id"] == near_top[0]
        else:  # a tie, up to rounding (which the summation order decides): undecided, or one of the tied keys
            assert r["best_id"] in (-1, *near_top.tolist())
        best = r["best_id"] if r["best_id"] >= 0 else int(np.argmax(scores))
        agree = int((bits == keys.messages[best]).sum())
        assert r["bit_accuracy"] == agree / 8
        assert r["p_value"] == pytest.approx(_binomial_tail(agree, 8), rel=1e-12)
        assert r["p_corrected"] == pytest.approx(min(1.0, 2 * r["p_value"]), rel=1e-12)
        assert 0.0 < r["p_value_sign_flip"] <= r["p_corrected_sign_flip"] <= 1.0
        # 2 IDs × 8 bits: the smallest corrected p-value is 2/256 > 1e-3, so nothing is claimed.
        assert r["p_corrected"] >= 2 / 256 and r["id"] == -1 and r["threshold"] == 1e-3
    code, out, _ = mnerf("extract", "--run", tiny.wm, *paths)
    lines = out.splitlines()
    assert code == 0 and len(lines) == 5
    # The last line: the threshold decided by, and that it is uncalibrated (test_false_claims calibrates one).
    assert (
        lines[-1].startswith("mnerf extract: threshold 0.001 (binomial test; the run's")
        and "uncalibrated" in lines[-1]
    )
    for line, r in zip(lines[:-1], records, strict=True):
        assert line.startswith(r["image"]) and line.endswith(identification_line(r))
        assert "no watermark (binomial p ≥ 0.001; best ID" in line or "no watermark (tie between keys" in line
    # With a looser threshold an image is claimed exactly when its corrected p-value is below it.
    code, out, _ = mnerf("extract", "--run", tiny.wm, *paths, "--threshold", "0.5", "--json")
    loose = [json.loads(line) for line in out.splitlines()]
    for r, b in zip(loose, records, strict=True):
        same = [k for k in b if k not in ("id", "threshold", "threshold_source", "decision_rule")]
        assert [r[k] for k in same] == [b[k] for k in same]
        assert r["threshold"] == 0.5 and r["id"] == (r["best_id"] if r["p_corrected"] < 0.5 else -1)
        assert r["threshold_source"] == "given" and b["threshold_source"] == "config"
        assert identification_line(r).startswith(f"ID {r['id']}" if r["id"] >= 0 else "no watermark")
    # --test sign_flip decides by the confidence-weighted p-value (both are in every record).
    code, out, _ = mnerf(
        "extract", "--run", tiny.wm, *paths, "--threshold", "0.5", "--test", "sign_flip", "--json"
    )
    flip = [json.loads(line) for line in out.splitlines()]
    for r, b in zip(flip, loose, strict=True):
        assert r["test"] == "sign_flip" and b["test"] == "binomial" and r["p_value"] == b["p_value"]
        assert r["p_value_sign_flip"] == b["p_value_sign_flip"]
        assert r["id"] == (r["best_id"] if r["p_corrected_sign_flip"] < 0.5 else -1)
    # An image whose decoded bits are ID k's key is named k, once the threshold lets 8 bits name anything
    # (2/256 < 0.01): the run copied with keys written from the first image's bits and their complement.
    assert not (logits[0] == 0).all()
    read = (logits[0] > 0).astype(np.uint8)
    for k in (0, 1):
        forged = tmp_path / f"keys-as-id{k}"
        shutil.copytree(tiny.wm, forged, ignore=shutil.ignore_patterns("eval-*", "checkpoints"))
        messages = np.stack([read, 1 - read] if k == 0 else [1 - read, read])
        keys_lib.save_keys(forged, dataclasses.replace(keys, messages=messages))
        code, out, err = mnerf("extract", "--run", forged, paths[0], "--threshold", "0.01", "--json")
        assert code == 0, err
        (r,) = [json.loads(line) for line in out.splitlines()]
        assert r["bits"] == "".join(map(str, read)) and r["best_id"] == k and r["bit_accuracy"] == 1.0
        assert r["p_value"] == 1 / 256 and r["p_corrected"] == 2 / 256 and r["id"] == k
        code, out, _ = mnerf("extract", "--run", forged, paths[0], "--threshold", "0.01")
        assert code == 0 and f"  ID {k}  (best ID {k}, bit accuracy 100.00%" in out


def test_extract_errors_and_the_decoder_mode(
    tiny: TinyRuns, id_renders: dict[int, Path], tmp_path: Path, mnerf
) -> None:
    png = sorted(id_renders[1].glob("*.png"))[0]
    gray = tmp_path / "gray.png"
    iio.imwrite(gray, np.zeros((32, 32), np.uint8))
    for argv, message in [
        ((gray,), "RGB"),
        ((tmp_path / "absent.png",), "does not exist"),
        ((png, "--bits", "8"), "--bits"),
    ]:
        code, _, err = mnerf("extract", "--run", tiny.wm, *argv)
        assert code == 2
        _one_error_line(err, message)
    code, _, err = mnerf("extract", "--run", tiny.fit, png)
    assert code == 2
    _one_error_line(err, "'tensorf' run without watermarks")
    # --decoder FILE still decodes bits only.
    code, out, _ = mnerf("extract", "--decoder", tiny.decoder, png)
    assert code == 0 and out.split()[0] == str(png) and len(out.split()[1]) == 8
    # --run and --decoder exclude each other (argparse).
    with pytest.raises(SystemExit):
        mnerf("extract", "--run", tiny.wm, "--decoder", tiny.decoder, png)


# ------------------------------------------------------------------------------------ the demo's step


def test_demo_finds_its_decoder(tiny: TinyRuns, tmp_path: Path, monkeypatch) -> None:
    from mnerf_jax.cli import demo
    from mnerf_jax.reader import decoder_io

    monkeypatch.setattr(decoder_io, "shipped_decoder_path", lambda bits: tmp_path / f"absent_l{bits}.npz")
    path, note = demo.find_decoder(None)
    assert str(path) == decoder_io.FRESH and "absent_l16.npz" in note and "--decoder FILE" in note
    assert demo.find_decoder(Path(decoder_io.FRESH)) == (Path(decoder_io.FRESH), "")
    # A --decoder of the wrong length is refused before the demo writes anything.
    with pytest.raises(MnerfError, match="16 bits are expected"):
        demo.find_decoder(tiny.decoder)
    shipped = tmp_path / "absent_l16.npz"
    shutil.copy(tiny.decoder, shipped)  # (any file at the shipped path is used; its length is checked later)
    assert demo.find_decoder(None) == (shipped, "")


def test_demo_resumes_its_fitted_run_and_writes_the_report(
    tiny: TinyRuns, tmp_path: Path, mnerf, monkeypatch
) -> None:
    """The whole ``mnerf demo`` on a demo folder whose run is already fitted (the tiny fit): the fit step
    resumes it with nothing left to train, then evaluation, renders, one phase-1 step of 4 IDs × 16 bits from
    a fresh decoder (none shipped, no --decoder: a note says so), the watermark evaluation and the report."""
    from conftest import TINY_FIT

    from mnerf_jax.reader import decoder_io

    monkeypatch.setattr(decoder_io, "shipped_decoder_path", lambda bits: tmp_path / f"absent_l{bits}.npz")
    out = tmp_path / "demo"
    shutil.copytree(tiny.fit, out / "run")
    (out / "demo.json").write_text("{}")  # an earlier demo's folder
    # The step's plumbing, not the embedding's quality (tests/test_embed.py has that). The run recorded the
    # preset's [watermark] section: these --set items must still reach the embedding (1 step, not 1,000).
    sets = [
        *TINY_FIT,
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=1",
        "watermark.schedule.phase2_steps=0",
    ]
    code, stdout, err = mnerf(
        "demo", "--out", out, *[a for s in sets for a in ("--set", s)], "--frames", "2", "--quiet"
    )
    assert code == 0, err
    notes = [line for line in err.splitlines() if "fresh decoder" in line]
    assert len(notes) == 1 and "--decoder FILE" in notes[0], err
    fitted = json.loads((tiny.fit / "metrics.json").read_text())["steps"]
    assert f"{fitted} steps" in stdout and "test PSNR" in stdout
    assert (out / "run" / "eval-test.json").is_file() and (out / "orbit" / "path.gif").is_file()
    assert len(list((out / "test").glob("*.png"))) == 6
    for name in ("report.md", "renders.png", "bit_accuracy.png"):
        assert (out / "report" / name).is_file(), name
    saved = json.loads((out / "wm" / "eval-test.json").read_text())
    assert saved["num_ids"] == 4 and saved["bits"] == 16 and saved["views"] == 6
    assert json.loads((out / "wm" / "embed.json").read_text())["steps_done"] == 1
    assert "4 IDs × 16 bits" in stdout and "IDs × bits" in stdout and "4 × 16" in stdout
    assert stdout.count("\n  3  ") == 1  # the per-ID table lists ID 3
