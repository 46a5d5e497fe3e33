"""Phone captures in nerfstudio's transforms.json: a small capture made here from real JPEG files (EXIF
orientation tags, OpenCV distortion, a frame of twice the size, a frame listed without its file), its poses
normalised into the scene box, and the rays of the normalised scene against the file's."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image, ImageOps

from mnerf_jax.cli.fit import choose_preset
from mnerf_jax.core.config import DataConfig, RenderConfig, load_preset
from mnerf_jax.data import Cameras, DataError, DataWarning, camera_rays, load_scene, world_rays
from mnerf_jax.data.capture import normalising_transform, upright_camera
from mnerf_jax.data.nerfstudio import resolve_orientation

W, H = 24, 16  # the upright images
TRUE_INTRINSICS = (20.0, 21.0, 12.3, 7.6)  # fx, fy, cx, cy of the upright images
TRUE_DISTORTION = (0.03, -0.01, 0.002, -0.001)  # k1, k2, p1, p2
RING = 16
# Frames stored turned, their cameras given for the pixels as stored (per-frame w, h, intrinsics): tags.
STORED_TURNED = {"frame_002": 6, "frame_003": 8, "frame_004": 3}
UPRIGHT_DESCRIBED = "frame_006"  # stored turned (tag 6), its camera given for the upright image
DOUBLE_SIZE = "frame_007"  # stored at 48x32 with its own w, h and intrinsics
MISSING = "frame_005"  # listed, no file
# What displays a stored image upright is the tag's transpose; the stored pixels are the inverse one's.
_TO_STORED = {3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}
_INVERSE_TAG = {3: 3, 6: 8, 8: 6}


def _rotation(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def _ring(n: int, elevation: float, radius: float = 2.0) -> np.ndarray:
    """[n, 3, 4] OpenGL cameras evenly spaced on a ring about the z axis, looking at the origin, no roll."""
    out = []
    for i in range(n):
        azimuth = 2.0 * math.pi * i / n
        pos = radius * np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        back = pos / np.linalg.norm(pos)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        out.append(np.stack([right, np.cross(back, right), back, pos], axis=1))
    return np.stack(out)


def _to_file_frame(c2w: np.ndarray, rotation: np.ndarray, scale: float, offset: np.ndarray) -> np.ndarray:
    """Cameras of a frame where a point p is ``scale * rotation @ p + offset`` (a COLMAP-like frame)."""
    rot = np.einsum("ij,njk->nik", rotation, c2w[:, :, :3])
    pos = scale * c2w[:, :, 3] @ rotation.T + offset
    return np.concatenate([rot, pos[:, :, None]], axis=-1)


def _upright_pattern(seed: int) -> Image.Image:
    """A W x H picture whose every turn or mirror looks different: red grows to the right, green downwards."""
    u = (np.arange(W) + 0.5) / W
    v = (np.arange(H) + 0.5) / H
    rgb = np.stack(
        [
            np.broadcast_to(u[None, :], (H, W)),
            np.broadcast_to(v[:, None], (H, W)),
            np.full((H, W), 0.1 * seed),
        ],
        axis=-1,
    )
    return Image.fromarray((rgb * 255 + 0.5).astype(np.uint8))


def _save_jpeg(image: Image.Image, path: Path, tag: int = 1) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    exif = Image.Exif()
    if tag != 1:
        exif[0x0112] = tag
    image.save(path, "JPEG", quality=95, subsampling=0, exif=exif.tobytes())


def make_capture(root: Path, size_mixup: bool = False) -> dict:
    """A 16-camera ring (elevation 25 degrees, tilted, offset and scaled in the file) plus a listed frame with
    no file, written as JPEG files and a nerfstudio transforms.json. Returns the truth per frame name: the
    upright camera in the file's frame and the upright picture."""
    tilt = _rotation((1.0, 2.0, 0.5), 0.7)
    truth_c2w = _to_file_frame(_ring(RING, math.radians(25.0)), tilt, 3.7, np.array([5.0, -2.0, 1.0]))
    names = [f"frame_{i:03d}" for i in range(RING + 1) if f"frame_{i:03d}" != MISSING]
    frames, truth = [], {}
    for k, (name, c2w) in enumerate(zip(names, truth_c2w, strict=True)):
        picture = _upright_pattern(k % 8)
        truth[name] = {"c2w": c2w, "picture": np.asarray(picture, np.float32) / 255.0}
        frame = {
            "file_path": f"images/{name}.jpg",
            "transform_matrix": np.vstack([c2w, [0, 0, 0, 1]]).tolist(),
        }
        path = root / frame["file_path"]
        if name in STORED_TURNED:
            tag = STORED_TURNED[name]
            (fx, fy, cx, cy), dist, stored_c2w = upright_camera(
                _INVERSE_TAG[tag], W, H, TRUE_INTRINSICS, TRUE_DISTORTION, c2w
            )
            stored = picture.transpose(_TO_STORED[tag])
            _save_jpeg(stored, path, tag)
            frame.update(w=stored.width, h=stored.height, fl_x=fx, fl_y=fy, cx=cx, cy=cy)
            frame.update(zip(("k1", "k2", "p1", "p2"), dist, strict=True))
            frame["transform_matrix"] = np.vstack([stored_c2w, [0, 0, 0, 1]]).tolist()
        elif name == UPRIGHT_DESCRIBED:
            _save_jpeg(picture.transpose(_TO_STORED[6]), path, 6)
            frame.update(w=W, h=H)
        elif name == DOUBLE_SIZE and not size_mixup:
            _save_jpeg(picture.resize((2 * W, 2 * H), Image.Resampling.NEAREST), path)
            fx, fy, cx, cy = TRUE_INTRINSICS
            frame.update(w=2 * W, h=2 * H, fl_x=2 * fx, fl_y=2 * fy, cx=2 * cx, cy=2 * cy)
        elif name == DOUBLE_SIZE:
            _save_jpeg(picture.resize((2 * W, 2 * H), Image.Resampling.NEAREST), path)
        else:
            _save_jpeg(picture, path)
        frames.append(frame)
    extra = {"file_path": f"images/{MISSING}.jpg", "transform_matrix": np.eye(4).tolist()}
    fx, fy, cx, cy = TRUE_INTRINSICS
    meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
    meta.update(zip(("k1", "k2", "p1", "p2"), TRUE_DISTORTION, strict=True))
    if not size_mixup:
        meta.update(w=W, h=H)
    meta["frames"] = [*frames[:4], extra, *frames[4:]][::-1]  # file order must not matter
    (root / "transforms.json").write_text(json.dumps(meta))
    return truth


