"""Scene containers: cameras, image splits and whole scenes, plus the data error type.

All arrays are numpy. Cameras follow the OpenGL/Blender convention (camera x right, y up, looking
down -z); intrinsics are in pixels with pixel centres at integer + 0.5.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mnerf_jax.core.errors import MnerfError


def view_indices(n: int, limit: int | None) -> list[int]:
    """``limit`` evenly spread view indices out of ``n``, first and last included (all when limit is None,
    ≤ 0 or ≥ n): the views a quick look, a test or an evaluation of ``limit`` views uses."""
    if limit is None or limit <= 0 or limit >= n:
        return list(range(n))
    return sorted({int(round(v)) for v in np.linspace(0, n - 1, limit)})


class DataError(MnerfError):
    """Bad scene input: a missing or unreadable file, malformed metadata, inconsistent images."""


class DataWarning(UserWarning):
    """Recoverable scene input problems (for example frames whose image file is missing)."""


@dataclasses.dataclass(frozen=True)
class NDCSpace:
    """TensoRF's normalised device coordinates for forward-facing scenes.

    ``focal`` (pixels), ``width`` and ``height`` are those of the training images; they define the
    NDC space, so rays of any camera of the scene (a video path, another resolution) use the same.
    """

    focal: float
    width: int
    height: int
    near: float = 1.0


@dataclasses.dataclass(frozen=True, eq=False)
class Cameras:
    """N pinhole cameras of one image size, optionally with OpenCV radial-tangential distortion.

    c2w:        [N, 3, 4] float32 camera-to-world (OpenGL: x right, y up, looking down -z)
    fx, fy:     [N] float32 focal lengths in pixels
    cx, cy:     [N] float32 principal point in pixels (the image centre is W/2, H/2)
    distortion: [N, 4] float32 OpenCV k1, k2, p1, p2 (zeros for none)
    width, height: image size in pixels
    ndc:        set for forward-facing scenes whose rays are mapped to NDC
    """

    c2w: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    ndc: NDCSpace | None = None

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, np.float32)
        if c2w.ndim != 3 or c2w.shape[1:] != (3, 4):
            raise ValueError(f"c2w must be [N, 3, 4], got {c2w.shape}")
        n = c2w.shape[0]
        object.__setattr__(self, "c2w", c2w)
        for name in ("fx", "fy", "cx", "cy"):
            value = np.broadcast_to(np.asarray(getattr(self, name), np.float32), (n,)).copy()
            object.__setattr__(self, name, value)
        dist = np.asarray(self.distortion, np.float32)
        dist = np.broadcast_to(dist, (n, 4)).copy()
        object.__setattr__(self, "distortion", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def centres(self) -> np.ndarray:
        """[N, 3] camera centres in world units."""
        return self.c2w[:, :, 3]

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    def select(self, indices: Sequence[int] | np.ndarray) -> Cameras:
        """The cameras at ``indices`` (same image size and NDC space)."""
        idx = np.asarray(indices, np.int64)
        return dataclasses.replace(
            self,
            c2w=self.c2w[idx],
            fx=self.fx[idx],
            fy=self.fy[idx],
            cx=self.cx[idx],
            cy=self.cy[idx],
            distortion=self.distortion[idx],
        )

    def scaled(self, width: int, height: int) -> Cameras:
        """The same cameras for images resampled to ``width`` x ``height`` pixels.

        Intrinsics are in corner-origin pixel units (centres at +0.5), so they scale exactly.
        """
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
            width=width,
            height=height,
        )


@dataclasses.dataclass(frozen=True, eq=False)
class SceneSplit:
    """One split of a scene.

    images:  [N, H, W, 3] float32 in [0, 1], composited on the scene background
    cameras: N cameras of size W x H
    names:   N image names (file stems)
    """

    images: np.ndarray
    cameras: Cameras
    names: list[str]

    def __post_init__(self) -> None:
        images = np.asarray(self.images, np.float32)
        n, h, w = len(self.cameras), self.cameras.height, self.cameras.width
        if images.shape != (n, h, w, 3):
            raise ValueError(f"images must be {(n, h, w, 3)} for these cameras, got {images.shape}")
        if len(self.names) != n:
            raise ValueError(f"{len(self.names)} names for {n} images")
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "names", list(self.names))

    def __len__(self) -> int:
        return len(self.cameras)


@dataclasses.dataclass(frozen=True, eq=False)
class SceneTransform:
    """The similarity that took a scene file's world coordinates to the scene's (a normalised capture).

    A point maps as ``p_scene = scale * (rotation @ p_file + translation)``; a camera-to-world matrix
    as ``[rotation @ R | scale * (rotation @ t + translation)]``. ``matrix`` ``[3, 4] = [rotation |
    translation]`` and ``scale`` are what nerfstudio writes to ``dataparser_transforms.json``.

    rotation:    [3, 3] float64 proper rotation
    translation: [3] float64, in file units (applied before ``scale``)
    scale:       world units of the scene per file unit
    orientation, centring: the methods that made it ("up" | "pca"; "focus" | "poses" | "none")
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float
    orientation: str
    centring: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "rotation", np.asarray(self.rotation, np.float64).reshape(3, 3))
        object.__setattr__(self, "translation", np.asarray(self.translation, np.float64).reshape(3))
        object.__setattr__(self, "scale", float(self.scale))

    @property
    def matrix(self) -> np.ndarray:
        """[3, 4] ``[rotation | translation]`` (nerfstudio's ``transform``)."""
        return np.concatenate([self.rotation, self.translation[:, None]], axis=1)

    def apply(self, c2w: np.ndarray) -> np.ndarray:
        """File camera-to-world matrices ``[..., 3, 4]`` -> the scene's (float64)."""
        c2w = np.asarray(c2w, np.float64)
        rot = np.einsum("ij,...jk->...ik", self.rotation, c2w[..., :3])
        t = self.scale * (np.einsum("ij,...j->...i", self.rotation, c2w[..., 3]) + self.translation)
        return np.concatenate([rot, t[..., None]], axis=-1)

    def invert(self, c2w: np.ndarray) -> np.ndarray:
        """Scene camera-to-world matrices ``[..., 3, 4]`` (a render path, say) -> the file's (float64)."""
        c2w = np.asarray(c2w, np.float64)
        back = self.rotation.T
        rot = np.einsum("ij,...jk->...ik", back, c2w[..., :3])
        t = np.einsum("ij,...j->...i", back, c2w[..., 3] / self.scale - self.translation)
        return np.concatenate([rot, t[..., None]], axis=-1)

    def to_dict(self) -> dict:
        """JSON-ready: nerfstudio's ``transform`` and ``scale``, plus the methods."""
        return {
            "transform": self.matrix.tolist(),
            "scale": self.scale,
            "orientation": self.orientation,
            "centring": self.centring,
        }


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene.

    kind:         "blender" | "llff" | "nerfstudio" | "procedural"
    splits:       split name -> SceneSplit
    aabb:         [2, 3] float32 scene box (min, max) in world units, or NDC units for NDC scenes
    near, far:    ray distance bounds (NDC scenes: the NDC ray parameter, [0, 1])
    ndc:          rays are TensoRF NDC rays
    white_bg:     images are composited on white (else black)
    ndc_space:    the NDC space (NDC scenes only)
    depth_bounds: forward-facing scenes: (nearest, farthest) scene depth after rescaling, used by
                  the spiral video path
    root:         directory the scene was read from
    transform:    the normalisation applied to a nerfstudio capture's poses (None: the file's own frame)
    """

    kind: str
    splits: dict[str, SceneSplit]
    aabb: np.ndarray
    near: float
    far: float
    ndc: bool
    white_bg: bool
    ndc_space: NDCSpace | None = None
    depth_bounds: tuple[float, float] | None = None
    root: Path | None = None
    transform: SceneTransform | None = None

    def __post_init__(self) -> None:
        aabb = np.asarray(self.aabb, np.float32).reshape(2, 3)
        object.__setattr__(self, "aabb", aabb)
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))
        if self.ndc and self.ndc_space is None:
            raise ValueError("an NDC scene needs its ndc_space")

    @property
    def ndc_focal(self) -> float | None:
        return None if self.ndc_space is None else self.ndc_space.focal

    @property
    def ndc_near(self) -> float:
        return 1.0 if self.ndc_space is None else self.ndc_space.near

    @property
    def ndc_size(self) -> tuple[int, int] | None:
        """(W, H) of the images that define the NDC space."""
        return None if self.ndc_space is None else (self.ndc_space.width, self.ndc_space.height)

    def split(self, name: str) -> SceneSplit:
        """The split ``name``, or a DataError that lists the loaded ones."""
        if name not in self.splits:
            raise DataError(f"scene has no split {name!r} (loaded: {', '.join(self.splits)})")
        return self.splits[name]
