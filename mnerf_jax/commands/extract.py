"""``mnerf extract``: decode the watermark bits of image files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NAME = "extract"
HELP = "Decode the watermark bits of images with a HiDDeN decoder (default: the shipped 16-bit one)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="image files")
    parser.add_argument(
        "--decoder",
        type=Path,
        default=None,
        help="decoder file (.npz from train-decoder or a conversion); default: shipped decoder",
    )
    parser.add_argument(
        "--bits",
        type=int,
        default=None,
        help="message length: picks the shipped decoder (16 or 48), or checks --decoder",
    )
    parser.add_argument("--batch", type=int, default=32, help="images per decoder call (32)")
    parser.add_argument("--json", action="store_true", help="one JSON object per image instead of text")


def extract_records(args: argparse.Namespace) -> tuple[list[dict], object]:
    """Decode ``args.images``: one record (path, bits string, logits) per image, and the decoder used."""
    from mnerf_jax import extract

    decoder = extract.resolve_decoder(args.decoder, args.bits)
    logits = extract.decode_paths(decoder.variables, args.images, decoder.wavelet, args.batch)
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


def run(args: argparse.Namespace) -> int:
    records, decoder = extract_records(args)
    if args.json:
        for record in records:
            print(json.dumps({**record, "decoder": str(decoder.path), "fingerprint": decoder.fingerprint}))
    else:
        width = max(len(r["image"]) for r in records)
        for record in records:
            print(f"{record['image']:<{width}}  {record['bits']}")
    return 0
