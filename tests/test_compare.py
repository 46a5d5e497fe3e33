"""``mnerf compare``: runs grouped by the settings they differ in, seeds summarised, bad runs refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mnerf_jax import cli
from mnerf_jax.core import rundir
from mnerf_jax.evaluation import attacks, compare, model_attacks

BASE_SETTINGS = {
    "lambda_key": 0.2,
    "fidelity_psnr": 0.0,
    "seed": 0,
    "key_seed": 0,
    "time_budget_min": 60.0,
    "wm_ranks": [8, 8, 8],
}


def write_run(
    root: Path,
    name: str,
    *,
    bits: float,
    psnr: float,
    settings: dict | None = None,
    source: str = "/runs/lego",
    kind: str = "multinerf",
    by_test: bool = True,
) -> Path:
    """A watermarked run directory with the files ``compare`` reads (no checkpoint)."""
    run = root / name
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"kind": kind, "source_run": source}))
    (run / "config.json").write_text(json.dumps({"watermark": {**BASE_SETTINGS, **(settings or {})}}))
    result = {
        "bit_accuracy_mean": bits,
        "bit_accuracy_png_mean": bits - 0.001,
        "bit_accuracy_min": bits - 0.1,
        "identification_accuracy": 0.95,
        "verified_identification_accuracy": 0.3,
        "misidentification_rate": 0.0,
        "clean_false_detection_rate": 0.01,
        "identification": {"test": "binomial"},
        "psnr": psnr,
        "clean_psnr": 32.0,
        "lpips": 0.1,
        "views": 200,
        "num_ids": 16,
        "bits": 16,
    }
    if by_test:
        result |= {
            "verified_identification_accuracy_by_test": {"binomial": 0.3, "sign_flip": 0.5},
            "misidentification_rate_by_test": {"binomial": 0.0, "sign_flip": 0.02},
            "clean_false_detection_rate_by_test": {"binomial": 0.01, "sign_flip": 0.03},
        }
    (run / "eval-test.json").write_text(json.dumps(result))
    return run


@pytest.fixture()
def four_runs(tmp_path: Path) -> list[Path]:
    """Two settings (lambda_key 0.1 / 0.2), two seeds each; one run with another time budget (folded)."""
    return [
        write_run(
            tmp_path, "a0", bits=0.90, psnr=24.0, settings={"lambda_key": 0.1, "seed": 0, "key_seed": 0}
        ),
        write_run(tmp_path, "b0", bits=0.80, psnr=22.0, settings={"seed": 0, "key_seed": 0}),
        write_run(
            tmp_path,
            "a1",
            bits=0.80,
            psnr=26.0,
            settings={"lambda_key": 0.1, "seed": 1, "key_seed": 1, "time_budget_min": 0.0},
        ),
        write_run(tmp_path, "b1", bits=0.94, psnr=23.0, settings={"seed": 1, "key_seed": 1}),
    ]


def test_runs_group_by_the_setting_they_differ_in_and_seeds_fold_together(four_runs: list[Path]) -> None:
    groups = compare.compare_runs(four_runs)
    assert [g.label for g in groups] == ["losses.lambda_key=0.1", "losses.lambda_key=0.2"]
    assert [[r.path.name for r in g.runs] for g in groups] == [["a0", "a1"], ["b0", "b1"]]
    mean, low, high = groups[0].stats("bits")
    assert (mean, low, high) == pytest.approx((0.85, 0.80, 0.90))
    assert groups[1].stats("psnr_drop") == pytest.approx((-9.5, -10.0, -9.0))
    assert groups[0].stats("named_sign_flip") == pytest.approx((0.5, 0.5, 0.5))


def test_a_differing_source_run_splits_a_setting_unless_ignored(tmp_path: Path) -> None:
    runs = [
        write_run(tmp_path, "x", bits=0.9, psnr=24.0, source="/runs/fit_a"),
        write_run(tmp_path, "y", bits=0.8, psnr=24.0, source="/runs/fit_b", settings={"seed": 1}),
    ]
    assert [g.label for g in compare.compare_runs(runs)] == [
        "source_run=/runs/fit_a",
        "source_run=/runs/fit_b",
    ]
    folded = compare.compare_runs(runs, ignore=(*compare.IGNORED_BY_DEFAULT, "source_run"))
    assert [(g.label, len(g.runs)) for g in folded] == [("all runs", 2)]


def test_an_evaluation_without_per_test_rates_keeps_its_own_tests_figure(tmp_path: Path) -> None:
    run = compare.load_run_figures(write_run(tmp_path, "old", bits=0.9, psnr=24.0, by_test=False))
    assert run.figures["named_binomial"] == pytest.approx(0.3)
    assert run.figures["named_sign_flip"] is None
    assert "—" in compare.runs_table(compare.group_runs([run]))


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda root: root / "absent", "no such run directory"),
        (lambda root: (root / "plain").mkdir() or root / "plain", "not a mnerf run directory"),
        (lambda root: write_run(root, "fit", bits=0.5, psnr=30.0, kind="tensorf"), "not a watermarked one"),
        (
            lambda root: (
                (write_run(root, "new", bits=0.9, psnr=24.0) / "eval-test.json").unlink() or root / "new"
            ),
            "mnerf evaluate --run",
        ),
    ],
)
def test_a_run_that_cannot_be_compared_is_refused_with_its_reason(tmp_path: Path, make, message: str) -> None:
    good = write_run(tmp_path, "good", bits=0.9, psnr=24.0)
    with pytest.raises(compare.CompareError, match=message):
        compare.compare_runs([good, make(tmp_path)])


def test_cli_prints_both_tables_json_and_a_plot(four_runs: list[Path], tmp_path: Path, capsys) -> None:
    plot = tmp_path / "out" / "tradeoff.png"
    assert cli.main(["compare", *map(str, four_runs), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert "| losses.lambda_key=0.1 | a0 | 0/0 | 90.0 % |" in out
    assert "| losses.lambda_key=0.2 | 2 | 87.0 % (80.0 % – 94.0 %) |" in out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli.main(["compare", *map(str, four_runs), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["groups"][1]["stats"]["bits"] == pytest.approx({"mean": 0.87, "min": 0.80, "max": 0.94})


def test_cli_bad_run_is_one_error_line(tmp_path: Path, capsys) -> None:
    assert cli.main(["compare", str(tmp_path / "absent")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mnerf: error:")


def test_the_watermark_kind_is_the_run_loaders() -> None:

    assert compare.WATERMARK_KIND == rundir.WATERMARK_KIND


def test_worst_id_named_is_the_lowest_diagonal_share_of_the_decision_confusion() -> None:
    # Rows: rendered ID; columns: named ID, last = no watermark. ID 1 is named for 2 of its 4 renders.
    result = {"identification": {"confusion_decision": [[4, 0, 0], [1, 2, 1]]}}
    assert compare.figures_of(result)["named_worst_id"] == pytest.approx(0.5)
    assert compare.figures_of({"identification": {}})["named_worst_id"] is None


def test_a_run_with_the_sections_folds_with_one_written_before_them(tmp_path: Path) -> None:
    # config.json's [watermark] in today's sections and in the flat layout of older runs compare by the same
    # dotted names: the two runs below are seeds of one setting.
    old = write_run(tmp_path, "old", bits=0.9, psnr=24.0, settings={"seed": 0})
    new = write_run(tmp_path, "new", bits=0.8, psnr=23.0, settings={"seed": 1})
    nested = {
        "seed": 1,
        "key_seed": 0,
        "module": {"wm_ranks": [8, 8, 8]},
        "losses": {"lambda_key": 0.2},
        "fidelity": {"psnr": 0.0},
        "time_budget": {"minutes": 60.0},
    }
    (new / "config.json").write_text(json.dumps({"watermark": nested}))
    runs = [compare.load_run_figures(p) for p in (old, new)]
    assert compare.varying_settings(runs) == []
    assert runs[1].settings["losses.lambda_key"] == 0.2


def write_attack_scores(
    run: Path, suite: str, rows: dict[str, tuple[float, float]], model: bool = False
) -> None:
    """``mnerf attack``'s score file for ``suite``: per attack (bit accuracy, false-claim rate)."""
    per_attack = {
        name: {
            "bit_accuracy_mean": bits,
            "bit_accuracy_min": bits - 0.1,
            "identification_accuracy": bits,
            "verified_identification_accuracy": bits - 0.2,
            "false_claim_rate": claims,
        }
        for name, (bits, claims) in rows.items()
    }
    scores = {"attacks": per_attack, "order": list(rows)}
    path = (
        model_attacks.model_attacks_path(run, "test", suite)
        if model
        else attacks.attacks_path(run, "test", suite)
    )
    path.write_text(json.dumps(scores))


