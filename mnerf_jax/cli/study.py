"""``mnerf study``: run a grid of watermarking runs from a spec file into one folder (``mnerf_jax.study``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

NAME = "study"
HELP = (
    "Run a study: scenes × methods × IDs × bit lengths × seeds from SPEC.toml, each scene fitted once, "
    "each cell embedded, evaluated and attacked; resumable, shardable; DIR/results.csv holds every figure, "
    "DIR/report.md the paper's comparisons."
)
EPILOG = """\
The spec's layout is documented in mnerf_jax/study/spec.py and docs/usage.md ("mnerf study"); studies/ holds
examples. Each cell lives in DIR/cells/<cell-id>/ (ID: scene-method-n<IDs>-b<bits>-s<seed>-<hash of its
settings>), each fit in DIR/fits/. A cell is done when its result.json is written; a failing cell is recorded
with its error (DIR/cells/<id>/error.json, the table's error column) and the study goes on.

--dry-run lists the selected cells and an estimated cost in millions of rendered pixels (Mpx): fit
iterations × batch, embedding steps × image pixels × IDs per step, evaluated views × (IDs + 1) × pixels;
--rate converts it to hours with a pixel rate you have measured on your machine.

At the end of a run (and of a --resume) DIR/report.md is written with its figures in DIR/figures/: the
capacity curve, the ablation, #WMCom, bit-length and single-message tables, robustness under the attack
suites, each over its seeds with the paper's figures beside and paired tests between methods, then the failed
cells. --report-only rebuilds the table and the report from DIR alone, running nothing.

Peak memory in the table is the process's peak resident set so far (ru_maxrss), recorded before and after
each cell: run one cell per process (--only CELL-ID) to measure each alone.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("spec", type=Path, metavar="SPEC.toml", help="the study spec")
    parser.add_argument(
        "--out", type=Path, metavar="DIR", help="the study folder (required unless --dry-run)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the study in DIR (finished cells are kept)"
    )
    parser.add_argument(
        "--shard",
        metavar="I/N",
        help="run shard I of N (0 ≤ I < N): the N shards split the cells into groups of about equal "
        "estimated cost; shards may share DIR (a shard joins the study already there)",
    )
    parser.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="PATTERN",
        help="run only the cells whose ID matches this glob, e.g. 'lego-multinerf-*' (repeatable, or "
        "comma-separated)",
    )
    parser.add_argument(
        "--dry-run", action="store_true", help="list the selected cells and their estimated cost; run nothing"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="PX_PER_S",
        help="with --dry-run: your machine's rendered pixels per second, to show the cost in hours",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rebuild DIR's table and report (DIR/report.md, DIR/figures/) from its cells; run nothing",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _fit_scene(config: Any, data: Path | None, out: Path, resume: bool, quiet: bool) -> None:
    from mnerf_jax.cli.fit import fit_run

    fit_run(config, data, out, resume=resume, evaluate=False, quiet=quiet)


def dry_run(spec: Any, cells: list[Any], out: Path | None, rate: float | None) -> str:
    """The listing of ``--dry-run``: each cell with its status in ``out`` and estimated cost, then totals."""
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.study import cost, grid, results, runner

    measure = spec.measure.to_dict()
    setups: dict[str, tuple[Any, cost.SceneShape]] = {}
    fits: dict[str, float] = {}
    lines, totals = [], {"fit": 0.0, "embed": 0.0, "evaluate": 0.0}
    unknown = False
    width = max(len(c.id) for c in cells)
    lines.append(f"{'cell':<{width}}  {'status':<8} {'embed Mpx':>10} {'eval Mpx':>9}  note")
    for cell in cells:
        key = grid.fit_id(cell.scene)
        note = ""
        try:
            config, shape = cost.fit_setup(cell, spec.measure.split, setups)
            if key not in fits:
                done = out is not None and (out / results.FITS_DIR / key / runner.FIT_DONE).is_file()
                fits[key] = cost.fit_mpx(config, cell.scene.fit is not None or done)
            runner.check_decoder(spec, cell.bits)
            estimate = cost.cell_mpx(cell, grid.embed_config(cell, config), shape, spec.measure.views)
        except MnerfError as err:
            estimate, note = {"embed": None, "evaluate": None}, f"cannot run: {err}"
        status = "pending"
        if out is not None:
            if results.finished_result(out, cell, measure) is not None:
                status, estimate = "done", {"embed": 0.0, "evaluate": 0.0}
            elif (results.cell_dir(out, cell) / results.ERROR_FILE).is_file():
                status = "failed"
        for part in ("embed", "evaluate"):
            unknown |= estimate[part] is None and not note
            totals[part] += estimate[part] or 0.0
        embed, evaluate = cost.format_mpx(estimate["embed"]), cost.format_mpx(estimate["evaluate"])
        lines.append(f"{cell.id:<{width}}  {status:<8} {embed:>10} {evaluate:>9}  {note}".rstrip())
    for key, fit in fits.items():
        totals["fit"] += fit
        if fit:
            lines.append(f"fit {key}: {cost.format_mpx(fit)} Mpx")
    total = sum(totals.values())
    line = (
        f"total: {cost.format_mpx(total)} Mpx (fits {cost.format_mpx(totals['fit'])}, embeddings "
        f"{cost.format_mpx(totals['embed'])}, evaluations {cost.format_mpx(totals['evaluate'])})"
    )
    if unknown:
        line += "; some image sizes or view counts are unknown (?), left out"
    if rate:
        line += f"; at {rate:,.0f} px/s: {total * 1e6 / rate / 3600:.2f} h"
    lines.append(line)
    return "\n".join(lines)


def command_line(args: argparse.Namespace) -> str:
    """The ``mnerf study`` command ``args`` stand for (the report's head names it)."""
    import shlex

    argv = ["mnerf", "study", str(args.spec), "--out", str(args.out)]
    argv += ["--resume"] * args.resume + (["--shard", args.shard] if args.shard else [])
    argv += [a for item in args.only for a in ("--only", item)]
    argv += ["--report-only"] * args.report_only
    return shlex.join(argv)


def write_report(spec: Any, out: Path, rows: Any, args: argparse.Namespace) -> Path:
    from mnerf_jax.study import report

    return report.write_report(out, rows, spec.name, str(args.spec), command_line(args))


def report_only(spec: Any, args: argparse.Namespace) -> int:
    """``--report-only``: the table and the report of the study in ``--out``, rebuilt from its cells."""
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.study import results, runner

    if args.dry_run or args.shard or args.only or args.resume:
        raise MnerfError("--report-only runs nothing: it takes no --dry-run, --resume, --shard or --only")
    marker = results.read_json(args.out / runner.STUDY_FILE)
    if marker is None or marker.get("kind") != runner.STUDY_KIND:
        raise MnerfError(f"--out {args.out} holds no study (no {runner.STUDY_FILE})")
    if marker.get("name") != spec.name:
        raise MnerfError(f"--out {args.out} holds study {marker.get('name')!r}, not {spec.name!r}")
    rows = results.write_tables(spec, args.out)
    path = write_report(spec, args.out, rows, args)
    print(f"mnerf study {spec.name}: report of {len(rows)} cells -> {path}")
    return 0


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.study import grid, runner
    from mnerf_jax.study.spec import load_spec

    if args.out is None and not args.dry_run:
        raise MnerfError("--out DIR is required (except with --dry-run)")
    if args.rate is not None and args.rate <= 0:
        raise MnerfError(f"--rate must be a positive pixel rate, got {args.rate}")
    spec = load_spec(args.spec)
    if args.report_only:
        return report_only(spec, args)
    shard = grid.parse_shard(args.shard) if args.shard else None
    only = [p.strip() for item in args.only for p in item.split(",") if p.strip()]
    cells = runner.select_cells(spec, shard, only)
    if args.dry_run:
        if not cells:
            raise MnerfError(f"no cell of study {spec.name!r} is selected (--shard / --only)")
        where = f" (shard {args.shard})" if shard else ""
        print(f"mnerf study {spec.name}: {len(cells)} of {len(grid.expand(spec))} cells{where}")
        print(dry_run(spec, cells, args.out, args.rate))
        return 0
    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    summary = runner.run_study(
        spec,
        args.out,
        _fit_scene,
        resume=args.resume,
        shard=shard,
        only=only,
        progress=not args.quiet,
    )
    report = write_report(spec, summary.out, summary.rows, args)
    print(
        f"mnerf study {spec.name}: {summary.ran} cells run, {summary.skipped} already done, "
        f"{len(summary.failed)} failed, of {summary.selected} selected -> {summary.out / 'results.csv'}, "
        f"{report}"
    )
    for cell_id, error in summary.failed:
        print(f"  failed {cell_id}: {error}", file=sys.stderr)
    return 1 if summary.failed else 0
