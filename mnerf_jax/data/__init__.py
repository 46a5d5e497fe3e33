"""Scenes from disk (Blender, LLFF, nerfstudio / instant-ngp), the built-in procedural scene, and
per-pixel rays.

>>> scene = load_scene("data/nerf_synthetic/lego", DataConfig(downscale=8))
>>> origins, directions, rgb = all_rays("train", scene)
"""

from mnerf_jax.data.loader import DATASETS, detect_dataset, load_scene
from mnerf_jax.data.procedural import procedural_scene_dir, write_procedural_scene
from mnerf_jax.data.rays import (
    all_rays,
    camera_rays,
    distort,
    ndc_rays,
    pixel_directions,
    ray_aabb_hit,
    ray_aabb_interval,
    undistort,
    world_rays,
)
from mnerf_jax.data.trajectory import PATH_SPLIT, camera_path
from mnerf_jax.data.types import (
    Cameras,
    DataError,
    DataWarning,
    NDCSpace,
    Scene,
    SceneSplit,
    SceneTransform,
    view_indices,
)

__all__ = [
    "DATASETS",
    "Cameras",
    "DataError",
    "DataWarning",
    "NDCSpace",
    "Scene",
    "SceneSplit",
    "SceneTransform",
    "all_rays",
    "PATH_SPLIT",
    "camera_path",
    "camera_rays",
    "detect_dataset",
    "distort",
    "load_scene",
    "view_indices",
    "ndc_rays",
    "pixel_directions",
    "procedural_scene_dir",
    "ray_aabb_hit",
    "ray_aabb_interval",
    "undistort",
    "world_rays",
    "write_procedural_scene",
]
