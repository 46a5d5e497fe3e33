"""Captures from a phone: the poses normalised into the scene box, cameras of EXIF-rotated images.

**Normalisation** follows nerfstudio's ``auto_orient_and_center_poses`` and its pose scaling:

- centring: ``"poses"`` the mean camera centre; ``"focus"`` the point nearest every camera's optical
  axis, among the cameras that have it in front (dropping those that do not until all do; the mean
  centre when fewer than two remain or their axes are nearly parallel); ``"none"`` the file's origin;
- orientation: ``"up"`` rotates the mean camera up vector (the y axis of the OpenGL camera frame) onto
  +z by the smallest rotation; ``"pca"`` aligns the principal axes of the camera centres with x, y, z
  (largest first, so z is normal to the plane the cameras are spread over), turned 180 degrees about x
  when the cameras' mean up vector would point down;
- scale: the largest absolute coordinate of a camera centre becomes 1, so every camera lies in
  [-1, 1]^3.

The result is a :class:`~mnerf_jax.data.types.SceneTransform` (``p_scene = scale * (R p + t)``).

**EXIF orientation.** A JPEG may store its pixels turned or mirrored and say so with the EXIF
Orientation tag (1-8); images are loaded upright (the tag applied, as Pillow's ``exif_transpose``).
When a frame's camera describes the pixels as stored, :func:`upright_camera` re-expresses it for the
upright image: every pixel keeps its ray. Stored pixel ``(u, v)`` (corner-origin, continuous) lands on
upright pixel ``A (u, v) + b`` for a signed permutation ``A``; then ``fx, fy`` are permuted as the axes
are, ``(cx, cy) -> A (cx, cy) + b``, the tangential distortion vector ``(p2, p1) -> A (p2, p1)`` (radial
terms are unchanged), and the camera-to-world rotation ``R -> R B^T`` with ``B`` the same map on the
OpenGL camera frame (x right, y up: ``B = diag(S A S, 1)``, ``S = diag(1, -1)``). Mirrored tags (2, 4,
5, 7) give a camera frame of determinant -1, whose rays are as correct as the others'.
"""

from __future__ import annotations

import numpy as np

from mnerf_jax.data.types import DataError, SceneTransform

