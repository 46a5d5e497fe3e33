"""Images for decoder training and its held-out evaluation, all available offline.

The photographs bundled with scikit-image (some held out whole), procedural textures (smooth noise,
gradients, checkers, textured shapes on flat backgrounds, like rendered objects), and optionally every image
in a user folder; random crops (scale 25–100 % of the short side), flips and colour changes. Every draw takes
an explicit ``numpy.random.Generator``, so a run's batches are a function of its seed and step.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.core.errors import MnerfError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")

# scikit-image photographs (bundled, offline). Held-out ones never appear in training batches.
TRAIN_PHOTOS = (
    "astronaut",
    "chelsea",
    "immunohistochemistry",
    "hubble_deep_field",
    "retina",
    "colorwheel",
    "logo",
    "stereo_motorcycle",
    "camera",
    "page",
    "text",
    "coins",
    "moon",
    "brick",
    "grass",
    "cell",
    "checkerboard",
)
HELDOUT_PHOTOS = ("coffee", "rocket", "clock", "gravel")
EVAL_SEED = 20250611  # fixed: the held-out set does not depend on the training seed


def _to_rgb_float(image: np.ndarray) -> np.ndarray:
    """Any skimage/imageio image → ``[H, W, 3]`` float32 in [0, 1] (alpha composited on white)."""
    a = np.asarray(image)
    if a.dtype == bool:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float32) / float(np.iinfo(a.dtype).max)
    else:
        a = a.astype(np.float32)
        a = (a - a.min()) / max(float(a.max() - a.min()), 1e-6) if a.max() > 1.0 or a.min() < 0.0 else a
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.shape[-1] == 4:
        alpha = a[..., 3:4]
        a = a[..., :3] * alpha + (1.0 - alpha)
    elif a.shape[-1] == 2:
        a = np.repeat(a[..., :1], 3, axis=-1)
    return np.clip(a[..., :3], 0.0, 1.0)


def load_photos(names: Sequence[str]) -> list[np.ndarray]:
    """The named ``skimage.data`` images as RGB float32 (stereo pairs give both views); cached."""
    return list(_load_photos(tuple(names)))


@functools.lru_cache(maxsize=4)
def _load_photos(names: tuple[str, ...]) -> tuple[np.ndarray, ...]:
    import skimage.data

    out = []
    for name in names:
        image = getattr(skimage.data, name)()
        if isinstance(image, tuple):  # stereo pairs: keep both views
            out.extend(_to_rgb_float(i) for i in image[:2] if np.ndim(i) >= 2)
        else:
            out.append(_to_rgb_float(image))
    for image in out:
        image.setflags(write=False)
    return tuple(out)


def load_folder(path: str | Path, limit: int = 5000, max_side: int = 512) -> list[np.ndarray]:
    """Every image file under ``path`` (recursively, sorted, at most ``limit``), shrunk to ``max_side``."""
    from PIL import Image

    root = Path(path)
    if not root.is_dir():
        raise MnerfError(f"--images: {root} is not a directory")
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)[:limit]
    if not files:
        raise MnerfError(f"--images: no image files ({', '.join(IMAGE_SUFFIXES)}) under {root}")
    out = []
    for file in files:
        try:
            with Image.open(file) as im:
                im.draft("RGB", (max_side, max_side))
                im = im.convert("RGBA") if im.mode in ("RGBA", "LA", "P") else im.convert("RGB")
                im.thumbnail((max_side, max_side))
                out.append(_to_rgb_float(np.asarray(im)))
        except OSError as err:
            raise MnerfError(f"--images: cannot read {file} ({err})") from None
    return out


def _resize(image: np.ndarray, size: int) -> np.ndarray:
    from PIL import Image

    im = Image.fromarray(np.round(image * 255.0).astype(np.uint8))
    im = im.resize((size, size), Image.Resampling.BILINEAR, reducing_gap=2.0)
    return np.asarray(im, np.float32) / 255.0


def random_crop(rng: np.random.Generator, image: np.ndarray, size: int) -> np.ndarray:
    """A square crop of 25–100 % of the short side, resized to ``size``, maybe flipped, colour-jittered."""
    h, w = image.shape[:2]
    side = int(round(min(h, w) * rng.uniform(0.25, 1.0)))
    side = max(min(side, h, w), 1)
    y = int(rng.integers(0, h - side + 1))
    x = int(rng.integers(0, w - side + 1))
    crop = _resize(image[y : y + side, x : x + side], size)
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    return colour_jitter(rng, crop)


def colour_jitter(rng: np.random.Generator, image: np.ndarray) -> np.ndarray:
    """Brightness, contrast, saturation and gamma changes; grey images may get a tint."""
    out = image
    if rng.random() < 0.8:
        grey = out.mean(axis=-1, keepdims=True)
        if np.allclose(out, grey, atol=1e-3) and rng.random() < 0.5:
            out = grey * rng.uniform(0.6, 1.0, size=3).astype(np.float32)
        out = grey + (out - grey) * rng.uniform(0.5, 1.5)
        out = (out - 0.5) * rng.uniform(0.7, 1.3) + 0.5 + rng.uniform(-0.15, 0.15)
        out = np.clip(out, 0.0, 1.0) ** rng.uniform(0.7, 1.4)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, size: int, channels: int = 3) -> np.ndarray:
    """Sum of octaves of bilinearly upsampled Gaussian noise, normalised to [0, 1] per channel."""
    out = np.zeros((size, size, channels), np.float32)
    base = int(rng.integers(2, 6))
    amp = 1.0
    persistence = rng.uniform(0.35, 0.75)
    while base <= size:
        grid = rng.normal(size=(base, base, channels)).astype(np.float32)
        for c in range(channels):
            out[..., c] += amp * _upsample(grid[..., c], size)
        base *= 2
        amp *= persistence
    lo = out.min(axis=(0, 1), keepdims=True)
    hi = out.max(axis=(0, 1), keepdims=True)
    return (out - lo) / np.maximum(hi - lo, 1e-6)


def _upsample(grid: np.ndarray, size: int) -> np.ndarray:
    n = grid.shape[0]
    coords = np.linspace(0, n - 1, size)
    i0 = np.floor(coords).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    t = (coords - i0).astype(np.float32)
    rows = grid[i0] * (1 - t)[:, None] + grid[i1] * t[:, None]
    return rows[:, i0] * (1 - t)[None, :] + rows[:, i1] * t[None, :]


def procedural_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """A procedural image ``[size, size, 3]``: smooth noise, gradient, checkers or a shape on flat ground."""
    kind = int(rng.integers(0, 4))
    yy, xx = np.meshgrid(np.linspace(-1, 1, size), np.linspace(-1, 1, size), indexing="ij")
    c0 = rng.uniform(0, 1, 3).astype(np.float32)
    c1 = rng.uniform(0, 1, 3).astype(np.float32)
    if kind == 0:
        image = _smooth_noise(rng, size)
        image = c0 * (1 - image) + c1 * image if rng.random() < 0.5 else image
    elif kind == 1:
        angle = rng.uniform(0, 2 * np.pi)
        t = ((np.cos(angle) * xx + np.sin(angle) * yy) * 0.5 + 0.5)[..., None].astype(np.float32)
        image = c0 * (1 - t) + c1 * t
        image = image + 0.08 * (_smooth_noise(rng, size) - 0.5)
    elif kind == 2:
        period = rng.uniform(0.1, 0.8)
        angle = rng.uniform(0, np.pi)
        u = np.cos(angle) * xx + np.sin(angle) * yy
        v = -np.sin(angle) * xx + np.cos(angle) * yy
        mask = ((np.floor(u / period) + np.floor(v / period)) % 2)[..., None].astype(np.float32)
        image = c0 * (1 - mask) + c1 * mask
    else:
        # A textured blob on a flat background (white, black or grey), like a rendered object.
        ground = np.float32(rng.choice([1.0, 0.0, rng.uniform(0.2, 0.9)]))
        shape = _smooth_noise(rng, size, 1)[..., 0]
        r = np.sqrt((xx / rng.uniform(0.3, 0.9)) ** 2 + (yy / rng.uniform(0.3, 0.9)) ** 2)
        mask = ((shape * 0.6 + (1 - r) * 0.8) > 0.5)[..., None].astype(np.float32)
        texture = _smooth_noise(rng, size)
        image = ground * (1 - mask) + texture * mask
    return np.clip(image, 0.0, 1.0).astype(np.float32)


class ImageSource:
    """Draws batches of crops from a pool of full images plus procedural ones."""

    def __init__(self, pool: list[np.ndarray], size: int, procedural_fraction: float):
        if not pool:
            raise MnerfError("no training images")
        self.pool = pool
        self.size = size
        self.procedural_fraction = procedural_fraction

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        out = np.empty((n, self.size, self.size, 3), np.float32)
        for i in range(n):
            if rng.random() < self.procedural_fraction:
                out[i] = colour_jitter(rng, procedural_image(rng, self.size))
            else:
                out[i] = random_crop(rng, self.pool[int(rng.integers(len(self.pool)))], self.size)
        return out


def heldout_images(n: int, size: int) -> np.ndarray:
    """The fixed held-out set: crops of held-out photographs and procedural images (never trained on)."""
    rng = np.random.default_rng(EVAL_SEED)
    source = ImageSource(load_photos(HELDOUT_PHOTOS), size, procedural_fraction=0.35)
    return source.sample(rng, n)


def heldout_messages(n: int, bits: int) -> np.ndarray:
    return np.random.default_rng(EVAL_SEED + 1).integers(0, 2, size=(n, bits)).astype(np.float32)
