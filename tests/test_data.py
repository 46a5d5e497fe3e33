"""Scene loaders on the real lego and fern scenes, the procedural scene, nerfstudio files, rays."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from mnerf_jax.core.config import DataConfig, RenderConfig
from mnerf_jax.data import (
    DataError,
    DataWarning,
    all_rays,
    camera_path,
    camera_rays,
    distort,
    load_scene,
    procedural_scene_dir,
    ray_aabb_hit,
    undistort,
    view_indices,
    world_rays,
    write_procedural_scene,
)
from mnerf_jax.data import procedural as procedural_module

LEGO_VIEWS = 6
LEGO_DOWNSCALE = 16


# ---------------------------------------------------------------- helpers


def reproject(cameras, index: int, directions: np.ndarray) -> np.ndarray:
    """World directions [R, 3] -> pixel coordinates [R, 2] through camera ``index`` (pinhole,
    forward OpenCV distortion): the inverse of ray generation, written independently of it."""
    rot = cameras.c2w[index, :, :3].astype(np.float64)
    local = directions.astype(np.float64) @ rot  # world -> camera frame (rot^T applied to rows)
    x = local[:, 0] / -local[:, 2]
    y = -local[:, 1] / -local[:, 2]  # OpenCV image y points down
    x, y = distort(x, y, cameras.distortion[index])
    u = cameras.fx[index] * x + cameras.cx[index]
    v = cameras.fy[index] * y + cameras.cy[index]
    return np.stack([u, v], axis=-1)


def pixel_centres(width: int, height: int) -> np.ndarray:
    """[H*W, 2] pixel-centre coordinates, row-major."""
    uu, vv = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5, indexing="xy")
    return np.stack([uu.reshape(-1), vv.reshape(-1)], axis=-1)


def distance_to_line(point: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    return np.linalg.norm(np.cross(point - origin, direction), axis=-1)


def ndc_point(p: np.ndarray, focal: float, width: int, height: int, near: float = 1.0) -> np.ndarray:
    """The standard NeRF NDC projection of world points [R, 3] (camera looking down -z)."""
    return np.stack(
        [
            -focal / (width / 2.0) * p[:, 0] / p[:, 2],
            -focal / (height / 2.0) * p[:, 1] / p[:, 2],
            1.0 + 2.0 * near / p[:, 2],
        ],
        axis=-1,
    )


def write_image(path: Path, rgba: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgba).save(path)


# ---------------------------------------------------------------- lego (NeRF-Synthetic)


@pytest.fixture(scope="module")
def lego(lego_dir):
    return load_scene(lego_dir, DataConfig(downscale=LEGO_DOWNSCALE), max_views=LEGO_VIEWS)


def test_lego_images_cameras_match_files(lego, lego_dir):
    meta = json.loads((lego_dir / "transforms_train.json").read_text())
    train = lego.split("train")
    size = 800 // LEGO_DOWNSCALE
    assert lego.kind == "blender" and not lego.ndc and lego.white_bg
    assert train.images.shape == (LEGO_VIEWS, size, size, 3)
    assert train.images.dtype == np.float32
    assert 0.0 <= train.images.min() and train.images.max() <= 1.0
    # max_views keeps evenly spread views, the first and the last included.
    frames = [meta["frames"][i] for i in view_indices(len(meta["frames"]), LEGO_VIEWS)]
    assert train.names[0] == "r_0" and train.names[-1] == Path(meta["frames"][-1]["file_path"]).name
    assert train.names == [Path(f["file_path"]).name for f in frames]
    expected_c2w = np.array([f["transform_matrix"] for f in frames])[:, :3]
    np.testing.assert_allclose(train.cameras.c2w, expected_c2w, atol=1e-6)
    focal = 0.5 * size / math.tan(0.5 * meta["camera_angle_x"])
    np.testing.assert_allclose(train.cameras.fx, focal, rtol=1e-6)
    np.testing.assert_allclose(train.cameras.fy, focal, rtol=1e-6)
    np.testing.assert_allclose(train.cameras.cx, size / 2)
    np.testing.assert_allclose(train.cameras.cy, size / 2)
    assert not train.cameras.has_distortion
    # White background at the corners, the model somewhere in the middle.
    np.testing.assert_allclose(train.images[:, 0, 0], 1.0)
    assert (train.images.min(axis=-1) < 0.5).any()
    np.testing.assert_allclose(lego.aabb, [[-1.5] * 3, [1.5] * 3])
    assert (lego.near, lego.far) == (2.0, 6.0)


def test_lego_downscale_is_area_average_of_composite(lego, lego_dir):
    rgba = np.asarray(Image.open(lego_dir / "train" / "r_0.png"), np.float64) / 255.0
    rgb, alpha = rgba[..., :3], rgba[..., 3:]
    f = LEGO_DOWNSCALE
    composited = rgb * alpha + (1.0 - alpha)
    expected = composited.reshape(800 // f, f, 800 // f, f, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(lego.split("train").images[0], expected, atol=1e-5)
    # Averaging straight colour and alpha separately bleeds the colour of transparent pixels into
    # the edges: a visibly different image, so the check above tells the two apart.
    blocks = lambda a: a.reshape(800 // f, f, 800 // f, f, -1).mean(axis=(1, 3))  # noqa: E731
    straight = blocks(rgb) * blocks(alpha) + (1.0 - blocks(alpha))
    assert np.abs(straight - expected).max() > 0.02


@pytest.mark.parametrize("n", [1, 2, 7, 200])
def test_view_indices_spread_limit_views_from_first_to_last(n: int) -> None:
    for limit in range(1, n + 3):
        chosen = view_indices(n, limit)
        assert chosen == sorted(set(chosen)) and len(chosen) == min(limit, n)
        assert chosen[0] == 0 and (chosen[-1] == n - 1 or limit == 1)
        gaps = np.diff(chosen)
        assert gaps.size == 0 or gaps.max() - gaps.min() <= 1  # evenly spread
    assert view_indices(n, None) == view_indices(n, 0) == list(range(n))


def test_lego_black_background(lego_dir):
    scene = load_scene(
        lego_dir, DataConfig(downscale=LEGO_DOWNSCALE, white_bg=False), splits=("test",), max_views=1
    )
    image = scene.split("test").images[0]
    assert not scene.white_bg
    np.testing.assert_allclose(image[0, 0], 0.0)
    assert list(scene.splits) == ["test"]


def test_lego_rays_follow_camera_geometry(lego):
    cams = lego.split("test").cameras
    w, h = cams.width, cams.height
    radii = np.linalg.norm(cams.centres, axis=-1)
    # NeRF-Synthetic cameras all sit on one sphere around the object and look at the origin.
    assert np.ptp(radii) < 1e-3 and 3.9 < radii.mean() < 4.2
    for i in range(len(cams)):
        o, d = camera_rays(cams, i)
        assert o.shape == d.shape == (w * h, 3) and o.dtype == d.dtype == np.float32
        np.testing.assert_allclose(o, np.broadcast_to(cams.centres[i], o.shape), atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
        np.testing.assert_allclose(reproject(cams, i, d), pixel_centres(w, h), atol=1e-3)
        # The four pixels around the image centre average to the optical axis (-z of c2w)...
        centre = d.reshape(h, w, 3)[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1].mean(axis=(0, 1))
        centre /= np.linalg.norm(centre)
        np.testing.assert_allclose(centre, -cams.c2w[i, :, 2], atol=1e-4)
        # ...which passes through the origin the cameras look at.
        assert distance_to_line(np.zeros(3), o[0], centre) < 1e-3


def test_all_rays_and_aabb_culling(lego):
    split = lego.split("train")
    origins, directions, rgb = all_rays("train", lego)
    n, h, w = split.images.shape[:3]
    assert origins.shape == directions.shape == rgb.shape == (n * h * w, 3)
    np.testing.assert_array_equal(rgb, split.images.reshape(-1, 3))
    o1, d1 = camera_rays(split.cameras, 1)
    np.testing.assert_array_equal(origins[h * w : 2 * h * w], o1)
    np.testing.assert_array_equal(directions[h * w : 2 * h * w], d1)
    hit = ray_aabb_hit(origins, directions, lego.aabb, lego.near, lego.far)
    # Rays through the middle of each image pass through the box; non-white pixels must too.
    middle = np.zeros((n, h, w), bool)
    middle[:, h // 2, w // 2] = True
    assert hit[middle.reshape(-1)].all()
    assert hit[rgb.min(axis=-1) < 0.9].all()


def test_orbit_path_circles_the_scene(lego):
    path = camera_path(lego, 12)
    assert len(path) == 12 and path.width == lego.split("train").cameras.width
    radii = np.linalg.norm(path.centres, axis=-1)
    train_radius = np.linalg.norm(lego.split("train").cameras.centres, axis=-1).mean()
    np.testing.assert_allclose(radii, train_radius, rtol=1e-4)
    assert np.ptp(path.centres[:, 2]) < 1e-3  # one elevation about the (vertical) mean up axis
    steps = np.linalg.norm(np.diff(np.concatenate([path.centres, path.centres[:1]]), axis=0), axis=-1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-4)
    for i in range(len(path)):
        rot = path.c2w[i, :, :3]
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-5)
        assert np.linalg.det(rot) > 0.999
        assert distance_to_line(np.zeros(3), path.centres[i], -path.c2w[i, :, 2]) < 1e-2


# ---------------------------------------------------------------- fern (LLFF)


@pytest.fixture(scope="module")
def fern(fern_dir):
    return load_scene(fern_dir, DataConfig(llff_factor=8, ndc=True))


def test_fern_split_intrinsics_and_bounds(fern, fern_dir):
    raw = np.load(fern_dir / "poses_bounds.npy")
    h_full, w_full, focal_full = raw[0, :15].reshape(3, 5)[:, 4]
    assert fern.kind == "llff" and fern.ndc
    test, train = fern.split("test"), fern.split("train")
    assert test.names == ["image000", "image008", "image016"]
    assert len(train) == len(raw) - 3 and "image001" in train.names
    h, w = test.images.shape[1:3]
    assert (w, h) == (round(w_full / 8), round(h_full / 8))
    np.testing.assert_allclose(train.cameras.fx, focal_full * w / w_full, rtol=1e-6)
    np.testing.assert_allclose(train.cameras.cx, w / 2)
    assert fern.ndc_size == (w, h) and fern.ndc_near == 1.0
    assert fern.ndc_focal == pytest.approx(float(train.cameras.fx[0]))
    near, far = fern.depth_bounds
    assert near == pytest.approx(1 / 0.75)
    assert far / near == pytest.approx(raw[:, 16].max() / raw[:, 15].min())
    np.testing.assert_allclose(fern.aabb, [[-1.5, -1.67, -1.0], [1.5, 1.67, 1.0]], atol=1e-6)
    assert (fern.near, fern.far) == (0.0, 1.0)


def test_fern_poses_recentred_and_rescaled(fern, fern_dir):
    raw = np.load(fern_dir / "poses_bounds.npy")
    raw_centres = raw[:, :15].reshape(-1, 3, 5)[:, :, 3]
    scale = raw[:, 15].min() * 0.75
    order = [int(n[-3:]) for n in fern.split("train").names + fern.split("test").names]
    c2w = np.concatenate([fern.split("train").cameras.c2w, fern.split("test").cameras.c2w])
    centres = c2w[:, :, 3].astype(np.float64)
    # Rigid motion plus uniform scale: pairwise camera distances shrink by exactly the scale.
    pairwise = lambda c: np.linalg.norm(c[:, None] - c[None], axis=-1)  # noqa: E731
    np.testing.assert_allclose(pairwise(centres), pairwise(raw_centres[order]) / scale, atol=1e-5)
    np.testing.assert_allclose(centres.mean(axis=0), 0.0, atol=1e-5)
    back = c2w[:, :, 2].mean(axis=0)
    np.testing.assert_allclose(back / np.linalg.norm(back), [0, 0, 1], atol=1e-6)
    for rot in c2w[:, :, :3]:
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-5)
        assert np.linalg.det(rot) > 0.999


def test_fern_ndc_rays(fern):
    cams = fern.split("test").cameras
    space = cams.ndc
    assert space is not None and (space.width, space.height) == (cams.width, cams.height)
    for i in range(len(cams)):
        o, d = camera_rays(cams, i)
        np.testing.assert_allclose(o[:, 2], -1.0, atol=1e-5)  # origins on the near plane
        np.testing.assert_allclose(o[:, 2] + d[:, 2], 1.0, atol=1e-5)  # t = 1 is infinitely far
        wo, wd = world_rays(cams, i)
        for depth in (1.5, 4.0, 30.0):  # world points along each ray land on its NDC ray
            s = (depth + wo[:, 2]) / -wd[:, 2]  # reach world z = -depth
            p = ndc_point(wo + s[:, None] * wd, space.focal, space.width, space.height)
            t = (p[:, 2] - o[:, 2]) / d[:, 2]
            assert ((t > 0) & (t < 1)).all()
            np.testing.assert_allclose(o + t[:, None] * d, p, atol=2e-4)


def test_fern_spiral_path(fern):
    path = camera_path(fern, 24)
    assert len(path) == 24 and path.ndc == fern.ndc_space
    c2w = np.concatenate([s.cameras.c2w for s in fern.splits.values()])
    radii = np.percentile(np.abs(c2w[:, :, 3]), 90, axis=0)
    assert (np.abs(path.centres) <= radii * 1.0001 + 1e-6).all()
    # Two turns: the path passes its start again halfway.
    np.testing.assert_allclose(path.centres[12, :2], path.centres[0, :2], atol=1e-5)
    # Every camera looks into the scene (down -z) at one focus point beyond the nearest depth.
    forward = -path.c2w[:, :, 2]
    assert (forward[:, 2] < -0.9).all()
    # Intersect the first two optical axes, then check every axis passes there.
    a = np.stack([forward[0], -forward[1]], axis=1)
    s, *_ = np.linalg.lstsq(a, path.centres[1] - path.centres[0], rcond=None)
    focus = path.centres[0] + s[0] * forward[0]
    assert -focus[2] > fern.depth_bounds[0]
    assert (distance_to_line(focus, path.centres, forward) < 1e-4).all()
    o, d = camera_rays(path, 3)
    np.testing.assert_allclose(o[:, 2], -1.0, atol=1e-5)


def test_fern_world_rays_without_ndc(fern_dir):
    scene = load_scene(fern_dir, DataConfig(llff_factor=8, ndc=False), splits=("test",))
    assert not scene.ndc and scene.split("test").cameras.ndc is None
    o, d = camera_rays(scene.split("test").cameras, 0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
    assert scene.near == pytest.approx(0.9 / 0.75) and scene.far == pytest.approx(scene.depth_bounds[1])


def test_ndc_scene_rejects_world_near_far(fern_dir):
    with pytest.raises(DataError, match="NDC"):
        load_scene(fern_dir, DataConfig(llff_factor=8, ndc=True), RenderConfig(near=2.0, far=6.0))
    scene = load_scene(
        fern_dir, DataConfig(llff_factor=8, ndc=True), RenderConfig(near=0.0, far=1.0), splits=("test",)
    )
    assert scene.far == 1.0


# ---------------------------------------------------------------- procedural scene


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_procedural_scene_is_deterministic(tmp_path):
    kw = dict(size=24, n_train=4, n_test=2)
    a = _tree_bytes(write_procedural_scene(tmp_path / "a", seed=3, **kw))
    b = _tree_bytes(write_procedural_scene(tmp_path / "b", seed=3, **kw))
    c = _tree_bytes(write_procedural_scene(tmp_path / "c", seed=4, **kw))
    assert sorted(a) == sorted(
        ["transforms_train.json", "transforms_test.json"]
        + [f"train/r_{i}.png" for i in range(4)]
        + [f"test/r_{i}.png" for i in range(2)]
    )
    assert a == b
    assert a.keys() == c.keys()
    assert all(a[k] != c[k] for k in a if k.endswith(".png"))


def test_procedural_scene_through_blender_loader(tmp_path):
    root = write_procedural_scene(tmp_path / "scene", seed=0, size=32, n_train=6, n_test=3)
    scene = load_scene(root, DataConfig(dataset="auto"))
    assert scene.kind == "blender"
    train = scene.split("train")
    assert train.images.shape == (6, 32, 32, 3) and len(scene.split("test")) == 3
    cams = train.cameras
    np.testing.assert_allclose(np.linalg.norm(cams.centres, axis=-1), 4.0, atol=1e-5)
    for i in range(len(cams)):
        assert distance_to_line(np.zeros(3), cams.centres[i], -cams.c2w[i, :, 2]) < 1e-5
    alpha = np.stack([np.asarray(Image.open(root / "train" / f"r_{i}.png"))[..., 3] for i in range(6)]) / 255
    coverage = (alpha > 0).mean()
    assert 0.1 < coverage < 0.8
    foreground = train.images[alpha > 0.99]
    # Several differently coloured, textured objects: a wide spread of colours.
    assert foreground.std(axis=0).min() > 0.08
    assert len(np.unique((foreground * 8).astype(int), axis=0)) > 20
    # Every object lies inside [-1.2, 1.2]^3: covered pixels' rays all cross that box.
    o, d, _ = all_rays(train)
    inside = ray_aabb_hit(o, d, np.array([[-1.2] * 3, [1.2] * 3]), 0.0, 10.0)
    assert inside[alpha.reshape(-1) > 0].all()


def test_procedural_dataset_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cfg = DataConfig(dataset="procedural", procedural_seed=1, procedural_size=16, procedural_views=4)
    scene = load_scene(None, cfg)
    assert scene.kind == "procedural"
    assert len(scene.split("train")) == 4 and len(scene.split("test")) == 2
    cache = tmp_path / "mnerf-jax" / "procedural"
    entries = [p.name for p in cache.iterdir()]
    assert len(entries) == 1 and not entries[0].startswith(".")  # no temporary left behind
    assert scene.root == cache / entries[0]

    def fail(*args, **kwargs):
        raise AssertionError("the cached scene was rendered again")

    monkeypatch.setattr(procedural_module, "write_procedural_scene", fail)
    again = load_scene(None, cfg)
    np.testing.assert_array_equal(again.split("train").images, scene.split("train").images)
    assert procedural_scene_dir(1, 16, 4, 2) == scene.root


# ---------------------------------------------------------------- nerfstudio / instant-ngp


def _nerfstudio_scene(root: Path, n: int, missing: tuple[int, ...] = (), **top) -> list[dict]:
    """``n`` frames of 20x16 images with per-frame focal lengths; frames in ``missing`` get no file."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        pos = np.array([3 * math.cos(angle), 3 * math.sin(angle), 1.0])
        back = pos / np.linalg.norm(pos)
        right = np.cross([0, 0, 1], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3] = np.stack([right, np.cross(back, right), back, pos], axis=1)
        name = f"images/frame_{i:03d}.png"
        frames.append({"file_path": name, "transform_matrix": m.tolist(), "fl_x": 18.0 + i, "fl_y": 17.0 + i})
        if i not in missing:
            write_image(root / name, rng.integers(0, 256, (16, 20, 3), dtype=np.uint8))
    meta = {"w": 20, "h": 16, "cx": 10.5, "cy": 7.5, "k1": 0.05, "k2": -0.01, "p1": 0.002, "p2": -0.001}
    meta.update(top)
    meta["frames"] = frames[::-1]  # file order must not matter: frames are sorted by path
    (root / "transforms.json").write_text(json.dumps(meta))
    return frames


