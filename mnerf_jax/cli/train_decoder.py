"""``mnerf train-decoder``: train a HiDDeN watermark decoder for L-bit messages, whiten it, evaluate it."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NAME = "train-decoder"
HELP = (
    "Train a HiDDeN watermark decoder (with its encoder) on bundled photos, procedural images and an "
    "optional folder; PCA-whiten it; write DIR/decoder.npz and DIR/metrics.json."
)


def _sides(text: str) -> tuple[int, ...]:
    try:
        sides = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated image sides, got {text!r}") from None
    if not sides or min(sides) < 16:
        raise argparse.ArgumentTypeError(f"image sides must be at least 16, got {text!r}")
    return sides


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mnerf_jax.reader.decoder import DECODER_INITS
    from mnerf_jax.reader.train.recipe import DecoderTrainConfig

    d = DecoderTrainConfig()
    parser.add_argument("--bits", type=int, required=True, help="message length L (8, 16, 32 or 48)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--images",
        type=Path,
        default=None,
        help="extra training images: every image file under this folder (e.g. COCO)",
    )
    parser.add_argument(
        "--informed-steps",
        type=int,
        default=d.informed_steps,
        help=f"decoder steps against its own gradient watermark, first ({d.informed_steps})",
    )
    parser.add_argument(
        "--informed-margin",
        type=int,
        default=d.informed_margin,
        help="informed stage: encode crops this much larger and read a random window of each, so only "
        f"shift-robust watermarks pay ({d.informed_margin}: whole crops)",
    )
    parser.add_argument(
        "--informed-sizes",
        type=_sides,
        default=d.informed_sizes,
        help="image sides of the informed steps, in turn, comma-separated "
        f"({','.join(map(str, d.informed_sizes))})",
    )
    parser.add_argument(
        "--pool-margin",
        type=int,
        default=d.pool_margin,
        help="the decoder's pool skips this many LL2 positions at each side; 9 (its receptive-field radius) "
        f"makes the read shift-invariant and needs training images larger than 72 px ({d.pool_margin})",
    )
    parser.add_argument(
        "--eval-sizes",
        type=_sides,
        default=d.eval_sizes,
        help=f"image sides of the held-out evaluation ({','.join(map(str, d.eval_sizes))})",
    )
    parser.add_argument(
        "--decoder-init",
        choices=DECODER_INITS,
        default=d.decoder_init,
        help="decoder start: a fixed local filter bank in the first block with the middle blocks near "
        f"identity, or random ({d.decoder_init})",
    )
    parser.add_argument("--steps", type=int, default=d.steps, help=f"joint encoder+decoder steps ({d.steps})")
    parser.add_argument(
        "--finetune-steps",
        type=int,
        default=d.finetune_steps,
        help=f"encoder steps through the whitened decoder ({d.finetune_steps})",
    )
    parser.add_argument(
        "--finetune-sizes",
        type=_sides,
        default=None,
        help="image sides of the encoder steps, in turn, comma-separated (the --size)",
    )
    parser.add_argument(
        "--lr-finetune",
        type=float,
        default=d.lr_finetune,
        help=f"peak learning rate of the encoder steps ({d.lr_finetune})",
    )
    parser.add_argument(
        "--finetune-decoder-lr",
        type=float,
        default=d.finetune_decoder_lr,
        help="peak learning rate of the decoder during the encoder steps, HiDDeN-style joint training once "
        f"the encoder writes for it (0: the decoder stays frozen) ({d.finetune_decoder_lr})",
    )
    parser.add_argument(
        "--finetune-decoder-start",
        type=float,
        default=d.finetune_decoder_start,
        help="share of the encoder steps before the decoder starts learning (with --finetune-decoder-lr) "
        f"({d.finetune_decoder_start})",
    )
    parser.add_argument(
        "--read-side",
        type=int,
        default=d.read_side,
        help="the encoder steps and the evaluation read each image downscaled to at most this side, as "
        f"watermark.reading.max_side does (0: as it is) ({d.read_side})",
    )
    parser.add_argument(
        "--encoder-from",
        type=Path,
        default=None,
        help="start the encoder steps from this encoder.npz (with --decoder-from; the same "
        "--encoder-channels and --encoder-depth) instead of a fresh encoder",
    )
    parser.add_argument(
        "--decoder-from",
        type=Path,
        default=None,
        help="train an encoder for this whitened decoder file (with --informed-steps 0 --steps 0); the "
        "decoder is copied unchanged unless --finetune-decoder-lr, its held-out figures re-measured",
    )
    parser.add_argument(
        "--size",
        type=int,
        default=d.size,
        help=f"side of the training windows the decoder sees ({d.size}; encoded at +{d.crop_margin})",
    )
    parser.add_argument(
        "--encoder-channels",
        type=int,
        default=d.encoder_channels,
        help=f"width of the HiDDeN encoder's convolutions ({d.encoder_channels})",
    )
    parser.add_argument(
        "--encoder-depth",
        type=int,
        default=d.encoder_depth,
        help=f"Conv-BN-ReLU blocks before the message joins the encoder's features ({d.encoder_depth})",
    )
    parser.add_argument("--batch", type=int, default=d.batch, help=f"images per step ({d.batch})")
    parser.add_argument("--seed", type=int, default=d.seed, help=f"random seed ({d.seed})")
    parser.add_argument("--lr", type=float, default=d.lr, help=f"peak learning rate ({d.lr})")
    parser.add_argument(
        "--target-psnr",
        type=float,
        default=d.target_psnr,
        help=f"PSNR of every encoded image against its original, at least ({d.target_psnr})",
    )
    parser.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.msgpack")
    parser.add_argument("--checkpoint-every", type=int, default=250, help="steps between checkpoints (250)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mnerf_jax.reader.train.recipe import DecoderTrainConfig
    from mnerf_jax.reader.train.stages import train_decoder

    cfg = DecoderTrainConfig(
        bits=args.bits,
        informed_steps=args.informed_steps,
        informed_margin=args.informed_margin,
        informed_sizes=args.informed_sizes,
        pool_margin=args.pool_margin,
        eval_sizes=args.eval_sizes,
        decoder_init=args.decoder_init,
        steps=args.steps,
        finetune_steps=args.finetune_steps,
        finetune_sizes=args.finetune_sizes or (),
        read_side=args.read_side,
        lr_finetune=args.lr_finetune,
        finetune_decoder_lr=args.finetune_decoder_lr,
        finetune_decoder_start=args.finetune_decoder_start,
        decoder_from=str(args.decoder_from.resolve()) if args.decoder_from else "",
        encoder_from=str(args.encoder_from.resolve()) if args.encoder_from else "",
        size=args.size,
        encoder_channels=args.encoder_channels,
        encoder_depth=args.encoder_depth,
        batch=args.batch,
        seed=args.seed,
        lr=args.lr,
        target_psnr=args.target_psnr,
        images_dir=str(args.images.resolve()) if args.images else "",
    )
    metrics = train_decoder(
        cfg,
        args.out,
        resume=args.resume,
        progress=not args.quiet,
        checkpoint_every=args.checkpoint_every,
        log=print,
    )
    summary = {
        "decoder": str(args.out / "decoder.npz"),
        "bits": cfg.bits,
        "wall_time_s": metrics["wall_time_s"],
    }
    for size, figures in metrics["heldout"].items():
        summary[size] = {
            k: None if figures[k] is None else round(figures[k], 4)
            for k in ("bit_acc_none", "bit_acc_low", "psnr_mean")
        }
    print(json.dumps(summary))
    return 0