@pytest.fixture(scope="module")
def made_capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("capture")
    return root, make_capture(root)


def _load(root: Path, orientation: str, **data) -> object:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return load_scene(root, DataConfig(dataset="nerfstudio", orientation=orientation, **data))


def _cameras(scene) -> tuple[Cameras, list[str]]:
    """Every loaded camera (train then test) and its name."""
    train, test = scene.split("train"), scene.split("test")
    c2w = np.concatenate([train.cameras.c2w, test.cameras.c2w])
    cams = Cameras(
        c2w=c2w,
        fx=np.concatenate([train.cameras.fx, test.cameras.fx]),
        fy=np.concatenate([train.cameras.fy, test.cameras.fy]),
        cx=np.concatenate([train.cameras.cx, test.cameras.cx]),
        cy=np.concatenate([train.cameras.cy, test.cameras.cy]),
        distortion=np.concatenate([train.cameras.distortion, test.cameras.distortion]),
        width=train.cameras.width,
        height=train.cameras.height,
    )
    return cams, train.names + test.names


def test_the_file_frame_loads_upright_images_with_their_cameras(made_capture):
    root, truth = made_capture
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(root, DataConfig(dataset="nerfstudio", orientation="none"))
    ours = [w for w in caught if issubclass(w.category, DataWarning)]
    assert len(ours) == 1 and "1 frame" in str(ours[0].message) and MISSING in str(ours[0].message)
    assert scene.transform is None
    present = sorted(truth)
    assert scene.split("test").names == [present[0], present[8]]  # every 8th frame held out
    assert scene.split("train").names == [n for k, n in enumerate(present) if k % 8]
    cams, names = _cameras(scene)
    assert (cams.width, cams.height) == (W, H)
    for i, name in enumerate(names):
        np.testing.assert_allclose(cams.c2w[i], truth[name]["c2w"], atol=1e-5, err_msg=name)
        np.testing.assert_allclose(
            [cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]], TRUE_INTRINSICS, rtol=1e-6, err_msg=name
        )
        np.testing.assert_allclose(cams.distortion[i], TRUE_DISTORTION, atol=1e-7, err_msg=name)
    images = np.concatenate([scene.split("train").images, scene.split("test").images])
    for i, name in enumerate(names):
        # Upright: the stored pixels turned by the EXIF tag (a wrong turn is off by a third of the range).
        assert np.abs(images[i] - truth[name]["picture"]).mean() < 0.02, name
    # The stored camera of a frame turned a quarter: its focal lengths are the upright one's swapped.
    meta = json.loads((root / "transforms.json").read_text())
    stored = next(f for f in meta["frames"] if "frame_002" in f["file_path"])
    assert (stored["w"], stored["h"]) == (H, W)
    assert (stored["fl_x"], stored["fl_y"]) == (TRUE_INTRINSICS[1], TRUE_INTRINSICS[0])


