"""Reading that survives geometry: read an image again as if it had been rescaled or rotated, and keep the
best read.

The decoders read patterns tied to the pixel grid: a render rescaled to 75 % or rotated by 15° reads at
chance, though the read window still finds the object. A search tries a small grid of candidate
transforms. Each :class:`Candidate` says what may have happened to the image (rescaled by ``scale``, rotated
anticlockwise by ``degrees`` about its centre); the search undoes it (one bilinear warp, scikit-image:
resized by ``1/scale``, anti-aliased when that shrinks, and rotated back), then reads the result as usual
(read window, jitter, DWT, decoder: :func:`reader.extract.decode`). Identity is always the first candidate
and reads the image untouched, so the search's first read is the plain read. The window, recomputed on each
warped image, re-centres on the object, so rotating about the image's centre rather than the object's
costs only a shift the window absorbs.

The read kept is the (read, key) pair with the smallest p-value
(:func:`identification.identify_best_read`). Picking the best of C reads gives chance C tries, so the p-value
is Bonferroni-corrected over C·N pairs instead of N: the false-claim rate stays at most the threshold, and the
smallest attainable corrected p-value grows to ``C·N / 2^L`` (16 bits, 16 keys, the default geometry grid's
28 candidates: 6.8e-3, above the default 1e-3 threshold; the scale grid's 4: 9.8e-4). Choosing the read
without the keys would need no correction, but the decoder's confidence does not point at the right read: an
undo that enlarges a small image reads blurred content, and reads it the most confidently.

A search costs C reads of each image (and a warp per candidate), C = the candidates of its grid.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, get_args

import numpy as np
import scipy.ndimage
from skimage import transform

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.watermark_config import ReadingConfig, SearchMode, check_search_grid
from mnerf_jax.reader import extract, read_window
from mnerf_jax.reader.identification import Identification, identify_best_read

SEARCH_MODES: tuple[str, ...] = get_args(SearchMode)
# Warped pixels held at once per decoder call (float32 RGB: 12 bytes each).
WARP_PIXEL_BUDGET = 1 << 23


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A transform the image may have undergone: rescaled by ``scale`` (0.75: to 75 % of its sides), rotated
    anticlockwise by ``degrees`` about its centre. The search undoes it before reading."""

    scale: float = 1.0
    degrees: float = 0.0

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and self.degrees == 0.0

    @property
    def label(self) -> str:
        """``identity``, ``scale 0.75``, ``rotation 15°`` or ``scale 0.75, rotation -15°``."""
        parts = [f"scale {self.scale:g}"] if self.scale != 1.0 else []
        parts += [f"rotation {self.degrees:g}°"] if self.degrees != 0.0 else []
        return ", ".join(parts) or "identity"

    def output_size(self, height: int, width: int) -> tuple[int, int]:
        """The undone image's ``(rows, columns)`` for an image of ``height × width`` (at least 4 each)."""
        return max(4, round(height / self.scale)), max(4, round(width / self.scale))

    def to_dict(self) -> dict[str, float]:
        return {"scale": float(self.scale), "degrees": float(self.degrees)}


@dataclasses.dataclass(frozen=True)
class GeometrySearch:
    """What a search tries: ``mode`` (``none``, ``scale``, ``rotation`` or ``geometry``, both grids'
    product) and the grids: scale factors and angles in degrees (identity is added to each)."""

    mode: str = "none"
    scales: tuple[float, ...] = ReadingConfig().search_scales
    degrees: tuple[float, ...] = ReadingConfig().search_degrees

    def __post_init__(self) -> None:
        if self.mode not in SEARCH_MODES:
            raise MnerfError(f"unknown geometry search {self.mode!r} (known: {', '.join(SEARCH_MODES)})")
        check_search_grid(self.scales, self.degrees, "the search's ")

    @property
    def active(self) -> bool:
        return self.mode != "none"

    def candidates(self) -> tuple[Candidate, ...]:
        """Every candidate, identity first, each once: the scales' and the rotations' grid (``mode``)."""
        scales = (1.0, *self.scales) if self.mode in ("scale", "geometry") else (1.0,)
        degrees = (0.0, *self.degrees) if self.mode in ("rotation", "geometry") else (0.0,)
        unique = dict.fromkeys(Candidate(float(s), float(d)) for s, d in itertools.product(scales, degrees))
        return tuple(unique)

    def describe(self) -> dict[str, Any]:
        """The search as plain data (for JSON): mode, grids, number of candidates."""
        return {
            "mode": self.mode,
            "scales": list(self.scales),
            "degrees": list(self.degrees),
            "candidates": len(self.candidates()),
        }


