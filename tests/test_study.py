"""``mnerf study``: the spec and its errors, the grid's cells and IDs, shards and ``--only``, the dry run,
the paper's numbers, and a small study end to end on the `tiny` fixture's fitted run (a cell without a
decoder recorded as failed while the others go on; a kill mid-embedding resumed to the uninterrupted run's
figures)."""

from __future__ import annotations

import json
import textwrap
import types
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from conftest import PROJECT_ROOT, TINY_EMBED

from mnerf_jax.study import cost, grid, paper_numbers, results
from mnerf_jax.study.spec import StudySpecError, load_spec

if TYPE_CHECKING:
    from conftest import TinyRuns

SPEC = """\
[study]
name = "unit"
ids = [2, 4]
bits = [16, 48]
seeds = [0, 1]

[[scenes]]
name = "proc"
preset = "procedural"
set = ["train.n_iters=100"]

[[scenes]]
name = "proc_small"
preset = "procedural"
set = ["data.procedural_size=32"]

[[methods]]
name = "multinerf"
variant = "multinerf"

[[methods]]
name = "no_grid"
variant = "no_grid"
ids = [16]
bits = [16]
set = ["watermark.module.wm_ranks=[2,2,2]"]
"""


def write_spec(folder: Path, text: str, name: str = "spec.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(textwrap.dedent(text))
    return path


# ------------------------------------------------------------------------------------------ spec and grid


def test_the_grid_expands_every_axis_and_ids_are_stable(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path, SPEC))
    cells = grid.expand(spec)
    # 2 scenes × (multinerf: 2 IDs × 2 bits × 2 seeds + no_grid: 1 × 1 × 2 seeds)
    assert len(cells) == 2 * (8 + 2)
    ids = [c.id for c in cells]
    assert len(set(ids)) == len(ids)
    assert ids[0].startswith("proc-multinerf-n2-b16-s0-") and len(ids[0].rsplit("-", 1)[1]) == 8
    assert [c.id for c in grid.expand(load_spec(write_spec(tmp_path / "again", SPEC)))] == ids
    # A name is in the slug, not the hash; a setting changes the hash.
    renamed = load_spec(write_spec(tmp_path / "renamed", SPEC.replace('name = "proc"\n', 'name = "p"\n')))
    assert grid.expand(renamed)[0].hash == cells[0].hash and grid.expand(renamed)[0].id != ids[0]
    edited = load_spec(write_spec(tmp_path / "edited", SPEC.replace("n_iters=100", "n_iters=101")))
    assert grid.expand(edited)[0].hash != cells[0].hash
    assert grid.expand(edited)[-1].id == ids[-1]  # the other scene's cells keep theirs
    assert cells[0].embed_overrides()[-2:] == ("watermark.seed=0", "watermark.key_seed=0")
    assert grid.fit_id(cells[0].scene) == grid.fit_id(cells[1].scene) != grid.fit_id(cells[-1].scene)


def test_shards_are_disjoint_and_cover_every_cell(tmp_path: Path) -> None:
    cells = grid.expand(load_spec(write_spec(tmp_path, SPEC)))
    for n in (1, 2, 3, 7):
        shards = [grid.select(cells, (i, n)) for i in range(n)]
        ids = [c.id for shard in shards for c in shard]
        assert sorted(ids) == sorted(c.id for c in cells)  # covering and disjoint
    assert grid.parse_shard("1/3") == (1, 3)
    for bad in ("3/3", "-1/2", "1", "a/b", "0/0"):
        with pytest.raises(Exception, match="--shard"):
            grid.parse_shard(bad)


def test_shards_balance_the_estimated_cost(tmp_path: Path) -> None:
    """The greedy longest-first rule: no shard exceeds another by more than the heaviest cell, and a cell
    with more IDs per step (or more steps) weighs more; every shard gets its share of the cells."""
    spec = load_spec(write_spec(tmp_path, SPEC))
    cells = grid.expand(spec)
    weights = cost.shard_weights(spec, cells)
    assert set(weights) == {c.id for c in cells} and min(weights.values()) > 0
    (n2,) = (weights[c.id] for c in cells if c.id.startswith("proc-multinerf-n2-b16-s0-"))
    (n4,) = (weights[c.id] for c in cells if c.id.startswith("proc-multinerf-n4-b16-s0-"))
    assert n4 > n2
    for n in (2, 3, 4):
        loads = [sum(weights[c.id] for c in grid.select(cells, (i, n), weights=weights)) for i in range(n)]
        assert max(loads) - min(loads) <= max(weights.values()) + 1e-9
        assert sum(loads) == pytest.approx(sum(weights.values()))
    assert grid.assign_shards(cells, 3, weights) == grid.assign_shards(list(reversed(cells)), 3, weights)
    # An ID entering the first colour layer runs the whole MLP: the same cell weighs more.
    uncached = SPEC.replace("watermark.module.wm_ranks=[2,2,2]", "watermark.schedule.cache_source=false")
    by_variant = {}
    for variant in ("no_grid", "waterf_mod"):
        text = uncached.replace('"no_grid"\nids', f'"{variant}"\nids')
        each = load_spec(write_spec(tmp_path / variant, text))
        (by_variant[variant],) = (
            w
            for k, w in cost.shard_weights(each, grid.expand(each)).items()
            if k.startswith("proc-no_grid-n16-") and "-s0-" in k
        )
    assert by_variant["waterf_mod"] > 2 * by_variant["no_grid"]


