"""A study's report (``mnerf_jax.study.report``) from synthetic results rows, no training: its tables hold the
figures computed here independently, its figures are PNGs, the paired tests separate a uniformly better
method from an equal one, missing cells show "—" and failed cells their error; ``--report-only`` rebuilds
a study folder's report alone."""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from test_study import SPEC, write_spec

from mnerf_jax.study import paper_numbers, report, report_stats
from mnerf_jax.study.spec import load_spec

IDS = (1, 2, 4, 8, 16, 32, 64)
SEEDS = (0, 1)


def mn_bits(n: int, seed: int) -> float:
    return 0.95 - 0.03 * math.log2(n) + 0.01 * seed


def make_row(method: str, variant: str, n: int, bits: int, seed: int, **extra: Any) -> dict[str, Any]:
    """A results row of a done cell on lego (its paper figures matched as ``results.row`` does)."""
    row: dict[str, Any] = {
        "study": "synthetic",
        "cell_id": f"lego-{method}-n{n}-b{bits}-s{seed}-00000000",
        "status": "done",
        "scene": "lego",
        "paper_scene": "lego",
        "method": method,
        "variant": variant,
        "num_ids": n,
        "bits": bits,
        "seed": seed,
        "wmcom": 8,
        "noised": False,
        "bit_acc": mn_bits(n, seed),
        "bit_acc_worst_id": mn_bits(n, seed) - 0.05,
        "psnr": 30.0 + seed,
        "ssim": 0.9,
        "lpips": 0.05,
        "params_m_watermark": 1.0,
        "error": None,
        "machine": "a CPU, 2 cores",
    }
    row.update(extra)
    found = paper_numbers.match(row)
    for metric in ("bit_acc", "psnr", "ssim", "lpips", "params_m_watermark"):
        row[f"paper_{metric}"] = found[metric].value if metric in found else None
    row["paper_tables"] = " ".join(sorted({f.table for f in found.values()})) or None
    row["paper_approx"] = any(f.approx for f in found.values()) if found else None
    if row["status"] != "done":
        for k in ("bit_acc", "bit_acc_worst_id", "psnr", "ssim", "lpips", "params_m_watermark"):
            row[k] = None
    return row


def synthetic_rows() -> list[dict[str, Any]]:
    rows = []
    for n in IDS:
        for s in SEEDS:
            rows.append(make_row("multinerf", "multinerf", n, 16, s, attack_low_bit_acc=0.8 + 0.01 * s))
    for n in IDS:
        for s in SEEDS:
            # uniformly worse by 10 to 17 points; its 64-ID cells not run
            worse = mn_bits(n, s) - 0.10 - 0.01 * math.log2(n)
            status = "pending" if n == 64 else "done"
            rows.append(
                make_row(
                    "waterf_mod", "waterf_mod", n, 16, s, bit_acc=worse, status=status, attack_low_bit_acc=0.6
                )
            )
    rows.append(make_row("no_grid", "no_grid", 16, 16, 0, bit_acc=0.5))
    rows.append(make_row("no_grid", "no_grid", 16, 16, 1, status="pending"))
    for s in SEEDS:
        rows.append(make_row("no_film", "no_film", 16, 16, s, status="failed", error="ValueError: boom"))
        rows.append(make_row("wmcom4", "multinerf", 16, 16, s, wmcom=4, bit_acc=0.7 + 0.02 * s))
        rows.append(make_row("multinerf_bits", "multinerf", 16, 48, s, bit_acc=0.85))
        rows.append(make_row("mn_single", "multinerf", 1, 48, s, bit_acc=0.9 + 0.01 * s))
        rows.append(make_row("waterf", "waterf", 1, 48, s, wmcom=None, bit_acc=0.9 + 0.01 * s))
    rows[0]["attack_low_gaussian_blur_bit_acc"] = 0.75
    return rows


def table_row(text: str, section: str, first_cell: str) -> list[str]:
    """The cells of the markdown row starting with ``first_cell`` in ``section`` (a heading's text)."""
    part = text.split(section, 1)[1]
    for line in part.splitlines():
        if line.startswith(f"| {first_cell} |"):
            return [c.strip() for c in line.strip("|").split("|")]
    raise AssertionError(f"no row {first_cell!r} after {section!r}")


def spread(values: list[float]) -> str:
    return f"{100 * statistics.mean(values):.1f} ± {100 * statistics.stdev(values):.1f} (n={len(values)})"