ORIENTATIONS = ("auto", "up", "pca", "none")
CENTRINGS = ("focus", "poses", "none")
# The focus point needs optical axes that cross: the mean projector's least eigenvalue (0 for parallel
# axes, 1/2 for a ring of cameras looking inwards) at least this.
MIN_AXIS_SPREAD = 1e-3


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotation_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3]: the smallest rotation taking the direction ``a`` [3] onto ``b`` [3] (Rodrigues).

    Opposite directions: a half turn about an axis perpendicular to ``a``.
    """
    a, b = _unit(np.asarray(a, np.float64)), _unit(np.asarray(b, np.float64))
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        perp = _unit(perp)
        return 2.0 * np.outer(perp, perp) - np.eye(3)
    k = axis / sin
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sin * kx + (1.0 - cos) * (kx @ kx)


def focus_of_attention(c2w: np.ndarray, start: np.ndarray) -> np.ndarray:
    """[3]: the point nearest (least squares) the optical axes of the cameras ``c2w [N, 3, 4]`` that
    have it in front of them, found by dropping the cameras behind the current estimate until none is;
    ``start`` [3] when fewer than two cameras have it in front or their axes are nearly parallel."""
    origins = np.asarray(c2w, np.float64)[:, :, 3]
    forward = _unit(-np.asarray(c2w, np.float64)[:, :, 2])
    focus = np.asarray(start, np.float64)
    active = np.einsum("ni,ni->n", forward, focus - origins) > 0
    while int(active.sum()) > 1:
        o, d = origins[active], forward[active]
        proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [K, 3, 3], symmetric and idempotent
        a = proj.mean(0)
        if np.linalg.eigvalsh(a)[0] < MIN_AXIS_SPREAD:
            break
        focus = np.linalg.solve(a, np.einsum("kij,kj->i", proj, o) / len(o))
        in_front = np.einsum("ni,ni->n", d, focus - o) > 0
        if in_front.all():
            break
        keep = np.flatnonzero(active)[in_front]
        active = np.zeros_like(active)
        active[keep] = True
    return focus


def normalising_transform(c2w: np.ndarray, orientation: str, centring: str) -> SceneTransform:
    """The transform that orients, centres and scales the cameras ``c2w [N, 3, 4]`` (file frame).

    orientation: "up" | "pca"; centring: "focus" | "poses" | "none" (see the module docstring).
    """
    if orientation not in ("up", "pca"):
        raise DataError(f"data.orientation {orientation!r}: expected one of {', '.join(ORIENTATIONS)}")
    if centring not in CENTRINGS:
        raise DataError(f"data.centring {centring!r}: expected one of {', '.join(CENTRINGS)}")
    c2w = np.asarray(c2w, np.float64)
    positions = c2w[:, :, 3]
    mean = positions.mean(0)
    if centring == "poses":
        centre = mean
    elif centring == "focus":
        centre = focus_of_attention(c2w, mean)
    else:
        centre = np.zeros(3)
    mean_up = c2w[:, :, 1].mean(0)
    if orientation == "up":
        rotation = rotation_onto(mean_up, [0.0, 0.0, 1.0]) if np.linalg.norm(mean_up) > 1e-9 else np.eye(3)
    else:
        spread = positions - mean
        _, vectors = np.linalg.eigh(spread.T @ spread)  # ascending eigenvalues, eigenvectors as columns
        rotation = vectors[:, ::-1].T.copy()  # rows: largest, middle, smallest principal axis
        if np.linalg.det(rotation) < 0:
            rotation[2] = -rotation[2]
        if (rotation @ mean_up)[2] < 0:
            rotation[1:] = -rotation[1:]  # a half turn about x
    translation = -rotation @ centre
    extent = float(np.abs(positions @ rotation.T + translation).max())
    scale = 1.0 / extent if extent > 1e-9 else 1.0
    return SceneTransform(rotation, translation, scale, orientation, centring)


def exif_pixel_map(tag: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(A [2, 2], b [2]) of EXIF orientation ``tag`` for a stored image of ``width`` x ``height``: the
    upright image's pixel coordinates are ``A @ (u, v) + b`` (corner origin, continuous)."""
    w, h = float(width), float(height)
    maps = {
        1: (((1, 0), (0, 1)), (0.0, 0.0)),
        2: (((-1, 0), (0, 1)), (w, 0.0)),  # mirrored left-right
        3: (((-1, 0), (0, -1)), (w, h)),  # turned half a turn
        4: (((1, 0), (0, -1)), (0.0, h)),  # mirrored top-bottom
        5: (((0, 1), (1, 0)), (0.0, 0.0)),  # transposed
        6: (((0, -1), (1, 0)), (h, 0.0)),  # upright once turned a quarter clockwise
        7: (((0, -1), (-1, 0)), (h, w)),  # transversed
        8: (((0, 1), (-1, 0)), (0.0, w)),  # upright once turned a quarter anticlockwise
    }
    if tag not in maps:
        raise DataError(f"EXIF orientation {tag} is not one of 1-8")
    rows, offset = maps[tag]
    return np.array(rows, np.float64), np.array(offset, np.float64)


def upright_size(tag: int, width: int, height: int) -> tuple[int, int]:
    """(width, height) of a stored ``width`` x ``height`` image once EXIF orientation ``tag`` is applied."""
    return (height, width) if tag in (5, 6, 7, 8) else (width, height)


def upright_camera(
    tag: int,
    width: int,
    height: int,
    intrinsics: tuple[float, float, float, float],
    distortion: tuple[float, float, float, float],
    c2w: np.ndarray,
) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float], np.ndarray]:
    """The camera of a stored ``width`` x ``height`` image re-expressed for its upright image.

    intrinsics: (fx, fy, cx, cy) in stored pixels; distortion: OpenCV (k1, k2, p1, p2);
    c2w: [3, 4] OpenGL camera-to-world. Returns the same three for the upright image (its size is
    :func:`upright_size`); the ray through every physical pixel is unchanged.
    """
    a, b = exif_pixel_map(tag, width, height)
    fx, fy, cx, cy = intrinsics
    focal = np.abs(a) @ np.array([fx, fy])  # A diag(f) A^T is diagonal: the focal lengths permuted
    centre = a @ np.array([cx, cy]) + b
    k1, k2, p1, p2 = distortion
    p2_new, p1_new = a @ np.array([p2, p1])
    s = np.diag([1.0, -1.0])
    frame = np.eye(3)
    frame[:2, :2] = s @ a @ s
    c2w = np.asarray(c2w, np.float64)
    rotated = np.concatenate([c2w[:, :3] @ frame.T, c2w[:, 3:]], axis=1)
    new_intrinsics = (float(focal[0]), float(focal[1]), float(centre[0]), float(centre[1]))
    return new_intrinsics, (float(k1), float(k2), float(p1_new), float(p2_new)), rotated
