"""Seconds per embedding step on this machine, and the wall time ``mnerf embed`` would take.

    python scripts/bench_embed_step.py --run RUN [--data PATH] [--num-ids 16] [--bits 16] [--config auto]
                                       [--phase1 6] [--phase2 8] [--set key=value ...] [--json]

RUN is a fitted TensoRF (``mnerf fit``). The script runs ``mnerf embed``'s own code (``embed.embed``, the
shipped decoder, the run's training views) into a temporary folder for ``--phase1`` phase-1 and ``--phase2``
phase-2 steps, and times every step (the wall time between two steps' callbacks, so budget refits, redone
steps and checkpoints are inside it). A step's cost does not depend on how many steps the schedule has, so
the medians of each phase (its first step left out: compilation) times the schedule that the same
``--num-ids``, ``--config`` (default ``auto``: what the plain ``mnerf embed`` runs) and ``--set`` resolve to
(``model.phase_steps``), plus the measured start-up, give the projected wall time of the whole embedding.
The protocol of the README (lego at 1/8, 16 IDs x 16 bits):

    python scripts/bench_embed_step.py --run LEGO_RUN --num-ids 16 --bits 16
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path


@dataclasses.dataclass
class StepClock:
    """``embed.embed``'s ``on_step``: the wall time of every field step (seconds between two steps' callbacks,
    from ``start`` for the first, so budget refits, redone steps and checkpoints are inside it) and its phase.
    ``bench_embed_scale.py`` shares it."""

    start: float = dataclasses.field(default_factory=time.perf_counter)
    stamps: list[float] = dataclasses.field(default_factory=list)
    phases: list[int] = dataclasses.field(default_factory=list)

    def on_step(self, step: int, metrics: dict[str, float]) -> None:
        self.stamps.append(time.perf_counter())
        self.phases.append(int(metrics["phase"]))

    def per_phase(self) -> dict[int, list[float]]:
        """Each phase's step times (seconds), phases 1 and 2."""
        seconds = [b - a for a, b in zip([self.start, *self.stamps[:-1]], self.stamps, strict=True)]
        return {p: [s for s, q in zip(seconds, self.phases, strict=True) if q == p] for p in (1, 2)}

    def medians(self) -> dict[int, float]:
        """Each phase's median step (seconds), its first step left out (compilation); nan without two."""
        return {
            p: statistics.median(v[1:]) if len(v) > 1 else float("nan") for p, v in self.per_phase().items()
        }

    def first_steps_extra(self) -> float:
        """Seconds each phase's first step took beyond its median (compilation), summed over the phases."""
        median = self.medians()
        return sum(v[0] - median[p] for p, v in self.per_phase().items() if v and median[p] == median[p])


def bench(
    run: str,
    data: str | None,
    num_ids: int,
    bits: int,
    phase1: int,
    phase2: int,
    overrides: list[str],
    preset: str = "auto",
) -> dict:
    from mnerf_jax.core import embed_defaults
    from mnerf_jax.watermark import embed, model

    source = embed.load_source(run)
    chosen, settings = preset, list(overrides)
    if preset == embed_defaults.AUTO:  # what the plain `mnerf embed` would run, as it chooses it
        scene = source.load_scene(data, splits=("train",))
        choice = embed.choose_embedding(source, scene, Path("/nonexistent"), num_ids, resume=False)
        if choice is not None:
            chosen, settings = choice.preset, [*choice.settings, *overrides]
    if chosen in (embed_defaults.AUTO, embed_defaults.FROM_RUN):
        chosen = None
    cfg = embed.resolve_config(source, chosen, settings, num_ids, bits).watermark
    schedule = model.phase_steps(cfg)
    short = [
        *overrides,
        f"watermark.schedule.phase1_steps={phase1}",
        f"watermark.schedule.phase2_steps={phase2}",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        clock = StepClock()
        result = embed.embed(
            run,
            Path(tmp) / "wm",
            num_ids,
            bits,
            preset=preset,
            overrides=short,
            data_path=data,
            progress=False,
            on_step=clock.on_step,
        )
    per_phase, median = clock.per_phase(), clock.medians()
    # Start-up (loading, keys, clean references) and each phase's first step, compilation included.
    overhead = sum(v[0] - median[p] for p, v in per_phase.items() if v)
    projected = overhead + schedule[0] * median[1] + schedule[1] * median[2]
    return {
        "num_ids": num_ids,
        "bits": bits,
        "ids_per_step": model.ids_per_step_of(cfg, num_ids),
        "phase1_s_per_step": round(median[1], 3),
        "phase2_s_per_step": round(median[2], 3),
        "first_steps_s": [round(v[0], 1) for v in per_phase.values() if v],
        "redone_steps": result.redone_steps,
        "schedule": list(schedule),
        "projected_s": round(projected),
        "projected_h": round(projected / 3600, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", required=True, help="a fitted TensoRF run (mnerf fit)")
    parser.add_argument("--data", default=None, help="scene directory (default: the run's)")
    parser.add_argument("--num-ids", type=int, default=16)
    parser.add_argument("--bits", type=int, default=16)
    parser.add_argument("--phase1", type=int, default=6, help="phase-1 steps to time (the first compiles)")
    parser.add_argument("--phase2", type=int, default=8, help="phase-2 steps to time (the first compiles)")
    parser.add_argument("--config", default="auto", help="as mnerf embed's --config (default: auto)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    parser.add_argument("--json", action="store_true", help="one JSON line")
    args = parser.parse_args()
    row = bench(args.run, args.data, args.num_ids, args.bits, args.phase1, args.phase2, args.set, args.config)
    if args.json:
        print(json.dumps(row))
        return
    p1, p2 = row["schedule"]
    print(
        f"{row['num_ids']} IDs x {row['bits']} bits, {row['ids_per_step']} per step: phase 1 "
        f"{row['phase1_s_per_step']} s/step, phase 2 {row['phase2_s_per_step']} s/step (first steps "
        f"{row['first_steps_s']} s, {row['redone_steps']} redone); the schedule {p1:,} + {p2:,} steps -> "
        f"{row['projected_s']:,} s ({row['projected_h']} h) projected"
    )


if __name__ == "__main__":
    main()