@pytest.mark.parametrize("tag", range(1, 9))
def test_upright_camera_keeps_every_pixels_ray(tag):
    """Pillow turns an image of pixel indices upright; the upright camera's ray at each pixel is the stored
    camera's ray at the pixel that landed there."""
    w, h = 7, 5
    c2w = _ring(3, 0.4)[1]
    intrinsics, distortion = (6.0, 6.5, 3.1, 2.7), (0.05, -0.02, 0.01, -0.004)
    index = Image.fromarray(np.arange(w * h, dtype=np.int32).reshape(h, w))
    index.getexif()[0x0112] = tag
    landed = np.asarray(ImageOps.exif_transpose(index)).reshape(-1)
    new_intrinsics, new_distortion, new_c2w = upright_camera(tag, w, h, intrinsics, distortion, c2w)
    up_w, up_h = (h, w) if tag >= 5 else (w, h)
    assert ImageOps.exif_transpose(index).size == (up_w, up_h)
    stored = Cameras(c2w[None], *intrinsics, distortion=distortion, width=w, height=h)
    upright = Cameras(new_c2w[None], *new_intrinsics, distortion=new_distortion, width=up_w, height=up_h)
    _, d_stored = world_rays(stored, 0)
    _, d_upright = world_rays(upright, 0)
    np.testing.assert_allclose(d_upright, d_stored[landed], atol=2e-6)


@pytest.mark.parametrize("orientation", ["up", "pca"])
def test_normalised_capture_is_upright_centred_and_in_the_box(made_capture, orientation):
    root, _ = made_capture
    scene = _load(root, orientation)
    assert scene.transform is not None and scene.transform.orientation == orientation
    cams, _ = _cameras(scene)
    centres = cams.centres.astype(np.float64)
    # The ring was level about its own up axis: that axis is now +z, so every camera is at one height.
    np.testing.assert_allclose(centres[:, 2], centres[0, 2], atol=1e-5)
    assert centres[0, 2] > 0.1  # above the object, as the ring was
    up = cams.c2w[:, :, 1].mean(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-5)
    # Centred on the focus: every optical axis passes through the origin, every camera as far from it.
    forward = -cams.c2w[:, :, 2].astype(np.float64)
    miss = np.linalg.norm(np.cross(forward, -centres), axis=-1) / np.linalg.norm(forward, axis=-1)
    np.testing.assert_allclose(miss, 0.0, atol=1e-5)
    dist = np.linalg.norm(centres, axis=-1)
    np.testing.assert_allclose(dist, dist[0], rtol=1e-5)
    # Scaled: the largest camera coordinate is 1, inside the capture box with room beyond.
    assert abs(np.abs(centres).max() - 1.0) < 1e-5
    assert np.all(np.abs(centres) <= scene.aabb[1] - 0.4)
    np.testing.assert_allclose(scene.aabb, [[-1.5] * 3, [1.5] * 3])
    assert (scene.near, scene.far) == (0.05, 6.0)


@pytest.mark.filterwarnings("ignore::mnerf_jax.data.DataWarning")
def test_normalised_rays_are_the_files_rays_transformed(made_capture):
    root, _ = made_capture
    plain = _load(root, "none")
    for orientation in ("up", "pca"):
        scene = _load(root, orientation)
        t = scene.transform
        for split in ("train", "test"):
            a, b = plain.split(split), scene.split(split)
            np.testing.assert_array_equal(a.images, b.images)
            for i in range(len(a)):
                o_file, d_file = camera_rays(a.cameras, i)
                o, d = camera_rays(b.cameras, i)
                np.testing.assert_allclose(o, t.scale * (o_file @ t.rotation.T + t.translation), atol=2e-5)
                np.testing.assert_allclose(d, d_file @ t.rotation.T, atol=2e-5)
        np.testing.assert_allclose(
            t.invert(t.apply(plain.split("train").cameras.c2w)), plain.split("train").cameras.c2w, atol=1e-5
        )
    # Any split, any number of views: the same transform (computed over every frame with an image).
    test_only = load_scene(root, DataConfig(dataset="nerfstudio"), splits=("test",), max_views=1)
    np.testing.assert_allclose(test_only.transform.matrix, _load(root, "auto").transform.matrix)


