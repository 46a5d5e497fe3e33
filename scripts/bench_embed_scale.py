"""How ``mnerf embed``'s step time and peak memory grow with the image's pixels and with the number of IDs.

    python scripts/bench_embed_scale.py --run RUN [--sizes 100,200,400] [--num-ids 4,16,64] [--bits 16]
                                        [--steps 4] [--phase3-views 8] [--config auto] [--decoder FILE]
                                        [--data PATH] [--set key=value ...] [--json] [--out FILE.json]

RUN is a fitted TensoRF (``mnerf fit``). The field is resolution-independent, so the run's training views are
made at each side S (px, the width; the height keeps the aspect ratio) by loading its scene again with another
``data.downscale`` (the native width / S; the loader resamples the images and scales the intrinsics) or, for
the procedural scene, another ``data.procedural_size``. For each side and each ID count, in a process of its
own (so that ``ru_maxrss`` is that configuration's alone), the script runs ``mnerf embed``'s own code
(``embed.embed`` into a temporary folder, the shipped decoder for ``--bits``, ``--config`` auto by default:
the settings the plain command chooses for that size, IDs and machine) with its schedule cut to ``--steps``
steps of each phase. Nothing in the embedding is changed: the script only wraps, inside the child process,
the functions that load the run (to hand it the rescaled one), choose and resolve the config (to record the
choice and the full schedule, and to cut it short), build the sample cache, run the field's loop, checkpoint,
render phase 3's set and make phase 3's step (to time them).

Figures per (side, IDs):

- ``cache_s``: building the sample cache (``sample_cache.build_cache``), once per run; ``cache_mb`` its size.
  None when the choice is deferred patches (``cache_source=false``: no cache).
- ``startup_s``: from ``embed.embed``'s start to the field's first step (loading, keys, cache, clean renders).
- ``phase1_step_s``, ``phase2_step_s``: the median field step of each phase (seconds), its first step left
  out (compilation; the surplus is ``compile_s``); ``field_step_s`` is phase 2's, most of the schedule.
- ``phase3_step_s``: the median phase-3 decoder step (first left out); ``phase3_setup_s`` from the field's
  end to phase 3's first step, with ``--phase3-views`` novel views rendered (the default embedding renders
  ``phase3.views``: the projection adds the views left out at the steady seconds per view of every ID's and
  the clean model's renders; ``phase3_set_mb`` / ``phase3_set_mb_projected``: the refit set's memory as
  rendered / with every view). None when the chosen embedding has no phase 3.
- ``field_peak_rss_mb``: peak RSS at the field's end (process-wide, MB); ``peak_rss_mb`` after phase 3 too
  (with ``--phase3-views`` views); ``device_peak_mb`` the accelerator's peak where it reports one.
- ``projected_s``: the whole default embedding at this size: start-up, the schedule's field steps at the
  medians plus their checkpoints, phase 3's set and steps, ended by the time budget as the loop ends it
  (``budget_ends_field``: the field stops before its schedule; ``field_steps_projected`` where, and
  ``phase3_steps_projected`` phase 3's schedule sized to the minutes left); ``unbudgeted_s`` without it.
- ``choice``: the auto choice (``Choice.to_dict()``; None with another ``--config``), ``schedule``,
  ``ids_per_step``, ``cache_source``, ``time_budget_min``.

The growth line: log-log slopes (least squares) of the phase-2 step time, peak RSS and projected time
against pixels (over the sizes, for each ID count) and against IDs (over the ID counts, for each size).

The protocol (issue 52): lego's ``quick`` fit at 1/8, 100², 200², 400² on the CPU, 4, 16, 64 IDs × 16 bits,
and 800² on a GPU:

    python scripts/bench_embed_scale.py --run LEGO_RUN --sizes 100,200,400 --num-ids 4,16,64 --json \\
        --out scale-cpu.json
    python scripts/bench_embed_scale.py --run LEGO_RUN --sizes 800 --num-ids 4,16,64 --out scale-gpu.json

Without ``--json`` a table (image, IDs, cache s, phase-2 step s, phase-3 step s, peak RSS MB, projected
minutes) is printed row by row, then the growth lines. The exit status is 1 when a configuration failed (its
row holds the error).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_embed_step import StepClock  # noqa: E402  (the scripts folder is no package)

# Every row's keys (a configuration that failed has size, num_ids and error instead).
ROW_KEYS = (
    "side",
    "num_ids",
    "bits",
    "image",
    "pixels",
    "views",
    "backend",
    "choice",
    "cache_source",
    "ids_per_step",
    "schedule",
    "phase3_schedule",
    "time_budget_min",
    "startup_s",
    "cache_s",
    "cache_mb",
    "compile_s",
    "checkpoint_s",
    "phase1_step_s",
    "phase2_step_s",
    "field_step_s",
    "phase3_setup_s",
    "phase3_views",
    "phase3_step_s",
    "phase3_set_mb",
    "phase3_set_mb_projected",
    "field_peak_rss_mb",
    "peak_rss_mb",
    "device_peak_mb",
    "projected_s",
    "projected_min",
    "unbudgeted_s",
    "field_steps_projected",
    "phase3_steps_projected",
    "budget_ends_field",
)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _device_peak_mb() -> float | None:
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else round(peak / 2**20)


def _median(values: Sequence[float]) -> float | None:
    """The median without the first value (compilation); None without two."""
    return statistics.median(values[1:]) if len(values) > 1 else None


def _round(value: float | None, digits: int = 3) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, digits)


# --------------------------------------------------------------------------------------------- one config


def scaled_source(source: Any, side: int, data: str | None) -> Any:
    """``source`` (a ``LoadedRun``) whose scene loads with training views ``side`` px wide: another
    ``data.procedural_size`` for the procedural scene, else ``data.downscale`` = the images' native width /
    ``side`` (at least 1: a side past the native width is the native width)."""
    cfg = source.config.data
    if cfg.dataset == "procedural":
        data_cfg = dataclasses.replace(cfg, procedural_size=int(side))
    else:
        native = dataclasses.replace(
            source, config=dataclasses.replace(source.config, data=dataclasses.replace(cfg, downscale=1.0))
        )
        width = int(native.load_scene(data, splits=("train",), max_views=1).split("train").images.shape[2])
        # A hair under native / side: scaled_size truncates width / downscale, which must land on side.
        data_cfg = dataclasses.replace(cfg, downscale=max(1.0, width / side * (1 - 1e-9)))
    return dataclasses.replace(source, config=dataclasses.replace(source.config, data=data_cfg))


def short_overrides(config: Any, steps: int, phase3_views: int) -> list[str]:
    """The timed run's schedule: ``steps`` steps of each phase the full ``config`` has (phase 3's novel views
    cut to ``phase3_views``; -1 keeps them)."""
    cfg = config.watermark
    p1, p2 = cfg.schedule.phase1_steps, cfg.schedule.phase2_steps
    short = [
        f"watermark.schedule.phase1_steps={min(p1, steps)}",
        f"watermark.schedule.phase2_steps={min(p2, steps)}",
    ]
    if cfg.phase3.steps:
        short.append(f"watermark.phase3.steps={min(cfg.phase3.steps, steps)}")
        if phase3_views >= 0:
            short.append(f"watermark.phase3.views={min(cfg.phase3.views, phase3_views)}")
    return short


def measure(
    run: str,
    side: int,
    num_ids: int,
    bits: int,
    *,
    steps: int = 4,
    phase3_views: int = 8,
    preset: str = "auto",
    overrides: Sequence[str] = (),
    decoder: str | None = None,
    data: str | None = None,
) -> dict[str, Any]:
    """One configuration in this process (``--child``): the timed, shortened embedding and its projection."""
    import jax
    import numpy as np

    from mnerf_jax.watermark import embed, model, phase3, sample_cache
    from mnerf_jax.watermark.loop import EmbedLoop

    scaled = scaled_source(embed.load_source(run), side, data)
    seen: dict[str, Any] = {"saves": [], "phase3_steps": [], "view_s": {}}
    clock = StepClock()

    def wrap(owner: Any, name: str, around: Callable[..., Any]) -> None:
        inner = getattr(owner, name)
        setattr(owner, name, lambda *a, **k: around(inner, *a, **k))

    def load_source(inner: Callable, run_dir: Any) -> Any:
        return scaled

    def choose(inner: Callable, *args: Any) -> Any:
        seen["choice"] = inner(*args)
        return seen["choice"]

    def resolve(inner: Callable, source: Any, preset: Any, items: Sequence[str], n: int, b: int) -> Any:
        seen["config"] = full = inner(source, preset, items, n, b)  # the default embedding's, in full
        return inner(source, preset, [*items, *short_overrides(full, steps, phase3_views)], n, b)

    def build_cache(inner: Callable, *args: Any) -> Any:
        tick = time.perf_counter()
        cache = inner(*args)
        seen["cache_s"], seen["cache_bytes"] = time.perf_counter() - tick, cache.nbytes
        return cache

    def loop_run(inner: Callable, self: Any, *args: Any) -> Any:
        seen["field_start"] = clock.start = time.perf_counter()
        seen["views"], seen["height"], seen["width"] = (int(n) for n in self.split.images.shape[:3])
        result = inner(self, *args)
        seen["field_end"], seen["field_rss"] = time.perf_counter(), _rss_mb()
        return result

    def save(inner: Callable, self: Any, state: Any) -> None:
        tick = time.perf_counter()
        inner(self, state)
        seen["saves"].append(time.perf_counter() - tick)

    def refit_set(inner: Callable, *args: Any, **kwargs: Any) -> Any:
        result = inner(*args, **kwargs)
        renders, negatives = np.asarray(result.renders), np.asarray(result.negatives)
        seen["refit_set_bytes"] = int(renders.nbytes + negatives.nbytes)
        seen["refit_views"] = int(renders.shape[1])
        # A novel view more: every ID's render of it and the clean model's (a negative).
        seen["refit_view_bytes"] = int(
            renders.nbytes // renders.shape[1] + negatives.nbytes // len(negatives)
        )
        return result

    def view_renders(inner: Callable, run: Any, cameras: Any, *args: Any, **kwargs: Any) -> Any:
        # Phase 3's renders (every ID's, the clean model's), each call's views timed one by one.
        stamps = [time.perf_counter()]
        given = kwargs.get("on_view")

        def on_view(i: int, rgb: Any) -> None:
            stamps.append(time.perf_counter())
            if given is not None:
                given(i, rgb)

        result = inner(run, cameras, *args, **{**kwargs, "on_view": on_view})
        passes = [b - a for a, b in zip(stamps[:-1], stamps[1:], strict=True)]
        # Steady seconds per view: the median pass after the first (which compiles; so may a later one, as
        # the sample budgets settle), times the passes per view (the last call's: the novel views).
        steady = statistics.median(passes[1:]) if len(passes) > 1 else sum(passes)
        seen["view_s"][inner.__name__] = steady * len(passes) / max(len(cameras), 1)
        return result

    def refit_step(inner: Callable, *args: Any) -> Any:
        seen["phase3_start"] = time.perf_counter()
        step = inner(*args)

        def timed(*a: Any) -> Any:
            tick = time.perf_counter()
            out = jax.block_until_ready(step(*a))
            seen["phase3_steps"].append(time.perf_counter() - tick)
            return out

        return timed

    wrap(embed, "load_source", load_source)
    wrap(embed, "choose_embedding", choose)
    wrap(embed, "resolve_config", resolve)
    wrap(sample_cache, "build_cache", build_cache)
    wrap(phase3, "render_refit_set", refit_set)
    wrap(phase3, "make_refit_step", refit_step)
    wrap(phase3.wm_run, "render_every_id", view_renders)
    wrap(phase3.runs, "render_views", view_renders)
    run_inner, save_inner = EmbedLoop.run, EmbedLoop.save
    EmbedLoop.run = lambda self, *a: loop_run(run_inner, self, *a)  # type: ignore[method-assign]
    EmbedLoop.save = lambda self, s: save(save_inner, self, s)  # type: ignore[method-assign]

    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        embed.embed(
            run,
            Path(tmp) / "wm",
            num_ids,
            bits,
            preset=preset,
            overrides=list(overrides),
            decoder_path=decoder,
            data_path=data,
            progress=False,
            on_step=clock.on_step,
        )
    cfg = seen["config"].watermark
    views, height, width = seen["views"], seen["height"], seen["width"]
    medians = clock.medians()
    m1, m2 = (None if math.isnan(medians[p]) else medians[p] for p in (1, 2))
    m3 = _median(seen["phase3_steps"])
    phase3_setup = seen["phase3_start"] - seen["field_end"] if "phase3_start" in seen else None
    row: dict[str, Any] = {
        "side": side,
        "num_ids": num_ids,
        "bits": bits,
        "image": f"{height}x{width}",
        "pixels": height * width,
        "views": views,
        "backend": jax.default_backend(),
        "choice": None if seen.get("choice") is None else seen["choice"].to_dict(),
        "cache_source": bool(cfg.schedule.cache_source),
        "ids_per_step": model.ids_per_step_of(cfg, num_ids),
        "schedule": [cfg.schedule.phase1_steps, cfg.schedule.phase2_steps],
        "phase3_schedule": int(cfg.phase3.steps),
        "time_budget_min": cfg.time_budget.minutes or None,
        "startup_s": _round(seen["field_start"] - start, 2),
        "cache_s": _round(seen.get("cache_s"), 2),
        "cache_mb": _round(seen["cache_bytes"] / 2**20, 1) if "cache_bytes" in seen else None,
        "compile_s": _round(clock.first_steps_extra(), 2),
        "checkpoint_s": _round(statistics.median(seen["saves"]), 2) if seen["saves"] else None,
        "phase1_step_s": _round(m1, 4),
        "phase2_step_s": _round(m2, 4),
        "field_step_s": _round(m2 if m2 is not None else m1, 4),
        "phase3_setup_s": _round(phase3_setup, 2),
        "phase3_views": int(cfg.phase3.views) if cfg.phase3.steps else None,
        "phase3_step_s": _round(m3, 4),
        "phase3_set_mb": _round(seen["refit_set_bytes"] / 2**20, 1) if "refit_set_bytes" in seen else None,
        "phase3_set_mb_projected": None,
        "field_peak_rss_mb": round(seen["field_rss"]),
        "peak_rss_mb": round(_rss_mb()),
        "device_peak_mb": _device_peak_mb(),
    }
    if "refit_set_bytes" in seen:
        extra = (cfg.phase3.views - (seen["refit_views"] - views)) * seen["refit_view_bytes"]
        row["phase3_set_mb_projected"] = _round((seen["refit_set_bytes"] + extra) / 2**20, 1)
    row.update(project(row, cfg, seen, views))
    return row


def project(row: dict[str, Any], cfg: Any, seen: dict[str, Any], views: int) -> dict[str, Any]:
    """The whole default embedding's wall time from the measured pieces, the time budget sizing the field
    and phase 3 as ``loop.EmbedLoop.run`` and ``phase3.refit_decoder`` do."""
    from mnerf_jax.watermark import time_budget as clock_lib

    p1, p2 = row["schedule"]
    m1 = row["phase1_step_s"] or row["phase2_step_s"] or 0.0
    m2 = row["phase2_step_s"] or m1
    save_s = row["checkpoint_s"] or clock_lib.FIRST_CHECKPOINT_S
    every = max(int(cfg.checkpoint_every), 1)
    field = [m1] * p1 + [m2] * p2
    budget = cfg.time_budget.minutes * 60.0 or None
    kept = cfg.phase3.reserve_min * 60.0 if (budget and cfg.phase3.steps) else 0.0

    def field_end(limit: float | None) -> tuple[float, int]:
        """Seconds at the field's end and its steps, within ``limit`` seconds as the loop ends it."""
        now = (row["startup_s"] or 0.0) + (row["compile_s"] or 0.0)
        done, horizon = 0, len(field)
        for step_s in field:
            sizing = limit and kept and p2 and done == p1 + clock_lib.SIZING_STEPS + 1
            if sizing:  # the field's schedule sized to the steps that fit, as the loop sizes it
                left = limit - now - kept - save_s - clock_lib.RESERVE_S
                horizon = clock_lib.steps_that_fit(done, left, m2, len(field))
            if done >= horizon:
                break
            # The loop's test before a step: that step, the time kept for phase 3, a checkpoint, the reserve.
            if limit and done and now + step_s + kept + save_s + clock_lib.RESERVE_S > limit:
                break
            done += 1
            now += step_s + (save_s if done % every == 0 or done == p1 else 0.0)
        return now + (save_s if done % every else 0.0), done  # the last checkpoint

    now, done = field_end(budget)
    unbudgeted, _ = field_end(None)
    ends_early = done < len(field)
    p3 = None
    if cfg.phase3.steps and row["phase3_step_s"] is not None and row["phase3_setup_s"] is not None:
        # Phase 3's set: the setup as measured, and the novel views it did not render at the steady seconds
        # per view of every ID's renders and of the clean model's.
        benched = seen.get("refit_views", views) - views
        setup = row["phase3_setup_s"] + (cfg.phase3.views - benched) * sum(seen["view_s"].values())
        first = seen["phase3_steps"][0] - row["phase3_step_s"] if seen["phase3_steps"] else 0.0
        m3 = row["phase3_step_s"]
        unbudgeted += setup + first + cfg.phase3.steps * m3 + save_s
        now += setup + first
        p3 = cfg.phase3.steps
        if budget:  # phase 3's schedule sized to the minutes left
            left = budget - now - save_s - clock_lib.RESERVE_S
            p3 = clock_lib.steps_that_fit(0, left, m3, p3)
        now += p3 * m3 + save_s
    elif cfg.phase3.steps:
        now = unbudgeted = float("nan")  # phase 3 did not run (the budget left it no time)
    projected = now if budget else unbudgeted
    return {
        "projected_s": _round(projected, 0),
        "projected_min": _round(projected / 60.0, 1),
        "unbudgeted_s": _round(unbudgeted, 0),
        "field_steps_projected": done,
        "phase3_steps_projected": p3,
        "budget_ends_field": ends_early,
    }