def test_the_report_holds_every_table_with_its_seeds_and_the_papers_figures(tmp_path: Path) -> None:
    rows = synthetic_rows()
    path = report.write_report(tmp_path, rows, "synthetic", "studies/x.toml", "mnerf study x --out y")
    text = path.read_text()
    assert text.startswith("# Study synthetic: report")
    assert "`studies/x.toml`" in text and "`mnerf study x --out y`" in text
    assert "- machine: a CPU, 2 cores\n" in text

    # Capacity: multinerf and waterf_mod at every number of IDs, waterf_mod's 64 IDs not run.
    capacity = "### lego, 16-bit messages"
    cells = table_row(text, capacity, "16")
    assert cells[1] == spread([mn_bits(16, s) for s in SEEDS])
    assert cells[2] == "82.8"  # tab:ablation's MN (ours), lego, 16 IDs
    assert cells[3] == "30.50 ± 0.71 (n=2)"
    assert table_row(text, capacity, "32")[2] == "≈70.0"  # the text's reading of the capacity figure
    assert table_row(text, capacity, "64")[5:7] == ["—", "≈50.0"]  # waterf_mod: not run; the paper's
    assert (tmp_path / "figures" / "capacity-lego-b16.png").is_file()

    # The ablation: every row of the paper's table, ours beside, the failed no_film shown as missing.
    ablation = text.split("## Ablation", 1)[1].split("## #WMCom", 1)[0]
    assert "| MN(-FiLM)(-GRID) | not in this study | — | 66.3 |" in ablation
    no_film = table_row(ablation, "### lego", "MN(-FiLM)")
    assert no_film[1].startswith("`no_film`") and no_film[2] == "—" and no_film[3] == "70.0"
    no_grid = table_row(ablation, "### lego", "MN(-GRID)(+MLP)")
    assert no_grid[2] == "50.0 (n=1)" and no_grid[3] == "51.6"
    assert "wmcom4" not in ablation  # another #WMCom than the ablations'
    assert "n < 2: no test" in ablation  # no_grid: one seed done

    # #WMCom: 4 and 8 at 16 IDs × 16 bits; the bit lengths: 16 and 48 at 16 IDs.
    wmcom = text.split("## #WMCom", 1)[1].split("## Bit length", 1)[0]
    assert (
        table_row(wmcom, "###", "4")[2] == spread([0.7, 0.72]) and table_row(wmcom, "###", "4")[3] == "79.8"
    )
    assert table_row(wmcom, "###", "8")[1].startswith("`multinerf`")
    bits = text.split("## Bit length", 1)[1].split("## Single", 1)[0]
    assert table_row(bits, "### lego, 16 IDs, #WMCom 8", "48")[2] == "85.0 ± 0.0 (n=2)"

    # The single message: 48 bits, MultiNeRF and WateRF beside the paper's lego column.
    single = text.split("### 48-bit message", 1)[1].split("##", 1)[0]
    assert "| `mn_single` (MultiNeRF) | 90.5 ± 0.7 (n=2) | 94.9 |" in single
    assert "| `waterf` (WateRF) | 90.5 ± 0.7 (n=2) | 93.2 |" in single

    # Robustness: the suite's mean and its attack, a figure.
    assert "## Robustness" in text and "gaussian_blur" in text
    assert (tmp_path / "figures" / "robustness-low.png").is_file()

    # The failed cells with their errors; the pending ones listed.
    failures = text.split("## Failed and pending cells", 1)[1]
    assert "- failed `lego-no_film-n16-b16-s0-00000000`: ValueError: boom" in failures
    assert "pending (not run yet): 3 cells" in failures

    for png in (tmp_path / "figures").glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        with Image.open(png) as image:
            assert image.size[0] > 100 and image.size[1] > 100


def test_the_paired_tests_in_the_report(tmp_path: Path) -> None:
    text = report.write_report(tmp_path, synthetic_rows(), "synthetic").read_text()
    capacity = text.split("### lego, 16-bit messages", 1)[1].split("## Ablation", 1)[0]
    line = next(x for x in capacity.splitlines() if "`waterf_mod`" in x and "| bit acc. % |" in x)
    cells = [c.strip() for c in line.strip("|").split("|")]
    # 6 numbers of IDs × 2 seeds paired (64 IDs not run); waterf_mod uniformly worse.
    diffs = [mn_bits(n, s) - (mn_bits(n, s) - 0.10 - 0.01 * math.log2(n)) for n in IDS[:-1] for s in SEEDS]
    assert cells[2] == "12" and cells[3] == f"{100 * np.mean(diffs):.1f}"
    assert float(cells[4]) < 1e-3 and float(cells[5]) < 1e-3
    # mn_single and waterf are equal on every pair: no evidence either way.
    single = text.split("### 48-bit message", 1)[1].split("##", 1)[0]
    line = next(x for x in single.splitlines() if "`waterf`" in x and "| bit acc. % |" in x)
    assert line.rstrip(" |").endswith("| 2 | 0.0 | 1.000 | 1.000")