@settings(max_examples=40, deadline=None)
@given(
    axis=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1)),
    angle=st.floats(-3.0, 3.0),
    scale=st.floats(0.05, 20.0),
    offset=st.tuples(st.floats(-10, 10), st.floats(-10, 10), st.floats(-10, 10)),
    elevation=st.floats(-0.8, 0.8),
    n=st.integers(3, 12),
    orientation=st.sampled_from(["up", "pca"]),
)
def test_any_tilted_offset_ring_normalises_alike(axis, angle, scale, offset, elevation, n, orientation):
    """Whatever frame a level ring of cameras is given in, normalising puts it level about +z, centred on
    the point its optical axes meet, its largest coordinate 1; every ray is the file's ray transformed."""
    c2w = _to_file_frame(_ring(n, elevation), _rotation(axis, angle), scale, np.asarray(offset))
    t = normalising_transform(c2w, orientation, "focus")
    out = t.apply(c2w)
    centres = out[:, :, 3]
    np.testing.assert_allclose(centres[:, 2], centres[0, 2], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(centres, axis=-1), np.linalg.norm(centres[0]), rtol=1e-6)
    assert abs(np.abs(centres).max() - 1.0) < 1e-9
    up = out[:, :, 1].mean(0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(t.rotation @ t.rotation.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(t.rotation) > 0
    cams = Cameras(c2w, 5.0, 5.0, 3.0, 2.0, distortion=(0.02, 0.0, 0.001, 0.0), width=6, height=4)
    moved = Cameras(out, 5.0, 5.0, 3.0, 2.0, distortion=(0.02, 0.0, 0.001, 0.0), width=6, height=4)
    for i in (0, n - 1):
        o_file, d_file = world_rays(cams, i)
        o, d = world_rays(moved, i)
        expect = t.scale * (o_file.astype(np.float64) @ t.rotation.T + t.translation)
        np.testing.assert_allclose(o, expect, atol=1e-5 * max(1.0, float(np.abs(expect).max())))
        np.testing.assert_allclose(d, d_file @ t.rotation.T, atol=1e-5)


def test_focus_falls_back_to_the_mean_centre_for_parallel_axes():
    c2w = np.tile(np.eye(4)[:3], (4, 1, 1))
    c2w[:, :, 3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 2]]
    t = normalising_transform(c2w, "up", "focus")
    np.testing.assert_allclose(t.apply(c2w)[:, :, 3].mean(0), 0.0, atol=1e-9)
    one = normalising_transform(c2w[:1], "pca", "poses")  # a single camera: centred, no scale to take
    np.testing.assert_allclose(one.apply(c2w[:1])[0, :, 3], 0.0, atol=1e-12)
    assert one.scale == 1.0


def test_frames_of_another_size_need_their_own_intrinsics(tmp_path):
    make_capture(tmp_path, size_mixup=True)
    with pytest.raises(DataError) as info:
        _load(tmp_path, "auto")
    message = str(info.value)
    assert "\n" not in message
    assert f"{DOUBLE_SIZE}.jpg: image is 48x32 but frame_000.jpg is 24x16" in message
    assert "needs its own w and h" in message


def test_auto_orientation_and_the_capture_preset(tmp_path):
    assert resolve_orientation({"fl_x": 1.0, "frames": []}, "auto") == "up"
    assert resolve_orientation({"frames": [{"fl_x": 1.0}]}, "auto") == "up"
    assert resolve_orientation({"fl_x": 1.0, "aabb_scale": 16, "frames": []}, "auto") == "none"
    assert resolve_orientation({"camera_angle_x": 0.7, "frames": []}, "auto") == "none"
    assert resolve_orientation({"aabb_scale": 16, "frames": []}, "pca") == "pca"
    with pytest.raises(DataError, match="data.orientation 'sideways'"):
        resolve_orientation({"frames": []}, "sideways")
    config = load_preset("capture")
    assert config.data.dataset == "nerfstudio" and config.data.llff_hold == 8
    assert config.data.orientation == "auto" and config.train.random_background and not config.data.white_bg
    assert config.render.aabb == (-1.5, -1.5, -1.5, 1.5, 1.5, 1.5) and config.render.near < 0.1
    (tmp_path / "transforms.json").write_text("{}")
    assert choose_preset(None, tmp_path) == "capture"
    assert RenderConfig().near == 2.0  # the blender default, which a normalised capture must not use


def test_a_near_plane_beyond_the_centre_of_a_normalised_capture_is_warned_of(made_capture):
    root, _ = made_capture
    config = DataConfig(dataset="nerfstudio", orientation="up")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        load_scene(root, config, RenderConfig(), ("train",), max_views=2)  # the Blender near of 2
        load_scene(root, config, RenderConfig(near=0.05, far=6.0), ("train",), max_views=2)
    near_warnings = [w for w in caught if "render.near" in str(w.message)]
    assert len(near_warnings) == 1 and "render.near = 2 " in str(near_warnings[0].message)