# --------------------------------------------------------------------------------------------- all configs


def slope(xs: Sequence[float], ys: Sequence[float | None]) -> float | None:
    """Least-squares slope of log y against log x (None with fewer than two positive points)."""
    points = [(math.log(x), math.log(y)) for x, y in zip(xs, ys, strict=True) if y and x > 0 and y > 0]
    if len({x for x, _ in points}) < 2:
        return None
    mx = statistics.fmean(x for x, _ in points)
    my = statistics.fmean(y for _, y in points)
    num = sum((x - mx) * (y - my) for x, y in points)
    return round(num / sum((x - mx) ** 2 for x, _ in points), 2)


GROWTH_OF = ("field_step_s", "peak_rss_mb", "projected_s")


def growth(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, dict[str, float | None]]]:
    """``{"pixels": {figure: {"N IDs": exponent}}, "ids": {figure: {"S px": exponent}}}``."""
    ok = [r for r in rows if "error" not in r]
    by_pixels: dict[str, dict[str, float | None]] = {f: {} for f in GROWTH_OF}
    by_ids: dict[str, dict[str, float | None]] = {f: {} for f in GROWTH_OF}
    for n in sorted({r["num_ids"] for r in ok}):
        group = [r for r in ok if r["num_ids"] == n]
        for f in GROWTH_OF:
            by_pixels[f][f"{n} IDs"] = slope([r["pixels"] for r in group], [r[f] for r in group])
    for s in sorted({r["side"] for r in ok}):
        group = [r for r in ok if r["side"] == s]
        for f in GROWTH_OF:
            by_ids[f][f"{s} px"] = slope([r["num_ids"] for r in group], [r[f] for r in group])
    return {"pixels": by_pixels, "ids": by_ids}