def test_the_paired_test_separates_a_better_method_from_an_equal_one() -> None:
    rng = np.random.default_rng(0)
    better = report_stats.paired_test(0.05 + 0.01 * rng.random(12))
    assert better.n == 12 and better.t_p < 1e-6 and better.wilcoxon_p == pytest.approx(2 / 2**12)
    equal = report_stats.paired_test([0.01, -0.01, 0.02, -0.02, 0.005, -0.005, 0.0])
    assert equal.t_p > 0.9 and equal.wilcoxon_p > 0.9
    assert report_stats.paired_test([0.0, 0.0]).t_p == 1.0
    flat = report_stats.paired_test([0.1, 0.1, 0.1])  # no spread: no t-test, the signed ranks exact
    assert math.isnan(flat.t_p) and flat.wilcoxon_p == pytest.approx(0.25)
    assert not report_stats.paired_test([0.3]).tested and math.isnan(report_stats.paired_test([]).mean_diff)
    a = [
        {"status": "done", "scene": "s", "num_ids": 2, "bits": 16, "seed": s, "x": float(s)} for s in range(3)
    ]
    b = [{**r, "x": r["x"] - 1.0} for r in a[1:]] + [{**a[0], "status": "failed", "x": None}]
    assert report_stats.paired_differences(a, b, "x").tolist() == [1.0, 1.0]
    s = report_stats.summarise([1.0, None, 3.0, float("nan")])
    assert (s.n, s.mean, s.low, s.high) == (2, 2.0, 1.0, 3.0) and s.std == pytest.approx(math.sqrt(2))


def test_a_study_with_no_cell_done_reports_every_table_as_missing(tmp_path: Path) -> None:
    rows = [make_row("multinerf", "multinerf", 2, 16, 0, status="pending")]
    text = report.write_report(tmp_path, rows, "empty").read_text()
    assert text.count("No rows of this study form this table.") == 5
    assert "No cell of this study measured an attack suite" in text


def test_report_only_rebuilds_a_study_folders_report(tmp_path: Path, mnerf) -> None:
    from mnerf_jax.study import runner

    path = write_spec(tmp_path, SPEC)
    out = tmp_path / "study"
    code, _, err = mnerf("study", path, "--out", out, "--report-only")
    assert code == 2 and "holds no study" in err
    runner.prepare_study_dir(out, load_spec(path), join=False)
    code, text, _ = mnerf("study", path, "--out", out, "--report-only")
    assert code == 0 and "report of 20 cells" in text
    body = (out / "report.md").read_text()
    assert f"--out {out} --report-only" in body and "pending (not run yet): 20 cells" in body
    assert (out / "results.csv").is_file()
    code, _, err = mnerf("study", path, "--out", out, "--report-only", "--resume")
    assert code == 2 and "runs nothing" in err


def test_the_paper_cpu_study_forms_every_table_the_paper_has(tmp_path: Path) -> None:
    """The rows of studies/paper_cpu.toml (figures made up, the 8- and 32-bit cells failed) form the capacity
    curve at 1–64 IDs for MultiNeRF and WateRF-modified, every row of the ablation table, the #WMCom and
    bit-length tables and the single-message table of MultiNeRF, MN-noised and WateRF."""
    from conftest import PROJECT_ROOT

    from mnerf_jax.study import grid, results

    spec = load_spec(PROJECT_ROOT / "studies" / "paper_cpu.toml")
    rows, fits = [], {}
    for cell in grid.expand(spec):
        r = results.row(spec, cell, tmp_path / "empty", fits)
        if r["bits"] in (8, 32):
            r.update(status="failed", error="no decoder")
        else:
            r.update(
                status="done", bit_acc=0.9 - 0.01 * math.log2(r["num_ids"]) + 0.01 * r["seed"], psnr=30.0
            )
        rows.append(r)
    text = report.write_report(tmp_path, rows, spec.name).read_text()
    capacity = text.split("## Capacity", 1)[1].split("## Ablation", 1)[0]
    assert "| IDs | `multinerf` (MultiNeRF" in capacity and "`waterf_mod` (WateRF-modified" in capacity
    for n in IDS:
        assert table_row(capacity, "###", str(n))[1].endswith("(n=2)")
    ablation = text.split("## Ablation", 1)[1].split("## #WMCom", 1)[0]
    for name in dict.fromkeys(f.label for f in paper_numbers.figures() if f.table == "tab:ablation"):
        assert f"| {name} | " in ablation
    wmcom = text.split("## #WMCom", 1)[1].split("## Bit length", 1)[0]
    assert [table_row(wmcom, "###", str(w))[1].split()[0] for w in (2, 4, 8, 48)] == [
        "`wmcom2`",
        "`wmcom4`",
        "`multinerf`",
        "`wmcom48`",
    ]
    bits = text.split("## Bit length", 1)[1].split("## Single", 1)[0]
    for b, shown in ((8, "—"), (16, "(n=2)"), (32, "—"), (48, "(n=2)")):
        assert table_row(bits, "### lego, 16 IDs", str(b))[2].endswith(shown)
    single = text.split("### 48-bit message", 1)[1].split("##", 1)[0]
    for method in ("`multinerf_single` (MultiNeRF)", "`multinerf_single_noised`", "`waterf` (WateRF"):
        assert f"| {method}" in single
