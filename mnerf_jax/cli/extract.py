"""``mnerf extract``: decode the watermark bits of image files, or identify their watermark ID with a
watermarked run's keys and decoder (best-matching key, bit accuracy, binomial and sign-flip p-values)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from mnerf_jax.cli import search_options

NAME = "extract"
HELP = (
    "Decode the watermark bits of images with a HiDDeN decoder (default: the shipped 16-bit one), or "
    "with --run WMRUN identify each image's watermark ID (bit accuracy, p-values)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="image files")
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--run",
        type=Path,
        default=None,
        metavar="WMRUN",
        help="watermarked run (mnerf embed): decode with its decoder, match its keys",
    )
    source.add_argument(
        "--decoder",
        type=Path,
        default=None,
        help="decoder file (.npz from train-decoder or a conversion); default: shipped decoder",
    )
    parser.add_argument(
        "--bits",
        type=int,
        default=None,
        help="message length: picks the shipped decoder (8, 16, 32 or 48), or checks --decoder",
    )
    parser.add_argument(
        "--threshold",
        type=float,
        default=None,
        metavar="P",
        help="with --run: claim an ID only when its Bonferroni-corrected p-value is below P "
        "(default: the run's calibrated threshold (scripts/false_claims.py), else its "
        "watermark.reading.id_threshold, 1e-3 unless set)",
    )
    parser.add_argument(
        "--test",
        choices=("binomial", "sign_flip"),
        default=None,
        help="with --run: the p-value that decides: binomial (matching bits) or sign_flip "
        "(matching bits weighted by the decoder's confidence); both are printed "
        "(default: the run's watermark.reading.id_test, binomial unless set)",
    )
    parser.add_argument(
        "--read-jitter",
        type=int,
        default=None,
        metavar="R",
        help="average the decoder's logits over the read windows moved by up to R pixels "
        "((2R + 1)² reads; default: as the run's decoder file records, 0 for others)",
    )
    search_options.add_arguments(parser, "with --run: ")
    parser.add_argument("--batch", type=int, default=32, help="images per decoder call (32)")
    parser.add_argument("--json", action="store_true", help="one JSON object per image instead of text")


def extract_records(args: argparse.Namespace) -> tuple[list[dict], object]:
    """Decode ``args.images``: one record (path, bits string, logits) per image, and the decoder used."""
    from mnerf_jax.reader import extract, read_window

    if args.search not in (None, "none") or args.search_scales or args.search_degrees:
        from mnerf_jax.core.errors import MnerfError

        raise MnerfError(
            "--search needs --run WMRUN: the search keeps the read that best matches one of the run's keys"
        )
    decoder = extract.resolve_decoder(args.decoder, args.bits)
    # A watermarked run's decoder.npz records the run's read window and jitter; others read the whole image.
    read = read_window.of_metadata(decoder.metadata)
    if args.read_jitter is not None:
        read = dataclasses.replace(read, jitter=read_window.check_jitter(args.read_jitter))
    logits = extract.decode_paths(decoder.variables, args.images, decoder.wavelet, args.batch, read)
    records = []
    for path, row in zip(args.images, logits, strict=True):
        records.append(
            {
                "image": str(path),
                "bits": extract.bits_to_string(extract.bits_from_logits(row)),
                "logits": [round(float(v), 4) for v in row],
            }
        )
    return records, decoder


def identification_line(record: dict[str, Any]) -> str:
    """One record of ``wm_eval.identify_images`` as text: the claimed ID or "no watermark", the best match's
    bit accuracy and its corrected p-value."""
    figures = (
        f"best ID {record['best_id']}, bit accuracy {record['bit_accuracy']:.2%}, "
        f"p = {record['p_corrected']:.3g} binomial (uncorrected {record['p_value']:.3g}), "
        f"{record['p_corrected_sign_flip']:.3g} sign-flip"
    )
    if record.get("candidate") and (record["candidate"]["scale"], record["candidate"]["degrees"]) != (1, 0):
        from mnerf_jax.reader.geometry_search import Candidate

        figures += f", read as {Candidate(**record['candidate']).label}"
    if record.get("reads", 1) > 1:
        figures += f", corrected over {record['reads']} reads"
    if record["id"] < 0:
        why = (
            "tie between keys"
            if record["best_id"] < 0
            else f"{record['test'].replace('_', '-')} p ≥ {record['threshold']:g}"
        )
        return f"no watermark ({why}; {figures})"
    return f"ID {record['id']}  ({figures})"


def run_identify(args: argparse.Namespace) -> int:
    """``--run WMRUN``: the ID of each image (``wm_eval.identify_images``)."""
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.evaluation import watermarked as wm_eval

    if args.bits is not None:
        raise MnerfError(
            "--bits applies to --decoder or the shipped decoders, not --run (the run's decoder "
            "fixes the message length)"
        )
    records = wm_eval.identify_images(
        args.run,
        args.images,
        args.threshold,
        args.batch,
        args.test,
        args.read_jitter,
        **search_options.of_args(args),
    )
    first = records[0]
    if first["min_attainable_p"] >= first["threshold"]:
        print(
            f"mnerf extract: note: {first.get('reads', 1)} read(s) × the run's keys put the smallest "
            f"corrected p-value at {first['min_attainable_p']:.3g}, not below the threshold "
            f"{first['threshold']:g}: no image can be named (fewer search candidates, or a higher "
            "--threshold)",
            file=sys.stderr,
        )
    if args.json:
        for record in records:
            print(json.dumps({**record, "run": str(args.run)}))
        return 0
    width = max(len(r["image"]) for r in records)
    for record in records:
        print(f"{record['image']:<{width}}  {identification_line(record)}")
    print(f"mnerf extract: {records[0]['decision_rule']}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.run is not None:
        return run_identify(args)
    records, decoder = extract_records(args)
    if args.json:
        for record in records:
            print(json.dumps({**record, "decoder": str(decoder.path), "fingerprint": decoder.fingerprint}))
    else:
        width = max(len(r["image"]) for r in records)
        for record in records:
            print(f"{record['image']:<{width}}  {record['bits']}")
    return 0