def test_attack_rows_summarise_each_attack_over_the_seeds(four_runs: list[Path], capsys) -> None:
    for run, (noise, claims) in zip(
        four_runs, [(0.8, 0.0), (0.7, 0.01), (0.9, 0.03), (0.6, 0.0)], strict=True
    ):
        write_attack_scores(run, "peers", {"none": (0.99, 0.0), "noise": (noise, claims)})
    groups = compare.compare_runs(four_runs, attacks=compare.AttackSuite("peers"))
    assert groups[0].attack_names() == ["none", "noise"]
    assert groups[0].attack_stats("noise", "bits") == pytest.approx((0.85, 0.8, 0.9))
    assert groups[0].attack_stats("noise", "false_claims") == pytest.approx((0.015, 0.0, 0.03))
    table = compare.attack_table(groups)
    assert "| losses.lambda_key=0.1 | 2 | noise | 85.0 % (80.0 % – 90.0 %) |" in table
    assert cli.main(["compare", *map(str, four_runs), "--attacks", "peers", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["groups"][1]["attack_stats"]["noise"]["bits"] == pytest.approx(
        {"mean": 0.65, "min": 0.6, "max": 0.7}
    )
    assert data["groups"][1]["runs"][0]["attacks"]["none"]["named"] == pytest.approx(0.79)


def test_attacks_on_the_model_are_their_own_files_and_a_missing_one_names_its_command(
    four_runs: list[Path], capsys
) -> None:
    for run in four_runs:
        write_attack_scores(run, "model", {"quantise8": (0.99, 0.0)}, model=True)
    groups = compare.compare_runs(four_runs, attacks=compare.AttackSuite("model", model=True))
    assert groups[1].attack_stats("quantise8", "bits") == pytest.approx((0.99, 0.99, 0.99))
    assert cli.main(["compare", *map(str, four_runs), "--attacks", "peers"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mnerf attack --run" in err[0] and "--suite peers" in err[0]


def test_attack_score_files_are_named_as_mnerf_attack_writes_them(tmp_path: Path) -> None:
    assert (
        compare.AttackSuite("peers").file_name("test") == attacks.attacks_path(tmp_path, "test", "peers").name
    )
    model = compare.AttackSuite("model", model=True).file_name("path")
    assert model == model_attacks.model_attacks_path(tmp_path, "path", "model").name
