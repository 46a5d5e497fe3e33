"""False claims of a watermarked run on clean images, and its decision threshold calibrated on them.

Reads about ``--images`` images without a watermark (the clean model's renders of every view under every
attack of ``--suite``, crops of scikit-image's photographs, procedural images and views of the built-in
procedural scene), decodes them in batches with the run's decoder and counts how many the decision names
as a key. Writes ``WMRUN/false-claims.json`` (counts per source and group, the empirical distribution of the
decision statistic, the best key's corrected p-value, under both tests, the threshold naming at most k of
them with its Clopper–Pearson bound) and ``WMRUN/calibration.json``: per test, the largest threshold whose
false-claim rate is at most ``--rate`` at 95 % (default the run's watermark.reading.id_threshold), which
``mnerf extract --run``, ``evaluate`` and ``attack`` then decide by.

    python scripts/false_claims.py --run WMRUN [--images 10000] [--sources clean,photos,procedural]
        [--suite all] [--views N] [--rate R] [--batch 64] [--seed 0] [--no-calibrate] [--quiet]
    python scripts/false_claims.py --run WMRUN --recalibrate --rate R    # from the saved distribution
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any


def summary(result: dict[str, Any]) -> str:
    """The measurement as text: images and named per source at the run's threshold, then per test the
    calibrated threshold."""
    from mnerf_jax.reader import calibration

    t = result["threshold"]
    lines = [
        f"{'source':<12} {'images':>8} {'named (binomial)':>17} {'named (sign-flip)':>18}   at p < {t:g}"
    ]
    for name, row in result["sources"].items():
        named = row["named"]
        lines.append(f"{name:<12} {row['images']:>8,} {named['binomial']:>17} {named['sign_flip']:>18}")
        if row.get("note"):
            lines.append(f"{'':<12} ({row['note']})")
    named = result["named"]
    lines.append(f"{'all':<12} {result['images']:>8,} {named['binomial']:>17} {named['sign_flip']:>18}")
    for test, entry in result["calibration"].items():
        lines.append(
            f"{test.replace('_', '-')}: threshold {entry['threshold']:.3g} for a rate of "
            f"{calibration.percent(entry['target_rate'])} ({calibration.describe(entry)})"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", type=Path, required=True, metavar="WMRUN", help="a watermarked run")
    parser.add_argument("--images", type=int, default=10_000, help="clean images to read (default 10000)")
    parser.add_argument(
        "--sources", default="clean,photos,procedural", help="comma-separated: clean, photos, procedural"
    )
    parser.add_argument("--split", default="test", help="the split of the clean renders (default test)")
    parser.add_argument("--suite", default="all", help="the mnerf attack suite the clean renders go through")
    parser.add_argument("--views", type=int, default=0, help="views to render when none are saved (0: all)")
    parser.add_argument("--data", type=Path, default=None, help="the scene directory (default: the run's)")
    parser.add_argument(
        "--rate", type=float, default=None, help="the stated false-claim rate to calibrate for"
    )
    parser.add_argument("--batch", type=int, default=64, help="images per decoder call (64)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the crops, textures and attacks")
    parser.add_argument("--no-calibrate", action="store_true", help="measure only: leave calibration.json")
    parser.add_argument(
        "--recalibrate",
        action="store_true",
        help="calibrate at --rate from false-claims.json, reading nothing",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.evaluation import false_claims

    try:
        if args.recalibrate:
            result = false_claims.recalibrate(args.run, args.rate)
        else:
            t0 = time.perf_counter()
            result = false_claims.measure_false_claims(
                args.run,
                args.images,
                [s.strip() for s in args.sources.split(",") if s.strip()],
                split=args.split,
                suite=args.suite,
                views=args.views or None,
                seed=args.seed,
                batch=args.batch,
                rate=args.rate,
                calibrate=not args.no_calibrate,
                data_path=args.data,
                progress=not args.quiet,
            )
            print(summary(result))
            print(f"false_claims: {result['images']:,} images in {time.perf_counter() - t0:.1f} s")
    except (MnerfError, ValueError) as err:
        print(f"false_claims: error: {err}", file=sys.stderr)
        return 2
    written = [false_claims.false_claims_path(args.run)]
    if args.recalibrate or not args.no_calibrate:
        written.append(args.run / "calibration.json")
    if args.recalibrate:
        print(summary(result))
    print(f"false_claims: wrote {', '.join(str(p) for p in written)}")
    return 0


if __name__ == "__main__":
    from mnerf_jax.cli.process import reexec_with_huge_pages

    reexec_with_huge_pages([sys.executable, *sys.argv])  # XLA's buffers on huge pages, as mnerf's commands
    sys.exit(main())
