"""The geometry search's options, shared by ``mnerf extract`` and ``mnerf attack``
(``reader.geometry_search``; the defaults are the run's ``watermark.reading.search*`` settings)."""

from __future__ import annotations

import argparse
from typing import Any


def add_arguments(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--search``, ``--search-scales``, ``--search-degrees`` (``mnerf extract``, ``mnerf attack``); their
    defaults are the run's ``watermark.reading.search*`` settings."""
    parser.add_argument(
        "--search",
        choices=("none", "scale", "rotation", "geometry"),
        default=None,
        help=f"{prefix}read each image again as if rescaled (scale), rotated (rotation) or both (geometry), "
        "each candidate undone, and keep the best-supported key; its p-value is corrected for the "
        "candidates too (default: the run's watermark.reading.search, none unless set)",
    )
    parser.add_argument(
        "--search-scales",
        default=None,
        metavar="S,...",
        help="the scales the search tries (0.75: the image was shrunk to 75 %%; default: the run's "
        "watermark.reading.search_scales, 0.5,0.75,1.5 unless set)",
    )
    parser.add_argument(
        "--search-degrees",
        default=None,
        metavar="D,...",
        help="the anticlockwise rotations the search tries, in degrees, given with = when the first is "
        "negative (--search-degrees=-15,15; default: the run's watermark.reading.search_degrees, "
        "-30,-15,-5,5,15,30 unless set)",
    )


def of_args(args: argparse.Namespace) -> dict[str, Any]:
    """The search options of ``args`` as keywords of ``identify_images`` and ``evaluate_attacks`` (None:
    the run's setting); MnerfError for a grid that is not comma-separated numbers."""
    from mnerf_jax.reader import geometry_search

    def numbers(text: str | None, option: str) -> tuple[float, ...] | None:
        return None if text is None else geometry_search.parse_numbers(text, option)

    return {
        "search": args.search,
        "search_scales": numbers(args.search_scales, "--search-scales"),
        "search_degrees": numbers(args.search_degrees, "--search-degrees"),
    }
