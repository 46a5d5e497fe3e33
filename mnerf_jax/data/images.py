"""Image decoding, compositing and area resampling.

Images are decoded with Pillow (turned upright by their EXIF Orientation tag on request), composited
on the background in float32 and resampled with an area (box) filter. Resampling is done on the
composited image, which equals averaging premultiplied colour and alpha and compositing afterwards
(compositing is linear in (alpha*rgb, alpha)); averaging straight (non-premultiplied) colour instead
would bleed the arbitrary colour of transparent pixels into object edges.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from mnerf_jax.data.types import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
EXIF_ORIENTATION = 0x0112  # the EXIF tag: 1 upright, 2-8 turned and/or mirrored

# Pillow raises these for corrupt or truncated files.
_DECODE_ERRORS = (OSError, UnidentifiedImageError, SyntaxError, ValueError, Image.DecompressionBombError)


def read_json(path: Path) -> Any:
    """Parse a JSON file; a missing or malformed file is a DataError naming the file and line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: unreadable ({err})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        where = f"line {err.lineno}, column {err.colno}"
        raise DataError(f"{path}: malformed JSON at {where}: {err.msg}") from None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except _DECODE_ERRORS as err:
        raise DataError(f"{path}: unreadable image ({_one_line(err)})") from None


def image_header(path: Path) -> tuple[tuple[int, int], int]:
    """((width, height) as stored, EXIF orientation 1-8) of an image file, reading only its header.

    A missing or out-of-range Orientation tag reads as 1 (upright), as Pillow's ``exif_transpose`` takes it.
    """
    try:
        with Image.open(path) as im:
            tag = im.getexif().get(EXIF_ORIENTATION, 1)
            size = (int(im.width), int(im.height))
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except _DECODE_ERRORS as err:
        raise DataError(f"{path}: unreadable image ({_one_line(err)})") from None
    return size, tag if isinstance(tag, int) and 1 <= tag <= 8 else 1


def scaled_size(width: int, height: int, downscale: float) -> tuple[int, int]:
    """Image size after dividing each side by ``downscale`` (rounded down, at least 1 pixel)."""
    if not downscale >= 1.0:
        raise DataError(f"downscale must be >= 1, got {downscale}")
    return max(1, int(width / downscale)), max(1, int(height / downscale))


def read_image(path: Path, upright: bool = False) -> np.ndarray:
    """Decode an image file to float32 [H, W, 3] (RGB) or [H, W, 4] (RGBA, straight alpha) in [0, 1].

    upright: apply the file's EXIF Orientation tag (Pillow's ``exif_transpose``); else the pixels as stored.
    """
    try:
        with Image.open(path) as im:
            im.load()
            return _to_float(ImageOps.exif_transpose(im) if upright else im)
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except _DECODE_ERRORS as err:
        raise DataError(f"{path}: unreadable image ({_one_line(err)})") from None


