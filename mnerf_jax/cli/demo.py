"""``mnerf demo``: the end-to-end job on the built-in procedural scene, as a list of steps.

After the fit, evaluation and renders, the watermark step embeds 4 IDs × 16 bits into the fitted run
(``out/wm``), evaluates every ID on the test views and writes ``out/report`` (:func:`step_watermark`).
It starts from the shipped 16-bit decoder, or ``--decoder FILE``, or ``--decoder fresh`` (a random-init
decoder that phase 2 trains with the field; also what it falls back to, with a line saying so, in a checkout
without the shipped file).

Each step is a function of a ``DemoContext``: it does one thing, records what it produced in
``ctx.rows`` (printed as a table at the end) and may leave objects for later steps in ``ctx.state``.
To extend the demo, add a step function to ``STEPS``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mnerf_jax.core import rundir, xla_cpu
from mnerf_jax.data import PATH_SPLIT
from mnerf_jax.watermark import run as wm_run

NAME = "demo"
HELP = (
    "Fit the built-in procedural scene, evaluate it, render its test views and an orbit GIF, then embed "
    "4 watermark IDs × 16 bits and write a report."
)

DEMO_MARKER = "demo.json"
DEMO_CONFIG = "procedural"
WM_IDS, WM_BITS = 4, 16
# The whole demo's wall clock on 2 CPU cores (the README's promise): the embedding gets what the steps before
# it left, less an allowance for the watermark's evaluation and report, and never more than its preset's.
DEMO_MINUTES = 10.0
FINISH_ALLOWANCE_S = 60.0
MIN_EMBED_MINUTES = 2.0  # a floor for the embedding: a machine too slow for it runs past the ten minutes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=Path, default=Path("mnerf-demo"), help="output folder (default ./mnerf-demo)"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a field of the procedural config (repeatable)",
    )
    parser.add_argument("--frames", type=int, default=48, help="frames of the orbit GIF (default 48)")
    parser.add_argument(
        "--decoder",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"{WM_BITS}-bit decoder for the watermark step (default: the shipped one; "
        "without either, a fresh decoder trained with the field: 'fresh')",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


@dataclasses.dataclass
class DemoContext:
    """What the steps share: where to write, the config, results so far."""

    out: Path
    config: Any
    frames: int = 48
    quiet: bool = False
    decoder: Path | None = None
    decoder_note: str = ""  # printed when the watermark step starts (why a fresh decoder is used)
    # --set items for the embedding, over the [watermark] section the fitted run recorded: the demo's own
    # ``--set watermark.*``, so that they also reach a resumed demo, whose run recorded an earlier section.
    embed_overrides: tuple[str, ...] = ()
    started: float = dataclasses.field(default_factory=time.perf_counter)  # the demo's start (perf_counter)
    rows: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    state: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def run_dir(self) -> Path:
        return self.out / "run"

    def row(self, name: str, value: str) -> None:
        self.rows.append((name, value))


def prepare_out(ctx: DemoContext) -> None:
    """Use ``out`` only if it is new, empty, or an earlier demo's folder (whose run is then resumed)."""

    out = ctx.out
    if out.exists() and not out.is_dir():
        raise rundir.RunError(f"--out {out} is a file, not a directory")
    if out.exists() and any(out.iterdir()) and not (out / DEMO_MARKER).is_file():
        raise rundir.RunError(
            f"--out {out} is not empty and is not a demo folder; choose a new or empty directory"
        )
    out.mkdir(parents=True, exist_ok=True)
    rundir.write_json_atomic(out / DEMO_MARKER, {"kind": "demo", "config": ctx.config.to_dict()})


def step_fit(ctx: DemoContext) -> None:
    """Fit the procedural scene into ``out/run`` (an earlier demo's run is resumed)."""
    from mnerf_jax.cli.fit import fit_run

    resume = rundir.read_marker(ctx.run_dir) is not None
    summary = fit_run(ctx.config, None, ctx.run_dir, resume=resume, evaluate=False, quiet=ctx.quiet)
    ctx.state["fit"] = summary
    ctx.row(
        "training",
        f"{summary['steps']} steps, {summary['train_seconds']:.1f} s, "
        f"{summary['train_rays_per_s']:,.0f} rays/s",
    )


