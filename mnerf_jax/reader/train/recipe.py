"""The decoder-training recipe as data (:class:`DecoderTrainConfig`, compared on ``--resume``) and its
schedules: the residual strength per step, the image side and batch of each step, the training images.
:mod:`mnerf_jax.reader.train.stages` runs it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from mnerf_jax.reader.train.cover_images import TRAIN_PHOTOS, ImageSource, load_folder, load_photos

# Config fields that only change the final evaluation: a finished run can be re-evaluated with --resume.
EVAL_FIELDS = ("eval_images", "eval_sizes", "eval_augment_draws", "eval_informed_iterations", "check_images")


@dataclasses.dataclass(frozen=True)
class DecoderTrainConfig:
    """Everything that decides the trajectory of a decoder training run (compared on ``--resume``)."""

    bits: int = 16
    informed_steps: int = 4000  # decoder steps against the informed (gradient) encoder, first
    informed_sizes: tuple[int, ...] = (64, 128)  # image sides of the informed steps, in turn
    # Informed crops are encoded at side + margin and the decoder reads a random side × side window of each,
    # so only watermarks that survive a shift pay (what a 3D field can carry); 0: whole crops.
    informed_margin: int = 0
    informed_start_psnr: float = 28.0  # curriculum of the informed steps (reaches target_psnr like the joint)
    steps: int = 0  # joint encoder+decoder steps, after the informed ones
    finetune_steps: int = 5000  # encoder-only steps through the whitened decoder (still gaining at 5,000)
    # Image sides of the encoder steps, in turn (each batch about as many pixels as ``batch`` × ``size``²);
    # empty: ``size`` only. An encoder trained at one side writes worse at the others.
    finetune_sizes: tuple[int, ...] = ()
    # The side the decoder reads at in the encoder steps and the final evaluation: each image is downscaled to
    # at most this side first (``watermark.reading.max_side``), and the encoder writes for that read, so its
    # batches keep ``batch`` images at every side; 0: read as it is.
    read_side: int = 0
    # Stage 4 can train the decoder too, HiDDeN-style, once the encoder writes for it: its peak learning rate
    # (0: the decoder stays frozen) and the share of the stage's steps before it starts. The decoder keeps its
    # BatchNorm statistics and whitening rotation (what the encoder learned against); the whitening's offset
    # and scale are re-fitted on clean crops at the end.
    finetune_decoder_lr: float = 0.0
    finetune_decoder_start: float = 0.25
    # A whitened decoder file to train an encoder for (stages 1-3 skipped; the decoder is not changed unless
    # finetune_decoder_lr > 0).
    decoder_from: str = ""
    # An encoder file (``encoder.npz``) of the same architecture to start the encoder steps from (with
    # decoder_from): an encoder that writes well at one read is refitted for another; "": a fresh encoder.
    encoder_from: str = ""
    size: int = 64  # side in pixels of the images the decoder sees in training (LL2 side = size / 4)
    crop_margin: int = 0  # images are encoded at size + margin; the decoder sees a random size × size window
    batch: int = 16
    seed: int = 0
    lr: float = 1e-3
    lr_finetune: float = 5e-4
    warmup_steps: int = 200
    weight_decay: float = 1e-4
    clean_fraction: float = 0.25  # curriculum: no augmentation for this fraction of the joint steps
    augment_strength: str = "low"
    augment_k: int = 2
    augment_p: float = 0.75
    temperature: float = 1.0  # BCE temperature during training (whitening fixes the final scale anyway)
    target_psnr: float = 35.5  # each encoded image's PSNR against its original is at least this
    start_psnr: float = 20.0  # curriculum: the residual starts this strong ...
    anneal_fraction: float = 0.4  # ... and reaches target_psnr after this fraction of the joint steps
    encoder_channels: int = 32
    encoder_depth: int = 3
    procedural_fraction: float = 0.35  # share of each batch drawn from procedural images
    whiten_images: int = 1024  # clean training crops used to fit the whitening
    eval_images: int = 128  # held-out crops per evaluation size
    eval_sizes: tuple[int, ...] = (64, 128, 256)  # held-out image sides (pixels)
    eval_augment_draws: int = 4  # Low-policy draws per held-out image (0: no attacked evaluation)
    eval_informed_iterations: tuple[int, ...] = (1, 10)  # informed embeddings evaluated (iterations each)
    check_images: int = 8  # encoded held-out images stored (uint8) beside the decoder
    wavelet: str = "bior4.4"
    decoder_init: str = "filterbank"  # filterbank (decoder.filterbank_init) | random
    # LL2 positions the decoder's pool skips at each side (decoder.with_pool_margin); 9 = receptive radius.
    pool_margin: int = 0
    images_dir: str = ""  # extra training images (every image file under it)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def trajectory(self) -> dict[str, Any]:
        """The fields that decide the training trajectory (what ``--resume`` compares)."""
        return {k: v for k, v in self.to_dict().items() if k not in EVAL_FIELDS}


def training_source(cfg: DecoderTrainConfig) -> ImageSource:
    """The training images of a run: the training photographs, ``cfg.images_dir``, procedural images."""
    pool = load_photos(TRAIN_PHOTOS)
    if cfg.images_dir:
        pool += load_folder(cfg.images_dir)
    return ImageSource(pool, cfg.size + cfg.crop_margin, cfg.procedural_fraction)


def informed_psnr(cfg: DecoderTrainConfig, step: int) -> float:
    """Residual strength at an informed step: ``informed_start_psnr`` rising linearly to ``target_psnr``."""
    span = cfg.anneal_fraction * cfg.informed_steps
    if step >= span or span <= 0 or cfg.informed_start_psnr >= cfg.target_psnr:
        return cfg.target_psnr
    return cfg.informed_start_psnr + (cfg.target_psnr - cfg.informed_start_psnr) * step / span


def side_and_batch(
    cfg: DecoderTrainConfig, sides: tuple[int, ...], step: int, read_side: int = 0
) -> tuple[int, int]:
    """``(side, batch)`` of a step whose image sides take turns: each batch holds about as many pixels as
    ``cfg.batch`` images of ``cfg.size``², as the decoder sees them (downscaled to ``read_side``; 0: as it
    is)."""
    side = sides[step % len(sides)]
    seen = min(side, read_side) if read_side > 0 else side
    return side, max(1, round(cfg.batch * (cfg.size / seen) ** 2))


def informed_batch(cfg: DecoderTrainConfig, step: int) -> tuple[int, int]:
    """``(side, batch)`` of an informed step."""
    return side_and_batch(cfg, cfg.informed_sizes, step)


def finetune_sides(cfg: DecoderTrainConfig) -> tuple[int, ...]:
    """The image sides of the encoder steps (``finetune_sizes``, or ``size`` alone)."""
    return tuple(cfg.finetune_sizes) or (cfg.size,)


def finetune_decoder_start_step(cfg: DecoderTrainConfig) -> int:
    """Stage-4 step (counted from the stage's start) from which the decoder learns too; the stage's length
    when it never does."""
    if cfg.finetune_decoder_lr <= 0:
        return cfg.finetune_steps
    return int(round(cfg.finetune_decoder_start * cfg.finetune_steps))


def psnr_schedule(cfg: DecoderTrainConfig, step: int) -> float:
    """Residual strength (PSNR in dB) at a joint step: ``start_psnr`` rising linearly to ``target_psnr``."""
    span = cfg.anneal_fraction * cfg.steps
    if step >= span or span <= 0 or cfg.start_psnr >= cfg.target_psnr:
        return cfg.target_psnr
    return cfg.start_psnr + (cfg.target_psnr - cfg.start_psnr) * step / span