def child_command(args: argparse.Namespace, side: int, num_ids: int) -> list[str]:
    spec = {
        "run": args.run,
        "side": side,
        "num_ids": num_ids,
        "bits": args.bits,
        "steps": args.steps,
        "phase3_views": args.phase3_views,
        "preset": args.config,
        "overrides": args.set,
        "decoder": args.decoder,
        "data": args.data,
    }
    return [sys.executable, str(Path(__file__).resolve()), "--run", args.run, "--child", json.dumps(spec)]


def run_child(command: Sequence[str], side: int, num_ids: int) -> dict[str, Any]:
    """One configuration in a process of its own: its row, or ``{side, num_ids, error}``."""
    proc = subprocess.run(list(command), capture_output=True, text=True)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
        return {"side": side, "num_ids": num_ids, "error": tail[0]}
    return json.loads(lines[-1])


def bench(args: argparse.Namespace, on_row: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Every (side, IDs) of ``args`` in a child process; the rows and their growth."""
    rows = []
    for side in args.sizes:
        for n in args.num_ids:
            row = run_child(child_command(args, side, n), side, n)
            rows.append(row)
            if on_row is not None:
                on_row(row)
    protocol = {k: getattr(args, k) for k in ("run", "sizes", "num_ids", "bits", "steps", "phase3_views")}
    return {**protocol, "config": args.config, "set": args.set, "rows": rows, "growth": growth(rows)}


# --------------------------------------------------------------------------------------------- output


def _cell(value: Any, fmt: str = "{:.3g}") -> str:
    return "-" if value is None else fmt.format(value)


def table_line(row: dict[str, Any]) -> str:
    """One row of the table (or the configuration's error)."""
    if "error" in row:
        return f"{row['side']:>5}  {row['num_ids']:>4}  failed: {row['error']}"
    early = " (budget ends field)" if row["budget_ends_field"] else ""
    cells = (
        _cell(row["cache_s"]),
        _cell(row["field_step_s"]),
        _cell(row["phase3_step_s"]),
        f"{row['peak_rss_mb']:,}",
        _cell(row["projected_min"], "{:.1f}"),
    )
    return f"{row['image']:>9}  {row['num_ids']:>4}  " + "  ".join(f"{c:>8}" for c in cells) + early


TABLE_HEAD = f"{'image':>9}  {'IDs':>4}  " + "  ".join(
    f"{c:>8}" for c in ("cache s", "field s", "phase3 s", "RSS MB", "proj min")
)


def growth_line(result: dict[str, Any]) -> str:
    """``growth: ...`` exponents against pixels and against IDs."""

    def part(figures: dict[str, dict[str, float | None]]) -> str:
        return "; ".join(
            f"{f} " + ", ".join(f"{k}: {_cell(v, '{:.2f}')}" for k, v in per.items())
            for f, per in figures.items()
        )

    g = result["growth"]
    return f"growth ∝ pixels^a: {part(g['pixels'])}\ngrowth ∝ IDs^b: {part(g['ids'])}"


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", required=True, help="a fitted TensoRF run (mnerf fit)")
    parser.add_argument(
        "--sizes", type=_ints, default=[100, 200, 400], help="image sides (px), comma-separated"
    )
    parser.add_argument("--num-ids", type=_ints, default=[4, 16, 64], help="ID counts, comma-separated")
    parser.add_argument("--bits", type=int, default=16)
    parser.add_argument("--steps", type=int, default=4, help="timed steps of each phase (the first compiles)")
    parser.add_argument(
        "--phase3-views", type=int, default=8, help="phase 3's novel views rendered (-1: the config's)"
    )
    parser.add_argument("--config", default="auto", help="mnerf embed --config (default: auto)")
    parser.add_argument("--decoder", default=None, help="decoder file (default: the shipped one for --bits)")
    parser.add_argument("--data", default=None, help="scene directory (default: the run's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        spec = json.loads(args.child)
        run, side, num_ids, bits = (spec.pop(k) for k in ("run", "side", "num_ids", "bits"))
        print(json.dumps(measure(run, side, num_ids, bits, **spec)), flush=True)
        return 0
    if not args.json:
        print(TABLE_HEAD, flush=True)
    result = bench(args, None if args.json else lambda row: print(table_line(row), flush=True))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    if args.json:
        print(json.dumps(result))
    else:
        print(growth_line(result))
    return 0 if all("error" not in r for r in result["rows"]) else 1


if __name__ == "__main__":
    sys.exit(main())