def step_evaluate(ctx: DemoContext) -> None:
    """Evaluate on every test view (``out/run/eval-test.json``)."""
    from mnerf_jax.cli.fit import evaluate_test

    test = evaluate_test(ctx.run_dir, 0, quiet=ctx.quiet)
    ctx.state["test"] = test
    ctx.row(
        "test PSNR / SSIM / LPIPS",
        f"{test['psnr']:.2f} dB / {test['ssim']:.4f} / {test['lpips']:.4f} ({test['views']} views)",
    )


def step_render_test(ctx: DemoContext) -> None:
    """Render every test view to ``out/test/*.png``."""
    from mnerf_jax.cli.render import render_to

    run = _loaded(ctx)
    result = render_to(run, "test", ctx.out / "test", overwrite=True, quiet=ctx.quiet)
    ctx.row("test renders", f"{result['views']} PNGs in {ctx.out / 'test'}")


def step_render_orbit(ctx: DemoContext) -> None:
    """Render an orbit around the scene to ``out/orbit/`` and ``out/orbit/path.gif``."""
    from mnerf_jax.cli.render import render_to

    run = _loaded(ctx)
    result = render_to(
        run, PATH_SPLIT, ctx.out / "orbit", frames=ctx.frames, fps=24, overwrite=True, quiet=ctx.quiet
    )
    ctx.row("orbit", f"{result['views']} frames, {ctx.out / 'orbit' / result['video']}")


def find_decoder(path: Path | None) -> tuple[Path, str]:
    """``(decoder to start the watermark step from, a note to print or "")``.

    ``path`` (``--decoder``) is checked at once (MnerfError: missing, corrupt, not ``WM_BITS`` bits), so a
    bad file stops the demo before it writes anything; without it the shipped decoder is used if present,
    else ``decoder_io.FRESH`` (a random-init decoder that phase 2 trains with the field) and a note saying so.
    """
    from mnerf_jax.reader import decoder_io

    if path is not None:
        if str(path) != decoder_io.FRESH:
            decoder_io.load_decoder(path, expect_bits=WM_BITS)
        return path, ""
    shipped = decoder_io.shipped_decoder_path(WM_BITS)
    if shipped.is_file():
        return shipped, ""
    note = (
        f"no {WM_BITS}-bit decoder is shipped ({shipped} is missing): starting from a fresh decoder "
        "trained with the field in phase 2 (--decoder FILE to start from your own)"
    )
    return Path(decoder_io.FRESH), note


def embedding_budget(minutes: float, reserve_min: float, elapsed_s: float) -> tuple[str, ...]:
    """``--set`` items that fit the embedding into what is left of the demo's ``DEMO_MINUTES`` after
    ``elapsed_s`` seconds: its time budget (the preset's ``minutes``, or less) and phase 3's reserve at the
    preset's share of it; none when the preset's budget fits or is off (0)."""
    left = (DEMO_MINUTES * 60.0 - elapsed_s - FINISH_ALLOWANCE_S) / 60.0
    if minutes <= 0 or left >= minutes:
        return ()
    budget = round(min(max(left, MIN_EMBED_MINUTES), minutes), 3)  # the reserve's share from what is set
    return (
        f"watermark.time_budget.minutes={budget:.3f}",
        f"watermark.phase3.reserve_min={reserve_min * budget / minutes:.3f}",
    )


