"""End to end on real data: a short fit of NeRF-Synthetic lego at 1/16 scale (50x50) must learn it."""

from __future__ import annotations

import numpy as np
import pytest

from mnerf_jax.core.config import load_config
from mnerf_jax.data import camera_rays, load_scene
from mnerf_jax.imaging import metrics
from mnerf_jax.tensorf import chunked, render
from mnerf_jax.tensorf.fit import loop as train

# 32^3 -> 64^3 (over the original box) after step 80, an alpha mask and box shrink at step 60,
# 160 steps of 256 rays keep the test short (about half of it is compilation).
OVERRIDES = [
    "data.downscale=16",
    "train.batch_size=256",
    "train.n_iters=160",
    "train.n_voxel_init=32768",
    "train.n_voxel_final=262144",
    "train.upsample_steps=80",
    "train.alpha_mask_steps=60",
]
TEST_VIEWS = 5  # evenly spread over the 200 test views: only these images are read


def _test_psnr(fns, state, split) -> float:
    preds = []
    for i in range(len(split)):
        o, d = camera_rays(split.cameras, i)
        out = chunked.render_image(
            fns,
            state.params,
            None,
            o,
            d,
            state.geometry,
            split.cameras.height,
            split.cameras.width,
            chunk=2500,
        )
        preds.append(out["rgb"])
    return float(np.mean(np.asarray(metrics.psnr(np.stack(preds), split.images))))


@pytest.mark.slow
def test_short_fit_on_lego_learns_the_scene(lego_dir, tmp_path):
    config = load_config("quick", OVERRIDES)
    scene = load_scene(lego_dir, config.data, config.render, ("train",))
    assert scene.split("train").images.shape == (100, 50, 50, 3)
    split = load_scene(lego_dir, config.data, config.render, ("test",), max_views=TEST_VIEWS).split("test")
    assert split.names == ["r_0", "r_50", "r_100", "r_149", "r_199"]
    fns = render.tensorf_field_fns(config.model)
    before = _test_psnr(fns, train.init_state(config, scene), split)

    result = train.fit(config, scene, tmp_path / "run")
    after = _test_psnr(fns, result.state, split)
    # An almost empty field on white starts well below 12 dB; a learnt one ends well above 19 dB.
    assert before < 12.0
    assert after > 19.0, f"test PSNR {after:.2f} dB after {result.steps} steps"
    assert result.steps == 160 and np.prod(result.state.resolution) > 32**3  # upsampled
    box = np.asarray(result.state.geometry.aabb)
    assert np.all(box[0] > -1.5) and np.all(box[1] < 1.5)  # shrunk to the alpha mask
    assert result.last_metrics["psnr"] > 19.0
