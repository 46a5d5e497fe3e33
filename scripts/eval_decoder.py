"""A decoder's held-out bit accuracy at each image size: does it read as well at 512² and 800² as at 64²?

Per side in ``--sizes``, on ``--images`` held-out images (crops of held-out photographs and procedural images,
never trained on) carrying held-out messages, every one at ≥ the recipe's target PSNR (35.5 dB unless the
decoder's training record says otherwise, or ``--psnr``):
- **informed**: images embedded by following the decoder's gradient for 1 and 10 iterations (how a radiance
  field carries the watermark), read with no attack and under the Low policy (``--draws`` random draws);
- **encoder**: the HiDDeN encoder's images: ``--encoder FILE`` (a run's ``encoder.npz``), or the encoder
  shipped with a ``--bits`` decoder when the package has one;
- ``--read-side S`` (default ``watermark.reading.max_side``'s, as ``mnerf extract`` reads; 0: as is): every
  read sees each image downscaled to at most S pixels a side, and the encoder writes for that read (its
  pattern carried to the image by the adjoint of the downscale, as Video Seal and Watermark Anything
  upsample their residual);
- **clean**: the share of 1 bits on the clean images, and the largest and mean per-bit bias ``|P[1] − ½|``
  (a decoder whose clean reads are fair keeps these near 0: the decision's p-values assume it).

    python scripts/eval_decoder.py --bits 16 --sizes 64,128,256,512,800 --json
    python scripts/eval_decoder.py --decoder RUN/decoder.npz --encoder RUN/encoder.npz --sizes 64,256
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any


def _ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def table(result: dict[str, Any]) -> str:
    """The measurement as a markdown table, a row per side."""
    first = next(iter(result["sizes"].values()))
    counts = list(first["informed"])
    head = ["side", *[f"informed {c.split('_')[0]} it. none / Low" for c in counts]]
    if "encoder" in first:
        head.append("encoder none / Low")
    head += ["clean: ones / max bias", "PSNR min"]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]

    def pair(row: dict[str, Any]) -> str:
        low = row["bit_acc_low"]
        return f"{100 * row['bit_acc_none']:.1f} / " + ("—" if low is None else f"{100 * low:.1f} %")

    for side, row in result["sizes"].items():
        cells = [side, *[pair(row["informed"][c]) for c in counts]]
        if "encoder" in row:
            cells.append(pair(row["encoder"]))
        clean = row["clean"]
        psnr = min(r["psnr_min"] for r in [*row["informed"].values(), row.get("encoder", {"psnr_min": 99.0})])
        cells += [f"{100 * clean['ones_mean']:.1f} / {100 * clean['bias_max']:.1f} %", f"{psnr:.2f} dB"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--bits", type=int, help="evaluate the shipped decoder of this many bits")
    which.add_argument("--decoder", type=Path, metavar="FILE", help="a decoder file (.npz)")
    parser.add_argument(
        "--encoder", type=Path, metavar="FILE", help="its HiDDeN encoder (a run's encoder.npz)"
    )
    parser.add_argument(
        "--sizes", type=_ints, default=(64, 128, 256, 512, 800), help="image sides, comma-separated"
    )
    parser.add_argument("--images", type=int, default=64, help="held-out images per side (default 64)")
    parser.add_argument(
        "--iterations", type=_ints, default=(1, 10), help="informed iterations (default 1,10)"
    )
    parser.add_argument(
        "--draws", type=int, default=None, help="Low-policy draws per image (default the recipe's)"
    )
    parser.add_argument("--psnr", type=float, default=None, help="PSNR of every embedded image, dB")
    parser.add_argument(
        "--read-side",
        type=int,
        default=None,
        help="read images downscaled to at most this side (0: as is; default: watermark.reading.max_side's "
        "default, as mnerf extract reads a render)",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON, not a table")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON to this file")
    args = parser.parse_args(argv)

    from mnerf_jax.core import rundir
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.core.watermark_config import ReadingConfig
    from mnerf_jax.reader import decoder_io
    from mnerf_jax.reader.train import evaluation, hidden_encoder
    from mnerf_jax.reader.train.recipe import DecoderTrainConfig

    try:
        path = decoder_io.shipped_decoder_path(args.bits) if args.bits is not None else args.decoder
        loaded = decoder_io.load_decoder(path, expect_bits=args.bits)
        enc_vars = None
        if args.encoder is None and args.bits is not None:
            args.encoder = decoder_io.shipped_encoder_path(args.bits)
        if args.encoder is not None:
            enc_vars, cfg = hidden_encoder.load_encoder(args.encoder)
            if cfg.bits != loaded.bits:
                raise MnerfError(f"{args.encoder} writes {cfg.bits}-bit messages, {path} reads {loaded.bits}")
        else:
            cfg = recipe_of(loaded.metadata, DecoderTrainConfig)
        cfg = dataclasses.replace(cfg, bits=loaded.bits, wavelet=loaded.wavelet)
        if args.draws is not None:
            cfg = dataclasses.replace(cfg, eval_augment_draws=args.draws)
        if args.psnr is not None:
            cfg = dataclasses.replace(cfg, target_psnr=args.psnr)
        if args.read_side is None:
            args.read_side = ReadingConfig().max_side
        if args.images < 1:
            raise MnerfError(f"--images must be at least 1, got {args.images}")
        t0 = time.perf_counter()
        sizes = evaluation.evaluate_across_sizes(
            cfg,
            loaded.variables,
            args.sizes,
            args.images,
            args.iterations,
            enc_vars,
            progress=lambda s: print(f"eval_decoder: {s} ...", file=sys.stderr, flush=True),
            max_side=args.read_side,
        )
    except (MnerfError, OSError) as err:
        print(f"eval_decoder: error: {err}", file=sys.stderr)
        return 2
    result = {
        "decoder": str(path),
        "fingerprint": loaded.fingerprint,
        "encoder": None if args.encoder is None else str(args.encoder),
        "bits": loaded.bits,
        "target_psnr": cfg.target_psnr,
        "low_draws": cfg.eval_augment_draws,
        "read_side": args.read_side,
        "seconds": time.perf_counter() - t0,
        "sizes": sizes,
    }
    print(json.dumps(result, indent=1) if args.json else table(result))
    if args.out is not None:
        rundir.write_json_atomic(args.out, result)
    return 0


def recipe_of(metadata: dict[str, Any], config_type: type) -> Any:
    """The training recipe a decoder file records (its fields this version knows), else the defaults."""
    recorded = (metadata.get("training") or {}).get("config") or {}
    fields = {f.name for f in dataclasses.fields(config_type)}
    known = {k: tuple(v) if isinstance(v, list) else v for k, v in recorded.items() if k in fields}
    return config_type(**known)


if __name__ == "__main__":
    from mnerf_jax.cli.process import reexec_with_huge_pages

    reexec_with_huge_pages([sys.executable, *sys.argv])
    sys.exit(main())