def step_watermark(ctx: DemoContext) -> None:
    """Embed ``WM_IDS × WM_BITS`` into the fitted run (``out/wm``; an earlier, unfinished one is resumed and
    a finished one reused), evaluate every ID on the test views, write ``out/report``."""
    from mnerf_jax.evaluation import report
    from mnerf_jax.evaluation import watermarked as wm_eval
    from mnerf_jax.watermark import embed

    if ctx.decoder_note:
        print(f"mnerf demo: {ctx.decoder_note}", file=sys.stderr)
    wm_dir = ctx.out / "wm"
    marker = rundir.read_marker(wm_dir) if wm_dir.is_dir() else None
    resume = marker is not None and marker.get("kind") == embed.WM_KIND
    overrides = ctx.embed_overrides
    if not any(item.strip().startswith("watermark.time_budget.") for item in overrides):
        wm = ctx.config.watermark
        elapsed = time.perf_counter() - ctx.started
        overrides += embedding_budget(wm.time_budget.minutes, wm.phase3.reserve_min, elapsed)
    embed.embed(
        ctx.run_dir,
        wm_dir,
        WM_IDS,
        WM_BITS,
        overrides=overrides,
        decoder_path=ctx.decoder,
        resume=resume,
        progress=not ctx.quiet,
    )
    xla_cpu.release_compiled()  # the embedding's compiled programs (memory maps) before the evaluation's
    ev = wm_eval.evaluate_watermarked_run(wm_dir, "test", progress=not ctx.quiet, keep_renders=True)
    renders = {n: r[0] for n, r in ev.pop("_renders").items()}
    clean = ev.pop("_clean")
    ev.pop("_gt")
    reference = clean[0] if clean is not None else next(iter(renders.values()))
    paths = report.write_report(ctx.out / "report", ev, renders, reference)
    ctx.state["watermark"] = {
        "eval": ev,
        "report": paths,
        "rows": report.summary_rows(ev),
        "table": report.format_table(ev),
    }
    ctx.row(
        "watermark",
        f"{ev['num_ids']} IDs × {ev['bits']} bits, bit accuracy "
        f"{ev['bit_accuracy_mean']:.1%} (worst ID {ev['bit_accuracy_min']:.1%}), best match "
        f"right for {ev['identification_accuracy']:.0%} of {ev['views']} views × IDs",
    )
    ctx.row("watermark report", str(paths["markdown"]))


def _loaded(ctx: DemoContext) -> Any:

    if "run" not in ctx.state:
        ctx.state["run"] = wm_run.load_run(ctx.run_dir)
    return ctx.state["run"]


STEPS: list[tuple[str, Callable[[DemoContext], None]]] = [
    ("fit", step_fit),
    ("evaluate", step_evaluate),
    ("render test views", step_render_test),
    ("render orbit", step_render_orbit),
    ("watermark", step_watermark),
]


def print_table(rows: list[tuple[str, str]], file: Any = sys.stdout) -> None:
    width = max((len(name) for name, _ in rows), default=0)
    for name, value in rows:
        print(f"  {name.ljust(width)}  {value}", file=file)


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.cli.process import prepare_process

    prepare_process()
    from mnerf_jax.core.config import load_config

    config = load_config(DEMO_CONFIG, args.set)
    decoder, note = find_decoder(args.decoder)
    watermark_sets = tuple(item for item in args.set if item.strip().startswith("watermark."))
    ctx = DemoContext(
        out=args.out,
        config=config,
        frames=args.frames,
        quiet=args.quiet,
        decoder=decoder,
        decoder_note=note,
        embed_overrides=watermark_sets,
    )
    prepare_out(ctx)
    for i, (title, step) in enumerate(STEPS, 1):
        if not ctx.quiet:
            print(f"[{i}/{len(STEPS)}] {title}", file=sys.stderr)
        step(ctx)
    ctx.row("total time", f"{time.perf_counter() - ctx.started:.1f} s")
    print_summary(ctx)
    return 0


def print_summary(ctx: DemoContext, file: Any = None) -> None:
    """The steps' table, then the watermark evaluation's table when that step ran (to ``file``, default
    stdout)."""
    file = sys.stdout if file is None else file
    print(f"mnerf demo: {ctx.out}", file=file)
    print_table(ctx.rows, file=file)
    if "watermark" in ctx.state:
        print(f"\nwatermark ({ctx.out / 'wm'}, test views):", file=file)
        print(ctx.state["watermark"]["table"], file=file)