def test_a_method_runs_on_the_scenes_it_names(tmp_path: Path) -> None:
    text = SPEC.replace('set = ["watermark.module', 'scenes = ["proc_small"]\nset = ["watermark.module')
    cells = grid.expand(load_spec(write_spec(tmp_path, text)))
    assert len(cells) == 2 * 8 + 2
    assert {c.scene.name for c in cells if c.method.name == "no_grid"} == {"proc_small"}
    # The filter selects cells; it is not a setting of theirs (their IDs are those of the unfiltered spec).
    every = {c.id for c in grid.expand(load_spec(write_spec(tmp_path / "all", SPEC)))}
    assert {c.id for c in cells} <= every


def test_only_selects_cells_by_glob(tmp_path: Path) -> None:
    cells = grid.expand(load_spec(write_spec(tmp_path, SPEC)))
    assert {c.method.name for c in grid.select(cells, only=["*-no_grid-*"])} == {"no_grid"}
    chosen = grid.select(cells, only=["proc-multinerf-n2-*-s1-*", "proc_small-*-b48-*"])
    assert len(chosen) == 2 + 4 and all(c.seed == 1 or c.bits == 48 for c in chosen)
    assert grid.select(cells, only=["nothing*"]) == []


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (('name = "unit"', 'name = "unit"\nnmae = 1'), r"study\.nmae: unknown key"),
        (("ids = [2, 4]", "ids = [0]"), r"study\.ids: expected integers ≥ 1"),
        (("ids = [2, 4]", "ids = []"), r"study\.ids: expected a non-empty list"),
        (("seeds = [0, 1]", "seeds = [0, 0]"), r"study\.seeds: lists a value twice"),
        (('variant = "no_grid"', 'variant = "nogrid"'), r"methods\[1\]\.variant: expected one of"),
        (
            ("wm_ranks=[2,2,2]", "wm_rank=[2,2,2]"),
            r"methods\[1\]: unknown config key .*wm_rank ",
        ),
        (
            ("watermark.module.wm_ranks=[2,2,2]", "model.mlp_width=4"),
            r"methods\[1\]\.set: .*watermark\.\* only",
        ),
        (("watermark.module.wm_ranks=[2,2,2]", "watermark.seed=3"), r"methods\[1\]\.set: .*study's axes"),
        (
            ('preset = "procedural"\nset = ["data', 'preset = "nope"\nset = ["data'),
            r"scenes\[1\]: no config preset",
        ),
        (('name = "proc_small"', 'name = "x"\nfit = "z"'), r"scenes\[1\]\.preset: not with fit"),
        (('name = "proc_small"', 'name = "proc"'), r"scenes\[1\]\.name: 'proc' is used twice"),
        (('name = "proc_small"', 'name = "proc small"'), r"scenes\[1\]\.name: letters, digits"),
        (
            (
                'name = "proc_small"\npreset = "procedural"\nset = ["data.procedural_size=32"]',
                'name = "x"\nfit = "z"',
            ),
            r"scenes\[1\]\.fit: .* not a fitted run",
        ),
        (
            ('name = "proc_small"', 'name = "x"\ndownscale = -2'),
            r"scenes\[1\]\.downscale: expected a number > 0",
        ),
        (('name = "proc_small"', 'name = "x"\npaper = "legos"'), r"scenes\[1\]\.paper: not one of the paper"),
        (
            ("[[methods]]", '[measure]\nattacks = ["extreme"]\n\n[[methods]]'),
            r"measure\.attacks: unknown 'extreme'",
        ),
        (
            ("[[methods]]", '[measure]\nattack_names = ["blur"]\n\n[[methods]]'),
            r"measure\.attack_names: unknown",
        ),
        (("[[methods]]", '[decoders]\nx = "a.npz"\n\n[[methods]]'), r"decoders\.x: expected a bit length"),
        (
            ('variant = "no_grid"', 'variant = "no_grid"\nscenes = ["proc", "fern"]'),
            r"methods\[1\]\.scenes: fern not among the \[\[scenes\]\] \(proc, proc_small\)",
        ),
        (("[study]", "[study\n"), r"malformed TOML"),
    ],
)
def test_a_bad_spec_is_one_line_naming_its_key(
    tmp_path: Path, mnerf, edit: tuple[str, str], message: str
) -> None:
    old, new = edit
    assert old in SPEC
    path = write_spec(tmp_path, SPEC.replace(old, new, 1))
    with pytest.raises(StudySpecError, match=message):
        load_spec(path)
    code, out, err = mnerf("study", path, "--dry-run")
    assert code == 2 and out == "" and err.startswith("mnerf: error: ") and err.count("\n") == 1