def of_config(
    reading: ReadingConfig,
    mode: str | None = None,
    scales: tuple[float, ...] | None = None,
    degrees: tuple[float, ...] | None = None,
) -> GeometrySearch:
    """The search of a watermark config's ``reading`` section, with ``mode``, ``scales``, ``degrees``
    replacing its settings where given (a command's options)."""
    return GeometrySearch(
        reading.search if mode is None else mode,
        tuple(reading.search_scales if scales is None else scales),
        tuple(reading.search_degrees if degrees is None else degrees),
    )


def parse_numbers(text: str, what: str) -> tuple[float, ...]:
    """``"0.5,0.75,1.5"`` as floats; MnerfError naming ``what`` (the option) for anything else."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise MnerfError(f"{what} takes comma-separated numbers, got {text!r}") from None
    if not values:
        raise MnerfError(f"{what} takes comma-separated numbers, got {text!r}")
    return values


# ------------------------------------------------------------------------------------------- the warps


def undo(images: np.ndarray, candidate: Candidate, fill: float = 0.0) -> np.ndarray:
    """Images ``[B, H, W, 3]`` float in [0, 1] with ``candidate``'s transform undone: float32
    ``[B, H', W', 3]`` (:meth:`Candidate.output_size`); pixels from outside the image get grey ``fill``.

    One bilinear warp per image: output pixel ``u`` (x, y) reads the input at
    ``s·(c + R(−θ)(u − c) + ½) − ½`` (``c`` the output's centre, ``s`` the scale, ``θ`` the angle, the
    pixel-centre convention of scikit-image's resize), after a Gaussian of σ = (s − 1)/2 px when the undo
    shrinks (s > 1), as scikit-image's anti-aliased resize does. Identity returns the images as they are.
    """
    images = np.asarray(images, np.float32)
    if candidate.is_identity:
        return images
    h, w = images.shape[1:3]
    rows, cols = candidate.output_size(h, w)
    s, theta = float(candidate.scale), np.deg2rad(-float(candidate.degrees))
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    matrix = np.eye(3)
    matrix[:2, :2] = s * rotation
    matrix[:2, 2] = s * (centre - rotation @ centre + 0.5) - 0.5
    inverse_map = transform.AffineTransform(matrix=matrix)
    sigma = max(0.0, (s - 1.0) / 2.0)
    out = np.empty((len(images), rows, cols, 3), np.float32)
    for i, image in enumerate(images):
        source = scipy.ndimage.gaussian_filter(image, (sigma, sigma, 0.0), mode="nearest") if sigma else image
        out[i] = transform.warp(
            source, inverse_map, output_shape=(rows, cols, 3), order=1, mode="constant", cval=fill
        )
    return out


def search_logits(
    variables: Mapping[str, Any],
    images: Any,
    search: GeometrySearch,
    wavelet: str = "bior4.4",
    batch_size: int = 32,
    read: read_window.ReadOptions = read_window.WHOLE_IMAGE,
) -> np.ndarray:
    """Logits ``[B, C, L]`` of every candidate read of images ``[B, H, W, 3]`` (uint8, or float in [0, 1]),
    candidates in :meth:`GeometrySearch.candidates`' order (``[:, 0]`` is the plain read).

    Candidates of one output size are read together: the undone copies of a slice of the images, every
    candidate's, go through :func:`extract.decode` in one call (``read``: as there), slices sized so that
    at most :data:`WARP_PIXEL_BUDGET` warped pixels are held at once. Pixels the undo brings in from outside
    get the backdrop's grey on a windowed read (the window ignores them), black otherwise (as the attacks
    fill).
    """
    x = np.asarray(extract.check_images(images))
    x = x.astype(np.float32) / 255.0 if not np.issubdtype(x.dtype, np.floating) else x.astype(np.float32)
    if x.ndim == 3:
        raise MnerfError("a geometry search reads a batch of images [B, H, W, 3]")
    fill = float(read.background) if read.window and read.background is not None else 0.0
    candidates = search.candidates()
    b, h, w = x.shape[:3]
    out: np.ndarray | None = None
    groups: dict[tuple[int, int], list[int]] = {}
    for c, candidate in enumerate(candidates):
        groups.setdefault(candidate.output_size(h, w), []).append(c)
    for (rows, cols), members in groups.items():
        per = max(1, min(b, WARP_PIXEL_BUDGET // (rows * cols * len(members))))
        per = -(-b // -(-b // per))  # even slices, the last one padded: one compiled shape
        for start in range(0, b, per):
            part = x[start : start + per]
            if len(part) < per:  # padded to the slice's shape (one decoder compilation per size)
                part = np.concatenate([part, np.zeros((per - len(part), h, w, 3), np.float32)])
            warped = np.concatenate([undo(part, candidates[c], fill) for c in members])
            logits = np.asarray(extract.decode(variables, warped, wavelet, batch_size, read)).reshape(
                len(members), per, -1
            )
            if out is None:
                out = np.zeros((b, len(candidates), logits.shape[-1]), np.float32)
            n = min(per, b - start)
            out[start : start + n, members] = np.swapaxes(logits[:, :n], 0, 1)
    assert out is not None
    return out


def search_paths(
    variables: Mapping[str, Any],
    paths: Sequence[str | Path],
    search: GeometrySearch,
    wavelet: str = "bior4.4",
    batch_size: int = 32,
    read: read_window.ReadOptions = read_window.WHOLE_IMAGE,
) -> np.ndarray:
    """Logits ``[N, C, L]`` of every candidate read of image files (:func:`search_logits`), in the given
    order; images of one size are searched together."""
    images = [extract.load_image(p) for p in paths]
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, image in enumerate(images):
        by_size.setdefault(image.shape[:2], []).append(i)
    out: np.ndarray | None = None
    for indices in by_size.values():
        batch = np.stack([images[i] for i in indices])
        logits = search_logits(variables, batch, search, wavelet, batch_size, read)
        if out is None:
            out = np.zeros((len(images), *logits.shape[1:]), np.float32)
        out[indices] = logits
    assert out is not None
    return out


# ------------------------------------------------------------------------------------- keeping a read


@dataclasses.dataclass(frozen=True)
class SearchRead:
    """The read kept of each of ``B`` images: its identification (corrected over candidates × keys), its
    logits ``[B, L]``, the index of its candidate ``chosen [B]`` in ``candidates``."""

    identification: Identification
    logits: np.ndarray
    chosen: np.ndarray
    candidates: tuple[Candidate, ...]

    def chosen_candidates(self) -> list[Candidate]:
        return [self.candidates[int(c)] for c in self.chosen]


def identify(
    logits: np.ndarray, messages: np.ndarray, candidates: tuple[Candidate, ...], threshold: float, test: str
) -> SearchRead:
    """Keep the best-supported of the C reads ``logits [B, C, L]`` of each image (the reads of
    ``candidates``, in order) against the keys ``messages [N, L]``: the (read, key) pair of smallest
    p-value under ``test``, corrected over C·N pairs (:func:`identification.identify_best_read`)."""
    logits = np.asarray(logits, np.float64)
    if logits.ndim != 3 or logits.shape[1] != len(candidates):
        raise ValueError(f"expected logits [B, {len(candidates)}, L] for the candidates, got {logits.shape}")
    ident, chosen = identify_best_read(logits, messages, threshold, test)
    return SearchRead(ident, logits[np.arange(len(logits)), chosen], chosen, tuple(candidates))