def test_nerfstudio_loader(tmp_path):
    _nerfstudio_scene(tmp_path, 11, missing=(3,), aabb_scale=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(tmp_path, DataConfig(downscale=2.0))
    ours = [w for w in caught if issubclass(w.category, DataWarning)]
    assert len(ours) == 1 and "1 frame" in str(ours[0].message) and "frame_003" in str(ours[0].message)
    assert scene.kind == "nerfstudio"
    present = [f"frame_{i:03d}" for i in range(11) if i != 3]
    assert scene.split("test").names == [present[0], present[8]]
    assert scene.split("train").names == [n for k, n in enumerate(present) if k not in (0, 8)]
    train = scene.split("train").cameras
    assert (train.width, train.height) == (10, 8)
    focal = np.array([18.0 + int(n[-3:]) for n in scene.split("train").names])
    np.testing.assert_allclose(train.fx, focal / 2, rtol=1e-6)
    np.testing.assert_allclose(train.fy, (focal - 1) / 2, rtol=1e-6)
    np.testing.assert_allclose(train.cx, 10.5 / 2)
    np.testing.assert_allclose(train.distortion, [[0.05, -0.01, 0.002, -0.001]] * len(train), atol=1e-7)
    # instant-ngp: the cube of side aabb_scale around 0.5 in ngp space, mapped back by x * 0.33 + 0.5.
    half = 2 / 2 / 0.33
    np.testing.assert_allclose(scene.aabb, [[-half] * 3, [half] * 3], rtol=1e-6)
    for i in range(len(train)):
        o, d = camera_rays(train, i)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
        # Distorted cameras: projecting each ray back through the lens lands on its pixel centre.
        np.testing.assert_allclose(reproject(train, i, d), pixel_centres(10, 8), atol=1e-3)


def test_nerfstudio_split_lists_and_per_frame_split(tmp_path):
    frames = _nerfstudio_scene(
        tmp_path,
        5,
        train_filenames=["images/frame_001.png", "images/frame_004.png"],
        test_filenames=["./images/frame_002"],
    )
    scene = load_scene(tmp_path, DataConfig(dataset="nerfstudio"))
    assert scene.split("train").names == ["frame_001", "frame_004"]
    assert scene.split("test").names == ["frame_002"]
    np.testing.assert_allclose(scene.aabb, np.reshape(RenderConfig().aabb, (2, 3)))

    meta = json.loads((tmp_path / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["split"] = "test" if frame["file_path"].endswith(("0.png", "3.png")) else "train"
    del meta["train_filenames"], meta["test_filenames"]
    meta.update(aabb_scale=1, scale=0.5, offset=[0.5, 0.7, 0.5])
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path, DataConfig(dataset="nerfstudio"))
    assert scene.split("test").names == ["frame_000", "frame_003"]
    assert len(scene.split("train")) == len(frames) - 2
    np.testing.assert_allclose(scene.aabb, [[-1.0, -1.4, -1.0], [1.0, 0.6, 1.0]], atol=1e-6)


# ---------------------------------------------------------------- ray maths


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-0.6, 0.6),
    y=st.floats(-0.6, 0.6),
    k1=st.floats(-0.25, 0.25),
    k2=st.floats(-0.08, 0.08),
    p1=st.floats(-0.01, 0.01),
    p2=st.floats(-0.01, 0.01),
)
def test_undistort_inverts_opencv_distortion(x, y, k1, k2, p1, p2):
    coeffs = np.array([k1, k2, p1, p2])
    xd, yd = distort(np.array([x]), np.array([y]), coeffs)
    xu, yu = undistort(xd, yd, coeffs)
    assert abs(xu[0] - x) < 1e-5 and abs(yu[0] - y) < 1e-5


def test_ray_aabb_hit_matches_dense_sampling():
    rng = np.random.default_rng(7)
    origins = rng.uniform(-4, 4, (1000, 3))
    directions = rng.normal(size=(1000, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    aabb = np.array([[-1.0, -1.5, -0.5], [1.5, 1.0, 0.8]])
    near, far = 0.5, 5.0
    hit = ray_aabb_hit(origins, directions, aabb, near, far)
    t = np.linspace(near, far, 2001)
    points = origins[:, None] + t[None, :, None] * directions[:, None]
    dense = ((points >= aabb[0]) & (points <= aabb[1])).all(axis=-1).any(axis=-1)
    assert 0.05 < hit.mean() < 0.95
    assert hit[dense].all()
    # Sampling can only step over chords shorter than its spacing (2 mm here): a few grazes at most.
    assert (hit & ~dense).sum() <= 3