def test_the_studies_in_the_repository_parse(tmp_path: Path) -> None:
    counts = {
        p.stem: len(grid.expand(load_spec(p))) for p in sorted((PROJECT_ROOT / "studies").glob("*.toml"))
    }
    # paper_gpu: two scenes, each 2 seeds × (7 + 7 capacity, 3 bit lengths, 6 ablations, 6 #WMCom, 3 single-
    # message cells); paper_cpu: the same on lego, fern's 3 single-message cells only.
    assert counts == {"paper_cpu": 70, "paper_gpu": 128, "smoke": 2}
    smoke = load_spec(PROJECT_ROOT / "studies" / "smoke.toml")
    assert smoke.scenes[0].preset == "procedural" and smoke.measure.attacks == ("low",)
    wmcom = [
        c for c in grid.expand(load_spec(PROJECT_ROOT / "studies" / "paper_gpu.toml")) if "wmcom24" in c.id
    ]
    assert grid.embed_config(wmcom[0]).watermark.module.wm_ranks == (24, 24, 24)


def test_dry_run_lists_the_cells_and_their_cost_without_running(tmp_path: Path, mnerf) -> None:
    path = write_spec(tmp_path, SPEC)
    out = tmp_path / "study"
    code, text, _ = mnerf("study", path, "--out", out, "--dry-run", "--only", "proc-*", "--rate", "1e6")
    assert code == 0 and not out.exists()
    cells = grid.select(grid.expand(load_spec(path)), only=["proc-*"])
    assert text.startswith(f"mnerf study unit: {len(cells)} of 20 cells")
    for cell in cells:
        assert cell.id in text
    assert "proc_small-" not in text and "fit proc-" in text and " h" in text.splitlines()[-1]
    code, text, _ = mnerf("study", path, "--dry-run", "--shard", "0/2")
    assert code == 0 and "(shard 0/2)" in text
    code, _, err = mnerf("study", path, "--dry-run", "--only", "nothing")
    assert code == 2 and "no cell" in err


def test_a_failure_is_recorded_in_one_line_and_the_folder_is_checked(tmp_path: Path) -> None:
    from mnerf_jax.study import runner

    spec = load_spec(write_spec(tmp_path, SPEC))
    cell = grid.expand(spec)[0]
    out = tmp_path / "study"
    try:
        raise ValueError("a bad\nvalue")
    except ValueError as err:
        assert runner.record_failure(out, cell, err) == "ValueError: a bad value"
    error = json.loads((out / "cells" / cell.id / "error.json").read_text())
    assert error["type"] == "ValueError" and "Traceback" in error["traceback"]
    row = results.row(spec, cell, out)
    assert row["status"] == "failed" and row["error"] == "ValueError: a bad value"
    # Resolved from the spec: the procedural preset's [watermark] section the fit records.
    assert (row["wm_ranks"], row["phase1_steps"], row["cache_source"]) == ("8,8,8", 100, True)
    with pytest.raises(runner.StudyError, match="holds no study"):
        runner.prepare_study_dir(out, spec, join=True)
    fresh = tmp_path / "fresh"
    runner.prepare_study_dir(fresh, spec, join=False)
    with pytest.raises(runner.StudyError, match="pass --resume"):
        runner.prepare_study_dir(fresh, spec, join=False)
    runner.prepare_study_dir(fresh, spec, join=True)
    other = load_spec(write_spec(tmp_path / "other", SPEC.replace('name = "unit"', 'name = "other"')))
    with pytest.raises(runner.StudyError, match="holds study 'unit', not 'other'"):
        runner.prepare_study_dir(fresh, other, join=True)