def _to_float(im: Image.Image) -> np.ndarray:
    if im.mode in ("I;16", "I;16B", "I;16L", "I"):
        # 16-bit grey: keep the precision, replicate to RGB.
        grey = np.asarray(im, np.float32) / 65535.0
        return np.repeat(np.clip(grey, 0.0, 1.0)[..., None], 3, axis=-1)
    has_alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    target = "RGBA" if has_alpha else "RGB"
    if im.mode != target:
        im = im.convert(target)
    return np.asarray(im, np.float32) * np.float32(1.0 / 255.0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Float images ``[..., H, W, 3]`` in [0, 1] as 8-bit values, rounded (what a saved PNG holds)."""
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def round_to_8bit(image: np.ndarray) -> np.ndarray:
    """Float images rounded to the 256 levels of an 8-bit file, float32 in [0, 1] again."""
    return to_uint8(image).astype(np.float32) / np.float32(255.0)


def composite(image: np.ndarray, white_bg: bool) -> np.ndarray:
    """[H, W, 3|4] straight-alpha image -> [H, W, 3] composited on white (or black)."""
    if image.shape[-1] == 3:
        return image
    rgb, alpha = image[..., :3], image[..., 3:4]
    out = rgb * alpha
    if white_bg:
        out += 1.0 - alpha
    return out


def area_resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average resample a float32 [H, W, C] image to [height, width, C].

    Integer factors average exact pixel blocks; other factors weight source pixels by their
    overlap with each target pixel (Pillow's box filter on 32-bit float channels).
    """
    h, w, c = image.shape
    if (w, h) == (width, height):
        return image
    fx, fy = w // width, h // height
    exact = fx * width == w and fy * height == h
    channels = []
    for k in range(c):
        plane = Image.fromarray(np.ascontiguousarray(image[..., k], np.float32))  # float32 -> mode "F"
        plane = plane.reduce((fx, fy)) if exact else plane.resize((width, height), Image.Resampling.BOX)
        channels.append(np.asarray(plane, np.float32))
    return np.stack(channels, axis=-1)


def load_image(
    path: Path,
    white_bg: bool,
    size: tuple[int, int] | None = None,
    expect: tuple[int, int] | None = None,
    expect_from: Path | None = None,
    upright: bool = False,
) -> np.ndarray:
    """Decode, composite and area-resample one image.

    size:    (width, height) to resample to; None keeps the file's size
    expect:  (width, height) the file must have (all images of a split share one size)
    upright: turn the image upright by its EXIF orientation first (``expect`` is then the upright size)
    Returns float32 [H, W, 3] in [0, 1].
    """
    image = read_image(path, upright)
    h, w = image.shape[:2]
    if expect is not None and (w, h) != tuple(expect):
        other = f" as {expect_from.name} is" if expect_from is not None else ""
        raise DataError(
            f"{path}: image is {w}x{h} but should be {expect[0]}x{expect[1]}{other}; "
            "all images of a split must share one size"
        )
    rgb = composite(image, white_bg)
    if size is not None:
        rgb = area_resize(rgb, *size)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32, copy=False)


def load_images(
    paths: Sequence[Path],
    white_bg: bool,
    size: tuple[int, int] | None = None,
    expect: tuple[int, int] | Sequence[tuple[int, int]] | None = None,
    workers: int | None = None,
    upright: bool = False,
) -> np.ndarray:
    """Load images in parallel threads (decoding releases the GIL) -> float32 [N, H, W, 3].

    expect: the (width, height) every file must have (default: the first file's), or one per file, in
            which case ``size`` is required; upright: see :func:`load_image`.
    """
    if not paths:
        raise DataError("no images to load")
    if expect is None:
        expect = image_size(paths[0])
    per_file = not isinstance(expect[0], int)
    if per_file and (len(expect) != len(paths) or size is None):
        raise ValueError("per-file sizes need one (width, height) per path and a common output size")
    out_w, out_h = size if size is not None else expect
    out = np.empty((len(paths), out_h, out_w, 3), np.float32)

    def one(i: int) -> None:
        want = expect[i] if per_file else expect
        out[i] = load_image(paths[i], white_bg, size, want, None if per_file else paths[0], upright)

    workers = workers or min(8, os.cpu_count() or 1)
    if workers <= 1 or len(paths) == 1:
        for i in range(len(paths)):
            one(i)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            # list() re-raises the first worker error here (a DataError naming the file).
            list(pool.map(one, range(len(paths))))
    return out


def resolve_image(root: Path, file_path: str) -> Path | None:
    """The image a frame's ``file_path`` names, relative to ``root``; tries common suffixes when the
    path has none that exists (NeRF-Synthetic writes ``./train/r_0`` for ``train/r_0.png``)."""
    base = root / file_path
    if base.is_file():
        return base
    for suffix in IMAGE_SUFFIXES:
        candidate = base.with_name(base.name + suffix)
        if candidate.is_file():
            return candidate
    return None


def list_images(directory: Path) -> list[Path]:
    """Image files in ``directory``, sorted by name."""
    return sorted(p for p in directory.iterdir() if p.is_file() and p.suffix in IMAGE_SUFFIXES)


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__
