"""Forward-facing (NDC) scenes in the watermark's paths: phase 3's novel views on the spiral render path, and
a short embedding of a tiny synthetic LLFF scene with every path the presets take (cached source, read
window, phase 3 with novel views)."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from mnerf_jax.core.config import load_config
from mnerf_jax.data import load_scene, trajectory
from mnerf_jax.data.rays import camera_rays, ndc_rays, world_rays
from mnerf_jax.data.types import Cameras, NDCSpace
from mnerf_jax.watermark import embed as E
from mnerf_jax.watermark import novel_views, phase3
from mnerf_jax.watermark import run as wm_run

DEPTHS = (1.0, 8.0)  # the synthetic cameras' (nearest, farthest) scene depth


def _forward_cameras(n: int = 9, seed: int = 0) -> Cameras:
    """``n`` cameras near the plane z = 0, looking down -z (a few degrees of tilt), with an NDC space."""
    rng = np.random.default_rng(seed)
    c2w = np.zeros((n, 3, 4))
    for i in range(n):
        tilt = rng.normal(0.0, 0.03, 3)
        c2w[i, :, :3] = _rotation(tilt)
        c2w[i, :, 3] = [rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(-0.02, 0.02)]
    ones = np.ones(n)
    return Cameras(
        c2w=c2w,
        fx=40.0 * ones,
        fy=40.0 * ones,
        cx=16.0 * ones,
        cy=12.0 * ones,
        distortion=np.zeros((n, 4)),
        width=32,
        height=24,
        ndc=NDCSpace(focal=40.0, width=32, height=24, near=1.0),
    )


def _rotation(angles: np.ndarray) -> np.ndarray:
    """A rotation matrix from small x, y, z angles (radians)."""
    a, b, c = angles
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


@settings(max_examples=20, deadline=None)
@given(count=st.integers(0, 24), seed=st.integers(0, 2**31 - 1), cams_seed=st.integers(0, 50))
def test_novel_ndc_views_lie_near_the_cameras_plane_and_look_forward(
    count: int, seed: int, cams_seed: int
) -> None:
    cams = _forward_cameras(seed=cams_seed)
    novel = novel_views.novel_cameras(cams, count, seed, "sphere", 5.0, depth_bounds=DEPTHS)
    assert len(novel) == count and (novel.width, novel.height) == (cams.width, cams.height)
    assert novel.ndc == cams.ndc  # their rays are mapped to NDC as the training rays are
    if not count:
        return
    np.testing.assert_allclose(novel.fx, cams.fx[0])
    c2w = cams.c2w.astype(np.float64)
    avg = trajectory.average_pose(c2w)
    # Within the spiral's radii (the 90th percentile of the cameras' offsets per axis) of the average pose,
    # so within a few hundredths of the cameras' plane in depth.
    radii = np.percentile(np.abs(c2w[:, :, 3]), 90, axis=0)
    local = (novel.c2w[:, :, 3].astype(np.float64) - avg[:, 3]) @ avg[:, :3]
    assert np.all(np.abs(local) <= radii + 1e-5)
    assert np.all(np.abs(local[:, 2]) <= 0.03)
    # Looking forward (down the average pose's -z, within a few degrees), all at one point in front.
    forward = -novel.c2w[:, :, 2].astype(np.float64)
    assert np.all(forward @ -avg[:, 2] > math.cos(math.radians(15.0)))
    if count >= 3:  # the optical axes meet at one point, between the scene's near depth and 5x its far one
        target = trajectory.focus_point(novel.c2w.astype(np.float64))
        to_target = target - novel.c2w[:, :, 3].astype(np.float64)
        off_axis = to_target - (to_target * forward).sum(-1, keepdims=True) * forward
        np.testing.assert_allclose(off_axis, 0.0, atol=1e-4)
        depth = (target - avg[:, 3]) @ -avg[:, 2]
        assert DEPTHS[0] * 0.9 - 1e-4 <= depth <= DEPTHS[1] * 5.0
    again = novel_views.novel_cameras(cams, count, seed, depth_bounds=DEPTHS)
    np.testing.assert_array_equal(novel.c2w, again.c2w)  # seeded; density and margin do not apply


def test_novel_ndc_views_are_poses_of_the_render_path_with_ndc_rays() -> None:
    # The path's poses at its own angles are the render path's frames; a novel camera's rays are the NDC map
    # of its world rays, as a training camera's are.
    cams = _forward_cameras()
    c2w = cams.c2w.astype(np.float64)
    frames = trajectory.spiral_poses(c2w, DEPTHS, 12)
    angles = np.linspace(0.0, 2 * math.pi * trajectory.SPIRAL_ROTATIONS, 13)[:-1]
    np.testing.assert_allclose(trajectory.spiral_poses_at(c2w, DEPTHS, angles), frames, atol=1e-12)
    novel = novel_views.novel_cameras(cams, 3, 7, depth_bounds=DEPTHS)
    o, d = camera_rays(novel, 1)
    wo, wd = world_rays(novel, 1, normalize=False)
    space = cams.ndc
    expected = ndc_rays(wo, wd, space.focal, space.width, space.height, space.near)
    np.testing.assert_allclose(o, expected[0], atol=1e-6)
    np.testing.assert_allclose(d, expected[1], atol=1e-6)
    np.testing.assert_allclose(o[:, 2], -1.0, atol=1e-5)  # NDC origins on the near plane
    assert not np.allclose(novel.c2w[0], novel.c2w[1])
    with pytest.raises(ValueError, match="depth bounds"):
        novel_views.novel_cameras(cams, 3, 0)
    with pytest.raises(ValueError, match="density"):
        novel_views.novel_cameras(cams, 3, 0, "cube", depth_bounds=DEPTHS)


# ------------------------------------------------------------------ a tiny synthetic forward-facing scene


def write_forward_facing_scene(root: Path, views: int = 9, width: int = 32, height: int = 24) -> Path:
    """An LLFF folder (``poses_bounds.npy``, ``images_8/``) of ``views`` cameras on a small grid in a plane,
    looking at a textured wall between depths 2 and 6 (each image the wall's pattern, shifted by the
    camera's offset: a parallax of a few pixels)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "images_8").mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    texture = rng.uniform(0.1, 0.9, (height // 4 + 4, width // 4 + 4, 3))
    texture = np.kron(texture, np.ones((4, 4, 1)))  # 4-px blocks, so that LL2 sees them
    rows = []
    focal = 30.0
    for i in range(views):
        x, y = (i % 3 - 1) * 0.2, (i // 3 - 1) * 0.15
        # LLFF's columns: [down, right, back | translation | (H, W, focal)].
        pose = np.array([[0.0, 1.0, 0.0, x, height], [-1.0, 0.0, 0.0, y, width], [0.0, 0.0, 1.0, 0.0, focal]])
        rows.append(np.concatenate([pose.ravel(), [2.0, 6.0]]))
        dx, dy = 8 + round(x * 10), 8 - round(y * 10)
        image = texture[dy : dy + height, dx : dx + width]
        Image.fromarray((image * 255).astype(np.uint8)).save(root / "images_8" / f"{i:03d}.png")
    np.save(root / "poses_bounds.npy", np.stack(rows))
    return root


TINY_LLFF_FIT = [
    "train.n_iters=30",
    "train.batch_size=512",
    "train.n_voxel_init=4096",
    "train.n_voxel_final=4096",
    "train.upsample_steps=",
    "train.alpha_mask_steps=",
    "train.checkpoint_every=30",
    "render.max_samples=32",
    "model.density_ranks=4,4,4",
    "model.appearance_ranks=8,8,8",
    "model.app_features=12",
    "model.mlp_width=32",
]
# The embed_cpu_quality paths (cached frozen source, read window, phase 3 with novel views) in a few steps.
TINY_LLFF_EMBED = [
    "watermark.schedule.phase1_steps=2",
    "watermark.schedule.phase2_steps=2",
    "watermark.schedule.cache_source=true",
    "watermark.schedule.jitter=false",
    "watermark.checkpoint_every=4",
    "watermark.module.wm_ranks=4,4,4",
    "watermark.augment.prob=0",
    "watermark.reading.window=0.72",
    "watermark.phase3.steps=2",
    "watermark.phase3.views=2",
    "watermark.phase3.batch=4",
]


@pytest.mark.slow  # compilations of a fit, a cached embedding step and phase 3: about 45 s of CPU
def test_a_tiny_forward_facing_scene_embeds_with_phase3_novel_views(
    tmp_path: Path, make_decoder: Callable[..., Path]
) -> None:
    from mnerf_jax.cli.fit import fit_run

    data = write_forward_facing_scene(tmp_path / "scene")
    config = load_config("llff", [*TINY_LLFF_FIT, "data.llff_factor=8"])
    fit_run(config, data, tmp_path / "fit", evaluate=False, quiet=True)
    scene = load_scene(data, config.data, config.render, ("train",))
    assert scene.ndc and scene.depth_bounds is not None
    decoder = make_decoder(tmp_path / "dec8.npz", 8, scene.split("train").images)
    out = tmp_path / "wm"
    result = E.embed(
        tmp_path / "fit", out, 2, 8, overrides=TINY_LLFF_EMBED, decoder_path=decoder, progress=False
    )
    assert result.steps == 4 + 2 and result.last_metrics["phase3_steps"] == 2
    run = wm_run.load_watermarked_run(out)
    assert run.geometry.ndc
    # The refit set: every ID's renders of the training views and of the two spiral views.
    split = scene.split("train")
    data_set = phase3.render_refit_set(
        run, split.cameras, run.config.watermark, split.images, depth_bounds=scene.depth_bounds
    )
    views = len(split.cameras) + 2
    # Without augmentations the set keeps each render as its two reads (as it is, rounded; phase3.reads_of).
    assert data_set.compact and data_set.renders.shape[:3] == (2, views, 2)
    # The photographs (no clean model given), and images from outside the scene.
    photographs = len(split.cameras)
    assert data_set.negatives.shape[0] == photographs + phase3.generic_count(photographs)
    assert data_set.attacked is None and data_set.attacked_negatives is None  # phase3.attacked is 0
    assert np.all(np.isfinite(data_set.renders))
    assert data_set.renders.min() >= 0.0 and data_set.renders.max() <= 1.0