def test_no_figure_of_the_table_takes_a_settings_name() -> None:
    figures = {*results.FIGURE_COLUMNS, *results.MACHINE_COLUMNS, *results.PAPER_COLUMNS, "id_test"}
    assert not (set(results.SETTING_COLUMNS) - {"views"}) & figures
    assert set(results.evaluation_figures({})) <= figures | {"views"}


def test_the_papers_numbers_match_the_rows_they_stand_beside() -> None:
    figures = paper_numbers.figures()
    assert {f.table for f in figures} >= {
        "tab:ablation",
        "tab:tensor_components_ablation",
        "tab:bit_acc_single",
    }
    row = {
        "paper_scene": "lego",
        "variant": "multinerf",
        "num_ids": 16,
        "bits": 16,
        "wmcom": 8,
        "noised": True,
    }
    found = paper_numbers.match(row)
    assert found["bit_acc"].value == pytest.approx(0.8279) and found["bit_acc"].table == "tab:ablation"
    assert found["params_m"].value == 19.98 and found["size_mb_source"].value == 68.6
    assert paper_numbers.match({**row, "wmcom": 24})["bit_acc"].value == pytest.approx(0.8566)
    # No lego figure for 8 bits: the SYN average of the bit-length table.
    assert paper_numbers.match({**row, "bits": 8})["bit_acc"].table == "tab:ablation_bit_length_sclable"
    single = {**row, "num_ids": 1, "bits": 48, "noised": False}
    assert paper_numbers.match(single)["bit_acc"].value == pytest.approx(0.9486)
    assert (
        paper_numbers.match({**single, "paper_scene": "ficus", "variant": "waterf"})["bit_acc"].value
        == 0.7983
    )
    assert paper_numbers.match({**row, "paper_scene": None}) == {}
    assert paper_numbers.match({**row, "variant": "no_grid"})["bit_acc"].value == pytest.approx(0.516)


# ---------------------------------------------------------------------------------------- end to end

# The tiny fixture's embedding (the same compiled steps), on a far shorter schedule: the phase steps and the
# checkpoint interval are host settings, which the compiled step does not read.
SMOKE_EMBED = [
    *(s for s in TINY_EMBED if not s.startswith(("watermark.schedule.phase", "watermark.checkpoint_every"))),
    "watermark.schedule.phase1_steps=2",
    "watermark.schedule.phase2_steps=4",
    "watermark.checkpoint_every=100",  # saved at the end of each phase only
]
KILL_AT = 4  # the interrupted cell stops here in phase 2 (a checkpoint), then the process is "killed"


def smoke_spec(folder: Path, tiny: TinyRuns) -> Path:
    items = ", ".join(json.dumps(s) for s in SMOKE_EMBED)
    # 12 bits: no decoder ships and [decoders] names none, so those cells fail (first), the others go on.
    return write_spec(
        folder,
        f"""\
        [study]
        name = "smoke_test"
        ids = [2]
        bits = [12, 8]
        seeds = [0, 1]

        [decoders]
        8 = "{tiny.decoder}"

        [measure]
        views = 2
        attacks = ["low"]
        attack_names = ["gaussian_blur"]

        [[scenes]]
        name = "tiny"
        fit = "{tiny.fit}"

        [[methods]]
        name = "multinerf"
        variant = "multinerf"
        set = [{items}]
        """,
    )


def figures(row: dict[str, Any]) -> dict[str, Any]:
    """A row less what the machine measures (times, memory)."""
    return {k: v for k, v in row.items() if k not in results.MACHINE_COLUMNS}


