"""Bad scene input: each case is a DataError with one line naming the file, and nothing is written."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mnerf_jax.core.config import DataConfig
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import DataError, load_scene, procedural_scene_dir

EYE = np.eye(4).tolist()


def _png(path: Path, width: int = 8, height: int = 8) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((height, width, 4), 128, np.uint8)).save(path)


def _blender(root: Path, n: int = 3, split: str = "train", **meta) -> dict:
    """A small valid Blender split: ``n`` 8x8 RGBA images and their transforms file."""
    for i in range(n):
        _png(root / split / f"r_{i}.png")
    content = {
        "camera_angle_x": 0.7,
        "frames": [{"file_path": f"./{split}/r_{i}", "transform_matrix": EYE} for i in range(n)],
    }
    content.update(meta)
    (root / f"transforms_{split}.json").write_text(json.dumps(content, indent=2))
    return content


def _llff(root: Path, n_poses: int = 4, n_images: int = 4, shape: tuple[int, ...] | None = None) -> None:
    root.mkdir(parents=True, exist_ok=True)
    pose = np.concatenate([np.eye(3), np.zeros((3, 1)), [[16.0], [16.0], [20.0]]], axis=1)
    rows = np.array([np.concatenate([pose.reshape(-1), [1.0, 10.0]]) for _ in range(n_poses)])
    rows[:, 3] = np.arange(n_poses)  # distinct camera positions
    np.save(root / "poses_bounds.npy", rows if shape is None else np.zeros(shape))
    for i in range(n_images):
        _png(root / "images_8" / f"image{i:03d}.png", 2, 2)


def _nerfstudio(root: Path, **meta) -> None:
    root.mkdir(parents=True, exist_ok=True)
    _png(root / "images" / "a.png")
    content = {"fl_x": 10.0, "frames": [{"file_path": "images/a.png", "transform_matrix": EYE}]}
    content.update(meta)
    (root / "transforms.json").write_text(json.dumps(content))


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _missing_image(root: Path) -> str:
    _blender(root)
    (root / "train" / "r_1.png").unlink()
    return "r_1"


def _corrupt_image(root: Path) -> str:
    _blender(root)
    (root / "train" / "r_2.png").write_bytes(b"\x89PNG\r\n\x1a\n not really an image")
    return "r_2.png"


def _truncated_image(root: Path) -> str:
    _blender(root)
    path = root / "train" / "r_0.png"
    path.write_bytes(path.read_bytes()[:45])  # cut inside the image data
    return "r_0.png"


def _malformed_json(root: Path) -> str:
    _blender(root)
    text = (root / "transforms_train.json").read_text().splitlines()
    text[3] = text[3] + ","  # a dangling comma on line 4
    (root / "transforms_train.json").write_text("\n".join(text[:4]) + "\n")
    return "transforms_train.json: malformed JSON at line"


def _mixed_sizes(root: Path) -> str:
    _blender(root)
    _png(root / "train" / "r_2.png", 8, 6)
    return "r_2.png"


def _empty_split(root: Path) -> str:
    _blender(root, frames=[])
    return "transforms_train.json: the split is empty"


def _missing_fov(root: Path) -> str:
    content = _blender(root)
    del content["camera_angle_x"]
    (root / "transforms_train.json").write_text(json.dumps(content))
    return "transforms_train.json: missing camera_angle_x"


def _bad_matrix(root: Path) -> str:
    _blender(root, frames=[{"file_path": "./train/r_0", "transform_matrix": [[1, 0], [0, 1]]}])
    return "transforms_train.json: frame 0: transform_matrix must be 4x4"


def _missing_test_split(root: Path) -> str:
    _blender(root)
    (root / "transforms_test.json").unlink(missing_ok=True)
    return "transforms_test.json: no such file"


def _poses_wrong_shape(root: Path) -> str:
    _llff(root, shape=(4, 15))
    return "poses_bounds.npy: expected an array of shape [N, 17]"


def _poses_count_mismatch(root: Path) -> str:
    _llff(root, n_poses=4, n_images=3)
    return "images_8: 3 images but poses_bounds.npy has 4 poses"


def _poses_not_an_array(root: Path) -> str:
    _llff(root)
    (root / "poses_bounds.npy").write_bytes(b"garbage")
    return "poses_bounds.npy: unreadable"


def _missing_llff_folder(root: Path) -> str:
    _llff(root)
    for p in (root / "images_8").iterdir():
        p.unlink()
    (root / "images_8").rmdir()
    return "images_8: no such image folder"


def _nerfstudio_no_intrinsics(root: Path) -> str:
    _nerfstudio(root, fl_x=None)
    return "missing intrinsics (fl_x or camera_angle_x)"


def _nerfstudio_no_images(root: Path) -> str:
    _nerfstudio(root, frames=[{"file_path": "images/nowhere.png", "transform_matrix": EYE}])
    return "transforms.json: none of the 1 frames has an image file"


def _nerfstudio_fisheye(root: Path) -> str:
    _nerfstudio(root, camera_model="OPENCV_FISHEYE")
    return "camera_model 'OPENCV_FISHEYE' is not supported"


def _nerfstudio_size_mismatch(root: Path) -> str:
    _nerfstudio(root, w=16, h=8)
    return "intrinsics say 16x8"


def _unknown_layout(root: Path) -> str:
    (root / "notes.txt").write_text("nothing here")
    return "not a known scene layout"


CASES: dict[str, tuple[Callable[[Path], str], dict]] = {
    "missing image": (_missing_image, {"splits": ("train",)}),
    "corrupt image": (_corrupt_image, {"splits": ("train",)}),
    "truncated image": (_truncated_image, {"splits": ("train",)}),
    "malformed json": (_malformed_json, {"splits": ("train",)}),
    "mixed sizes": (_mixed_sizes, {"splits": ("train",)}),
    "empty split": (_empty_split, {"splits": ("train",)}),
    "missing camera_angle_x": (_missing_fov, {"splits": ("train",)}),
    "bad matrix": (_bad_matrix, {"splits": ("train",)}),
    "missing split file": (_missing_test_split, {}),
    "poses wrong shape": (_poses_wrong_shape, {}),
    "poses count mismatch": (_poses_count_mismatch, {}),
    "poses unreadable": (_poses_not_an_array, {}),
    "missing llff folder": (_missing_llff_folder, {}),
    "nerfstudio no intrinsics": (_nerfstudio_no_intrinsics, {"splits": ("test",)}),
    "nerfstudio no images": (_nerfstudio_no_images, {"splits": ("test",)}),
    "nerfstudio fisheye": (_nerfstudio_fisheye, {"splits": ("test",)}),
    "nerfstudio size mismatch": (_nerfstudio_size_mismatch, {"splits": ("test",)}),
    "unknown layout": (_unknown_layout, {}),
}


@pytest.mark.filterwarnings("ignore::mnerf_jax.data.DataWarning")
@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_data_error(case, tmp_path):
    make, load_kwargs = CASES[case]
    expected = make(tmp_path)
    before = _snapshot(tmp_path)
    with pytest.raises(DataError) as info:
        load_scene(tmp_path, DataConfig(llff_factor=8), **load_kwargs)
    message = str(info.value)
    assert "\n" not in message
    assert expected in message
    assert isinstance(info.value, MnerfError)
    assert _snapshot(tmp_path) == before  # nothing written


def test_valid_small_scenes_load(tmp_path):
    """The builders above make loadable scenes, so each failure comes from the one defect."""
    _blender(tmp_path / "b")
    _blender(tmp_path / "b", split="test")
    assert len(load_scene(tmp_path / "b", DataConfig()).split("train")) == 3
    _llff(tmp_path / "l")
    scene = load_scene(tmp_path / "l", DataConfig(llff_factor=8, llff_hold=2, ndc=True))
    assert scene.split("test").names == ["image000", "image002"]
    _nerfstudio(tmp_path / "n")
    assert load_scene(tmp_path / "n", DataConfig(llff_hold=8), splits=("test",)).split("test").names == ["a"]


def test_bad_arguments(tmp_path):
    with pytest.raises(DataError, match="needs a scene directory"):
        load_scene(None, DataConfig(dataset="blender"))
    with pytest.raises(DataError, match="no such scene directory"):
        load_scene(tmp_path / "absent", DataConfig())
    with pytest.raises(DataError, match="unknown dataset"):
        load_scene(tmp_path, DataConfig(dataset="colmap"))
    _blender(tmp_path)
    with pytest.raises(DataError, match="NDC rays need a forward-facing"):
        load_scene(tmp_path, DataConfig(ndc=True), splits=("train",))
    with pytest.raises(DataError, match="downscale must be >= 1"):
        load_scene(tmp_path, DataConfig(downscale=0.5), splits=("train",))
    with pytest.raises(DataError, match="procedural scene needs size >= 8"):
        procedural_scene_dir(0, size=4, cache_root=tmp_path / "cache")
    assert not (tmp_path / "cache").exists()