def test_a_study_end_to_end_records_failures_and_resumes_after_a_kill(
    tiny: TinyRuns, tmp_path: Path, mnerf, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mnerf_jax.watermark import embed as wm_embed

    path = smoke_spec(tmp_path / "spec", tiny)
    cells = grid.expand(load_spec(path))
    assert [c.bits for c in cells] == [12, 12, 8, 8]
    first, killed = (c.id for c in cells[2:])

    # Killed while embedding the second 8-bit cell, after a checkpoint at step KILL_AT.
    real, calls = wm_embed.embed, []

    def embed(source: Any, out: Path, *args: Any, **kwargs: Any) -> Any:
        calls.append((Path(out).parent.name, kwargs["resume"]))
        if Path(out).parent.name == killed and len(calls) == 2:
            real(source, out, *args, **{**kwargs, "stop_at": KILL_AT})
            raise KeyboardInterrupt
        return real(source, out, *args, **kwargs)

    monkeypatch.setattr(wm_embed, "embed", embed)
    study = tmp_path / "study"
    code, _, err = mnerf("study", path, "--out", study, "--quiet")
    assert code == 130 and "interrupted" in err
    # The 12-bit cells failed with their reason and the study went on to the next cells.
    rows = json.loads((study / "results.json").read_text())
    assert [r["status"] for r in rows] == ["failed", "failed", "done", "pending"]
    assert all("no shipped decoder for 12 bits" in r["error"] for r in rows[:2])
    assert (study / "cells" / cells[0].id / "error.json").is_file()
    assert (study / "cells" / first / "result.json").is_file()
    assert not (study / "cells" / killed / "result.json").exists()
    code, _, err = mnerf("study", path, "--out", study, "--quiet")
    assert code == 2 and "--resume" in err

    # Resumed: the finished cell is not redone, the killed one continues from its checkpoint.
    code, out, _ = mnerf("study", path, "--out", study, "--quiet", "--resume")
    assert code == 1 and "1 cells run, 1 already done, 2 failed, of 4 selected" in out
    assert calls == [(first, False), (killed, False), (killed, True)]
    rows = json.loads((study / "results.json").read_text())
    assert [r["status"] for r in rows] == ["failed", "failed", "done", "done"]
    # The report, written at the end of the run: the failed cells with their error, the figures beside.
    report = (study / "report.md").read_text()
    assert report.startswith("# Study smoke_test: report") and "--resume" in report
    assert f"- failed `{cells[0].id}`: " in report and "no shipped decoder for 12 bits" in report
    assert (study / "figures" / "robustness-low.png").is_file()

    # The killed cell's figures equal an uninterrupted run's (--only: that cell alone).
    ref = tmp_path / "ref"
    code, out, _ = mnerf("study", path, "--out", ref, "--quiet", "--only", killed)
    assert code == 0 and "1 cells run, 0 already done, 0 failed, of 1 selected" in out
    ref_rows = json.loads((ref / "results.json").read_text())
    assert [r["status"] for r in ref_rows] == ["pending", "pending", "pending", "done"]
    assert figures(rows[3]) == figures(ref_rows[3])
    # Its embedding time counts the killed process up to its checkpoint too, not only the resumed one.
    embed_record = json.loads((study / "cells" / killed / "result.json").read_text())["embed"]
    assert (
        embed_record["run_seconds"] > embed_record["seconds"]
        and rows[3]["embed_s"] == embed_record["run_seconds"]
    )

    done = rows[2]
    assert (done["num_ids"], done["bits"], done["seed"], done["variant"]) == (2, 8, 0, "multinerf")
    assert 0 <= done["bit_acc"] <= 1 and done["psnr_drop"] is not None and done["named"] is not None
    assert done["attack_low_gaussian_blur_bit_acc"] is not None and done["attack_low_bit_acc"] is not None
    assert 0 < done["params_m_watermark"] < done["params_m"] and done["size_mb"] > done["size_mb_watermark"]
    assert done["embed_steps"] == 6 and done["views"] == 2 and done["wall_s"] > 0 and done["peak_rss_mb"] > 0
    assert done["wmcom"] == 4 and done["noised"] is True and done["paper_bit_acc"] is None
    assert "cores" in done["machine"] and f"- machine: {done['machine']}" in report
    assert rows[0]["bits"] == 12 and rows[0]["bit_acc"] is None
    header = (study / "results.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["study", "cell_id", "status"] and "attack_low_named" in header
    assert len(header) == len(set(header))
    assert first in (study / "results.md").read_text()


def test_results_table_says_where_the_time_budget_stopped_an_embedding() -> None:
    spec = types.SimpleNamespace(name="s")
    base = {"phase1_steps": 100, "phase2_steps": 1100, "bit_acc": 0.5}
    rows = [
        {"cell_id": "cut", "status": "done", "embed_steps": 661, "embed_stopped_by_budget": True, **base},
        {"cell_id": "whole", "status": "done", "embed_steps": 1200, "embed_stopped_by_budget": False, **base},
        {"cell_id": "waiting", "status": "pending", "embed_stopped_by_budget": None},
    ]
    lines = {line.split(" | ")[0]: line for line in results.to_markdown(spec, rows).splitlines()}
    assert "| done, stopped by the time budget at step 661 of 1,200 |" in lines["| `cut`"]
    assert "| done |" in lines["| `whole`"] and "| pending |" in lines["| `waiting`"]
