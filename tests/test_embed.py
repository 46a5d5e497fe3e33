"""Embedding: patch layout, deferred back-propagation == direct gradient, optimiser groups, tiny runs."""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.core import rundir
from mnerf_jax.core.config import ModelConfig, WatermarkConfig
from mnerf_jax.core.config import watermark_from_flat as wm_config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder_io, dwt
from mnerf_jax.reader import keys as keys_lib
from mnerf_jax.tensorf import raymarch
from mnerf_jax.watermark import deferred as D
from mnerf_jax.watermark import embed as E
from mnerf_jax.watermark import inputs as EI
from mnerf_jax.watermark import model as watermark
from mnerf_jax.watermark import objective as O
from mnerf_jax.watermark import run as wm_run
from mnerf_jax.watermark import step as S

if TYPE_CHECKING:
    from conftest import TinyRuns  # the `tiny` fixture's type (tests/conftest.py)

# ----------------------------------------------------------------------------- toy differentiable renderer


def _image_loss_spec(cfg: WatermarkConfig, phase: int, side: int) -> S.StepSpec:
    """The step spec of the image-loss tests: a default model, a ``side``-pixel square view, unit budgets."""
    return S.StepSpec(
        model=ModelConfig(),
        wm=cfg,
        adam_b1=0.9,
        adam_b2=0.99,
        phase=phase,
        height=side,
        width=side,
        density_budget=1,
        colour_budget=1,
    )


def _toy_params(key: jax.Array) -> dict:
    k1, k2, k3 = jax.random.split(key, 3)
    return {
        "w0": jax.random.normal(k1, (3, 16)) * 2.0,
        "w1": jax.random.normal(k2, (16 + 3, 4)) * 0.5,
        "b1": jax.random.normal(k3, (4,)) * 0.1,
    }


def _toy_render(
    params: dict, rays: tuple[jax.Array, jax.Array], key: jax.Array | None
) -> tuple[jax.Array, dict]:
    """Emission-absorption along 8 samples per ray (jittered given a key) through a sine-feature field."""
    origins, dirs = rays
    t = jnp.broadcast_to(jnp.linspace(0.2, 1.8, 8)[None, :], (origins.shape[0], 8))
    if key is not None:
        t = t + 0.1 * jax.random.uniform(key, (origins.shape[0], 1))
    pts = origins[:, None, :] + dirs[:, None, :] * t[..., None]  # [R, 8, 3]
    h = jnp.sin(pts @ params["w0"])
    view = jnp.broadcast_to(dirs[:, None], h.shape[:2] + (3,))
    out = jnp.concatenate([h, view], -1) @ params["w1"] + params["b1"]
    sigma = jax.nn.softplus(out[..., 0] * 3.0)
    rgb = jax.nn.sigmoid(out[..., 1:])
    alpha = 1.0 - jnp.exp(-sigma * 0.2)
    trans = jnp.exp(-jnp.cumsum(jnp.concatenate([jnp.zeros_like(sigma[:, :1]), sigma[:, :-1] * 0.2], -1), -1))
    weights = alpha * trans
    image = (weights[..., None] * rgb).sum(1) + (1.0 - weights.sum(1, keepdims=True))
    return image, {"samples": jnp.sum(weights > 1e-4)}


def _toy_rays(height: int, width: int) -> tuple[jax.Array, jax.Array]:
    ys, xs = jnp.meshgrid(jnp.linspace(-0.6, 0.6, height), jnp.linspace(-0.6, 0.6, width), indexing="ij")
    dirs = jnp.stack([xs, ys, jnp.full_like(xs, 1.0)], -1).reshape(-1, 3)
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = jnp.broadcast_to(jnp.array([0.0, 0.0, -1.0]), dirs.shape)
    return origins, dirs


def _image_loss(image: jax.Array, extra: dict) -> tuple[jax.Array, dict]:
    """A decoder-like image loss: LL2 → linear → BCE against fixed bits."""
    feat = dwt.ll2(image[None])[0].mean(axis=(0, 1))  # [3]
    logits = jnp.tanh(feat @ extra["w"] + extra["b"]) * 3.0
    bits = jnp.array([1.0, 0.0, 1.0, 1.0])
    loss = jnp.mean(jax.nn.softplus(-logits * (2 * bits - 1)))
    return loss, {"logits": logits}


def _patch_loss(rgb: jax.Array, target: jax.Array) -> jax.Array:
    tv = jnp.mean(jnp.abs(rgb[1:] - rgb[:-1])) + jnp.mean(jnp.abs(rgb[:, 1:] - rgb[:, :-1]))
    return 0.1 * jnp.mean(jnp.abs(rgb - target)) + 0.02 * tv + 0.2 * jnp.mean((rgb - target) ** 2)


# ------------------------------------------------------------------------------------------- layout


@pytest.mark.parametrize("h,w,s", [(32, 32, 16), (20, 27, 8), (8, 8, 64), (17, 16, 16), (5, 9, 4)])
def test_patch_layout_covers_every_pixel_once(h: int, w: int, s: int) -> None:
    layout = D.patch_layout(h, w, s)
    size = min(s, h, w)
    assert layout.size == size and layout.index.shape[1] == size * size
    owned = np.zeros(h * w)
    np.add.at(owned, layout.index.reshape(-1), layout.owner.reshape(-1))
    np.testing.assert_array_equal(owned, 1.0)
    # Every patch is a real square of the image.
    for idx in layout.index:
        rows, cols = np.divmod(idx.reshape(size, size), w)
        assert (np.diff(rows, axis=0) == 1).all() and (np.diff(cols, axis=1) == 1).all()


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 300), st.integers(1, 300), st.integers(1, 128), st.integers(1, 16))
def test_tiling_patch_size_fewest_patches_least_overlap(h: int, w: int, s: int, floor: int) -> None:
    size = D.tiling_patch_size(h, w, s, floor)
    cap = min(s, h, w)
    assert min(floor, cap) <= size <= cap
    layout = D.patch_layout(h, w, size)
    # As few patches as the largest allowed side needs, and never more rendered pixels than with it.
    widest = D.patch_layout(h, w, cap)
    assert layout.num_patches == widest.num_patches
    assert layout.index.size <= widest.index.size


def test_tiling_patch_size_on_a_100px_view() -> None:
    assert D.tiling_patch_size(100, 100, 64) == 50  # 4 patches, 10,000 rays (64 px: 16,384)
    assert D.tiling_patch_size(100, 100, 64, 11) == 50
    assert D.tiling_patch_size(20, 20, 19, 11) == 11  # ceil(20/2) = 10 < the SSIM window
    assert D.tiling_patch_size(64, 64, 64) == 64


def test_assemble_inverts_gather() -> None:
    h, w = 11, 13
    layout = D.patch_layout(h, w, 4)
    image = jax.random.uniform(jax.random.PRNGKey(0), (h, w, 3))
    patches = image.reshape(-1, 3)[layout.index]
    out = D.assemble(patches, jnp.asarray(layout.index), jnp.asarray(layout.owner), h, w)
    np.testing.assert_allclose(np.asarray(out), np.asarray(image))


# -------------------------------------------------------------------------------- deferred == direct


def _gradients(height: int, width: int, patch: int, use_patch_loss: bool = True, whole: bool = False):
    params = _toy_params(jax.random.PRNGKey(1))
    extra = {"w": jax.random.normal(jax.random.PRNGKey(2), (3, 4)), "b": jnp.zeros(4)}
    rays = _toy_rays(height, width)
    targets = jax.random.uniform(jax.random.PRNGKey(3), (height * width, 3))
    layout = D.whole_view_layout(height, width) if whole else D.patch_layout(height, width, patch)
    args = (jnp.asarray(layout.index), jnp.asarray(layout.owner), jax.random.PRNGKey(4), height, width)
    ploss = _patch_loss if use_patch_loss else None
    loss_d, _, image, g_params_d, g_extra_d = jax.jit(
        lambda p, e: D.deferred_grad(
            _toy_render, _image_loss, ploss, p, e, rays, targets, *args[:3], height, width
        )
    )(params, extra)
    (loss_r, _), (g_params_r, g_extra_r) = jax.value_and_grad(
        lambda p, e: D.direct_objective(
            _toy_render, _image_loss, ploss, p, e, rays, targets, *args[:3], height, width
        ),
        argnums=(0, 1),
        has_aux=True,
    )(params, extra)
    return (loss_d, g_params_d, g_extra_d), (loss_r, g_params_r, g_extra_r), image, layout


def _assert_trees_close(a, b, tol=1e-4) -> None:
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        scale = max(1.0, float(jnp.max(jnp.abs(y))))
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=tol * scale, rtol=0)


@pytest.mark.parametrize("h, w, patch", [(13, 10, 4), (8, 8, 8)])
def test_deferred_gradient_equals_direct_gradient(h: int, w: int, patch: int) -> None:
    # 13×10 pixels in 4-px patches: border patches overlap, every patch is jittered with its own key.
    # 8×8 in one 8-px patch: the single-patch path (one render on the graph, no graph-free render).
    deferred, direct, image, layout = _gradients(h, w, patch)
    assert layout.num_patches == (1 if patch == 8 else 12)
    assert abs(float(deferred[0]) - float(direct[0])) < 1e-5
    _assert_trees_close(deferred[1], direct[1])
    _assert_trees_close(deferred[2], direct[2])
    # Not vacuous: the gradients are far from zero.
    assert float(jnp.abs(direct[1]["w0"]).max()) > 1e-3
    # The graph-free render is the jittered image the patches re-render.
    rays = _toy_rays(h, w)
    params = _toy_params(jax.random.PRNGKey(1))
    keys = D.patch_keys(jax.random.PRNGKey(4), layout.num_patches)
    pairs = zip(layout.index, keys, strict=True)
    patches = [_toy_render(params, D.gather_rays(rays, i), k)[0] for i, k in pairs]
    expected = D.assemble(jnp.stack(patches), jnp.asarray(layout.index), jnp.asarray(layout.owner), h, w)
    np.testing.assert_allclose(np.asarray(image), np.asarray(expected), atol=1e-6)


def test_a_whole_view_patch_of_a_non_square_view_takes_the_patch_loss_on_the_view() -> None:
    # A cached source renders the whole view as one patch, of the view's own shape (LLFF's views are 4:3).
    deferred, direct, _, layout = _gradients(7, 11, 0, whole=True)
    assert layout.num_patches == 1 and layout.rays == 77 and layout.size == 7
    assert D.patch_shape(layout.index, 7, 11) == (7, 11)
    assert abs(float(deferred[0]) - float(direct[0])) < 1e-5
    _assert_trees_close(deferred[1], direct[1])
    _assert_trees_close(deferred[2], direct[2])


def test_deferred_gradient_equals_one_full_render_gradient() -> None:
    # With no jitter shared between patches, the reference is one render of all rays at once.
    h, w = 12, 12
    params = _toy_params(jax.random.PRNGKey(5))
    extra = {"w": jax.random.normal(jax.random.PRNGKey(6), (3, 4)), "b": jnp.zeros(4)}
    rays = _toy_rays(h, w)
    targets = jax.random.uniform(jax.random.PRNGKey(7), (h * w, 3))
    layout = D.patch_layout(h, w, 5)  # 5 does not divide 12: overlapping border patches
    fixed = lambda p, r, k: _toy_render(p, r, None)  # no jitter: per-ray results independent of batching
    idx, own = jnp.asarray(layout.index), jnp.asarray(layout.owner)

    def full(p, e):
        image = fixed(p, rays, None)[0].reshape(h, w, 3)
        loss, _ = _image_loss(image, e)
        flat = image.reshape(-1, 3)
        s = layout.size
        patch = sum(_patch_loss(flat[i].reshape(s, s, 3), targets[i].reshape(s, s, 3)) for i in layout.index)
        return loss + patch

    g_ref = jax.grad(full, argnums=(0, 1))(params, extra)
    _, _, _, g_p, g_e = D.deferred_grad(
        fixed, _image_loss, _patch_loss, params, extra, rays, targets, idx, own, jax.random.PRNGKey(9), h, w
    )
    _assert_trees_close(g_p, g_ref[0])
    _assert_trees_close(g_e, g_ref[1])


def _small_watermarked_scene(cfg, num_ids: int, h: int, w: int) -> tuple:
    """``(model, params, geometry, rays, targets [h·w, 3])``: a random watermarked TensoRF on a 6³ grid with
    semi-transparent matter (σ ≈ 2, Δt = 0.3, distance scale 1: every sample gets gradient), seen by an
    ``h × w`` pinhole camera at z = 4."""
    from mnerf_jax.tensorf import field

    model = ModelConfig(
        density_ranks=(2, 2, 2), appearance_ranks=(3, 3, 3), app_features=6, mlp_width=16, density_shift=0.0
    )
    base = field.init_field(jax.random.PRNGKey(0), model, (6, 6, 6))
    base["density"] = jax.tree.map(lambda a: a + 0.6, base["density"])  # visible matter
    params = watermark.add_watermark(jax.random.PRNGKey(1), base, cfg, num_ids, extra_scale=0.3)
    geometry = raymarch.make_geometry(
        np.array([[-1.5] * 3, [1.5] * 3]), (6, 6, 6), n_samples=24, distance_scale=1.0
    )
    ys, xs = jnp.meshgrid(jnp.linspace(-0.35, 0.35, h), jnp.linspace(-0.35, 0.35, w), indexing="ij")
    dirs = jnp.stack([xs, ys, -jnp.ones_like(xs)], -1).reshape(-1, 3)
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    rays = (jnp.broadcast_to(jnp.array([0.0, 0.0, 4.0]), dirs.shape), dirs)
    targets = jax.random.uniform(jax.random.PRNGKey(2), (h * w, 3))
    return model, params, geometry, rays, targets


@pytest.mark.parametrize("h, w, size", [(13, 12, 11)])
def test_deferred_gradient_equals_direct_gradient_with_the_real_renderer_and_losses(
    h: int, w: int, size: int
) -> None:
    # The watermarked TensoRF through render_rays (dense budgets, no jitter), the decoder's BCE on LL2 plus
    # Watson, and the phase-2 patch loss (L1 + TV + SSIM) on overlapping 11-px patches of a 13×12 image.
    # (The single-patch path, one render on the graph, is test_deferred_gradient_equals_direct_gradient
    # [8-8-8]; a second real-renderer case for it would cost compilation and test no other code.)
    from mnerf_jax.imaging import losses
    from mnerf_jax.reader import decoder
    from mnerf_jax.tensorf import render

    cfg = wm_config(wm_ranks=(2, 2, 2))
    model, params, geometry, rays, targets = _small_watermarked_scene(cfg, 3, h, w)
    fns = watermark.field_fns(model, cfg)
    dec = decoder.init_decoder(jax.random.PRNGKey(3), 8)
    message = jnp.array([1, 0, 1, 1, 0, 0, 1, 0], jnp.float32)

    def render_fn(p, r, k):
        out = render.render_rays(
            fns,
            p,
            watermark.condition(p, 1, cfg),
            r[0],
            r[1],
            geometry,
            k,
            train=False,
            density_budget=None,
            colour_budget=None,
        )
        return out["rgb"], {}

    def image_loss(image, dec_params):
        logits = decoder.apply_ll2(
            {"params": dec_params, "batch_stats": dec["batch_stats"]}, dwt.ll2(image[None])
        )[0]
        loss = 0.95 * losses.bce_with_logits(logits, message) + 0.05 * losses.watson_dct_loss(
            image, targets.reshape(h, w, 3)
        )
        return loss, {}

    ploss = functools.partial(O.patch_loss, cfg)
    layout = D.patch_layout(h, w, size)
    index, owner = jnp.asarray(layout.index), jnp.asarray(layout.owner)
    _, _, image, g_params, g_dec = jax.jit(
        lambda p, d: D.deferred_grad(
            render_fn, image_loss, ploss, p, d, rays, targets, index, owner, jax.random.PRNGKey(4), h, w
        )
    )(params, dec["params"])

    def full(p, d):
        rgb, _ = render_fn(p, rays, None)
        loss, _ = image_loss(rgb.reshape(h, w, 3), d)
        for idx in layout.index:
            loss = loss + ploss(rgb[idx].reshape(size, size, 3), targets[idx].reshape(size, size, 3))
        return loss

    ref_params, ref_dec = jax.jit(jax.grad(full, argnums=(0, 1)))(params, dec["params"])
    assert float(jnp.mean(image)) < 0.9  # rays meet matter, not just the white background
    _assert_trees_close(g_params, ref_params)
    _assert_trees_close(g_dec, ref_dec)
    assert float(jnp.abs(ref_params["wm"]["grid"]["planes"][0]).max()) > 0


def test_clean_negative_term_pulls_the_decoder_on_ground_truth_towards_the_null_word() -> None:
    # losses.lambda_clean adds λ·BCE(decoder(ground truth), null word) in phase 2: a constant in the image
    # (the field's gradient is unchanged) that trains the decoder to read no key from unwatermarked images.
    from mnerf_jax.imaging import losses
    from mnerf_jax.reader import decoder

    dec = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    image = jax.random.uniform(jax.random.PRNGKey(1), (24, 24, 3))
    target = jax.random.uniform(jax.random.PRNGKey(2), (24, 24, 3))
    message = jnp.array([1, 0, 1, 1, 0, 0, 1, 0], jnp.float32)

    def loss_fn(lambda_clean: float, phase: int = 2):
        cfg = wm_config(augment_per_step=0, lambda_clean=lambda_clean, lambda_key=0.0)
        spec = _image_loss_spec(cfg, phase, 24)
        return S.make_image_loss(spec, jax.random.PRNGKey(3), message, target, dec, null=null)

    null = jnp.array([0, 1, 0, 0, 1, 1, 0, 1], jnp.float32)
    with_clean, without = loss_fn(0.5), loss_fn(0.0)
    clean_logits = decoder.apply_ll2(dec, dwt.ll2(target[None]))[0]
    expected = 0.5 * losses.bce_with_logits(clean_logits, null)
    delta = with_clean(image, dec["params"])[0] - without(image, dec["params"])[0]
    np.testing.assert_allclose(delta, expected, rtol=1e-5)
    g_with = jax.grad(lambda x: with_clean(x, dec["params"])[0])(image)
    g_without = jax.grad(lambda x: without(x, dec["params"])[0])(image)
    np.testing.assert_allclose(g_with, g_without, rtol=1e-6, atol=1e-9)
    d_with = jax.grad(lambda d: with_clean(image, d)[0])(dec["params"])
    d_without = jax.grad(lambda d: without(image, d)[0])(dec["params"])
    assert float(jnp.abs(d_with["linear"]["bias"] - d_without["linear"]["bias"]).max()) > 0
    # Phase 1 (decoder frozen) has no such term.
    phase1 = [loss_fn(lam, 1)(image, dec["params"])[0] for lam in (0.5, 0.0)]
    np.testing.assert_allclose(phase1[0], phase1[1])


def _temp_bytes(height: int, deferred: bool) -> int:
    """XLA's temporary memory of one gradient computation on a ``height²`` image with 8-px patches."""
    params = _toy_params(jax.random.PRNGKey(1))
    extra = {"w": jnp.ones((3, 4)), "b": jnp.zeros(4)}
    rays = _toy_rays(height, height)
    targets = jnp.zeros((height * height, 3))
    layout = D.patch_layout(height, height, 8)
    index, owner = jnp.asarray(layout.index), jnp.asarray(layout.owner)
    args = (rays, targets, index, owner, jax.random.PRNGKey(0), height, height)
    if deferred:
        fn = lambda p, e: D.deferred_grad(_toy_render, _image_loss, _patch_loss, p, e, *args)
    else:
        fn = lambda p, e: jax.grad(
            lambda q: D.direct_objective(_toy_render, _image_loss, _patch_loss, q, e, *args)[0]
        )(p)
    return jax.jit(fn).lower(params, extra).compile().memory_analysis().temp_size_in_bytes


def test_deferred_memory_follows_the_patch_not_the_image() -> None:
    # 16x the pixels: the direct gradient's working memory grows with the image, the deferred one barely.
    small, large = _temp_bytes(16, True), _temp_bytes(64, True)
    direct_small, direct_large = _temp_bytes(16, False), _temp_bytes(64, False)
    assert large < 2.0 * small
    assert direct_large > 8.0 * direct_small and direct_large > 10 * large


# ------------------------------------------------------------------------------------- tiny real runs
# The `tiny` fixture (tests/conftest.py): a fitted procedural TensoRF, an 8-bit decoder, a 2-ID WMRUN.


def test_tiny_embed_writes_a_complete_watermarked_run(tiny: TinyRuns) -> None:
    from mnerf_jax.reader import keys as K

    wm = tiny.wm
    for name in ("run.json", "config.json", "keys.json", "decoder.npz", "embed.json"):
        assert (wm / name).is_file(), name
    marker = rundir.read_marker(wm)
    assert marker["kind"] == "multinerf" and marker["num_ids"] == 2 and marker["bits"] == 8
    keys = K.load_keys(wm, expect_bits=8)
    assert keys.num_ids == 2 and K.min_pairwise_hamming(keys.messages) >= keys.min_hamming >= 2
    progress = json.loads((wm / "embed.json").read_text())
    assert progress["steps_done"] == 80 and progress["phase"] == 2
    # The decoder was fine-tuned in phase 2, and keys.json names the decoder saved with the run.
    from mnerf_jax.reader import decoder_io

    saved = decoder_io.load_decoder(wm / "decoder.npz")
    start = decoder_io.load_decoder(tiny.decoder)
    assert keys.decoder_fingerprint == saved.fingerprint != start.fingerprint
    loaded = wm_run.load_run(wm)
    assert loaded.kind == "multinerf" and loaded.step == 80 and loaded.extras["num_ids"] == 2
    # Training curves: TensorBoard scalars, each the mean of 10 steps, at steps 10, 20, ..., 80.
    from mnerf_jax.core.scalar_log import read_scalars

    curves = read_scalars(wm / "tb")
    assert set(curves) >= {"train/bit_acc", "train/psnr", "train/bce", "train/loss"}
    assert [step for step, _ in curves["train/bit_acc"]] == list(range(10, 81, 10))
    assert all(0.0 <= value <= 1.0 for _, value in curves["train/bit_acc"])


def test_loaded_run_renders_each_id_differently(tiny: TinyRuns) -> None:

    loaded = wm_run.load_watermarked_run(tiny.wm)
    split = loaded.load_scene(splits=("test",)).split("test")
    a, a2, b = (wm_run.render_with_id(loaded, i, split.cameras, [0])[0] for i in (0, 0, 1))
    np.testing.assert_array_equal(a, a2)
    assert np.abs(a - b).max() > 1e-2
    # Both IDs from one geometry pass (what `mnerf evaluate` renders): the same images.
    both = wm_run.render_with_ids(loaded, [1, 0], split.cameras, [0])
    np.testing.assert_allclose(both[0][0], a, atol=1e-5)
    np.testing.assert_allclose(both[1][0], b, atol=1e-5)
    with pytest.raises(MnerfError, match="outside"):
        wm_run.render_with_ids(loaded, [0, 2], split.cameras, [0])
    assert wm_run.with_id(loaded, 1).extras["id"] == 1
    with pytest.raises(MnerfError, match="outside"):
        wm_run.with_id(loaded, 2)
    plain = wm_run.load_run(tiny.fit)
    with pytest.raises(MnerfError, match="not a watermarked run"):
        wm_run.with_id(plain, 0)


def test_embedding_config_records_the_schedule_it_runs(tiny: TinyRuns) -> None:

    source = wm_run.load_run(tiny.fit)
    wm = E.resolve_config(source, None, [], 16, 16).watermark
    # Both phases from the procedural preset (100 + 3,200); -1 is by the number of IDs.
    assert (wm.schedule.phase1_steps, wm.schedule.phase2_steps) == (100, 3200)
    wm = E.resolve_config(source, None, ["watermark.schedule.phase2_steps=-1"], 16, 16).watermark
    assert (wm.schedule.phase1_steps, wm.schedule.phase2_steps) == (100, 3200)
    sets = ["watermark.schedule.phase1_steps=-1", "watermark.schedule.phase2_steps=7"]
    wm = E.resolve_config(source, None, sets, 2, 8).watermark
    assert (wm.schedule.phase1_steps, wm.schedule.phase2_steps) == (200, 7)
    with pytest.raises(MnerfError, match="must be ≥ 1"):
        E.resolve_config(
            source, None, ["watermark.schedule.phase1_steps=0", "watermark.schedule.phase2_steps=0"], 2, 8
        )
    with pytest.raises(MnerfError, match="reading.window"):
        E.resolve_config(source, None, ["watermark.reading.window=1.5"], 2, 8)
    for bad in (
        ["watermark.reading.jitter=-1", "watermark.reading.window=0.7"],
        ["watermark.reading.jitter=1"],
    ):
        with pytest.raises(MnerfError, match="reading.jitter"):
            E.resolve_config(source, None, bad, 2, 8)


def test_resume_continues_exactly(tiny: TinyRuns) -> None:
    # 3 steps, stop, resume to 5  ==  5 steps in one go, across the phase boundary (phase 2 with its random
    # augmentations). The tiny run's own settings, so the steps compiled for it serve.
    root = tiny.root
    overrides = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=78",
    ]
    args = dict(overrides=overrides, decoder_path=tiny.decoder, progress=False)
    E.embed(tiny.fit, root / "r_split", 2, 8, stop_at=3, **args)
    with pytest.raises(MnerfError, match="--resume"):
        E.embed(tiny.fit, root / "r_split", 2, 8, stop_at=5, **args)
    resumed = E.embed(tiny.fit, root / "r_split", 2, 8, stop_at=5, resume=True, **args)
    E.embed(tiny.fit, root / "r_once", 2, 8, stop_at=5, **args)
    assert resumed.steps == 5
    assert json.loads((root / "r_split" / "embed.json").read_text())["phase"] == 2
    a = wm_run.load_watermarked_run(root / "r_split")
    b = wm_run.load_watermarked_run(root / "r_once")
    assert a.step == b.step == 5
    for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    assert (
        json.loads((root / "r_split" / "keys.json").read_text())["messages"]
        == json.loads((root / "r_once" / "keys.json").read_text())["messages"]
    )


def test_the_run_records_its_read_window_in_its_decoder_file(tiny: TinyRuns) -> None:
    # The decoder reads a read window (watermark.reading.window), which the run's decoder file and config
    # record from the start (stopped before its first step: nothing to compile).
    overrides = [
        *tiny.embed_overrides,
        "watermark.reading.window=0.75",
        "watermark.reading.background=-1",
        "watermark.reading.jitter=1",
    ]
    out = tiny.root / "r_window"
    E.embed(tiny.fit, out, 2, 8, stop_at=0, overrides=overrides, decoder_path=tiny.decoder, progress=False)
    meta = decoder_io.load_decoder(out / "decoder.npz").metadata
    assert (meta["read_window"], meta["read_background"], meta["read_jitter"]) == (0.75, -1.0, 1)
    assert wm_run.load_watermarked_run(out).config.watermark.reading.window == 0.75


def test_a_time_budget_ends_the_run_early_as_a_prefix_of_the_full_one(tiny: TinyRuns) -> None:
    # A budget far below one step's cost lets the first step run and stops before the second (saved there);
    # the schedule is not resized, so resuming without a budget gives exactly the unbudgeted run.
    root = tiny.root
    schedule = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=2",
        "watermark.schedule.phase2_steps=3",
    ]
    args = dict(decoder_path=tiny.decoder, progress=False)
    tiny_budget = [*schedule, "watermark.time_budget.minutes=0.001"]
    stopped = E.embed(tiny.fit, root / "b_split", 2, 8, overrides=tiny_budget, **args)
    assert stopped.stopped_by_budget and stopped.steps == 1
    progress = json.loads((root / "b_split" / "embed.json").read_text())
    assert progress["steps_done"] == 1 and 0 < progress["run_seconds"] <= stopped.run_seconds + 0.01
    # The budget is the run's: resumed under the same budget, the time its first process spent counts, and
    # no step is taken.
    again = E.embed(tiny.fit, root / "b_split", 2, 8, resume=True, overrides=tiny_budget, **args)
    assert again.stopped_by_budget and again.steps == 1 and again.run_seconds > progress["run_seconds"]
    resumed = E.embed(tiny.fit, root / "b_split", 2, 8, resume=True, overrides=schedule, **args)
    assert resumed.steps == 5 and not resumed.stopped_by_budget
    assert resumed.run_seconds > stopped.run_seconds  # the first process's time and its own
    roomy = E.embed(
        tiny.fit, root / "b_roomy", 2, 8, overrides=[*schedule, "watermark.time_budget.minutes=30"], **args
    )
    assert roomy.steps == 5 and not roomy.stopped_by_budget
    E.embed(tiny.fit, root / "b_plain", 2, 8, overrides=schedule, **args)
    a, b, c = (wm_run.load_watermarked_run(root / name) for name in ("b_split", "b_roomy", "b_plain"))
    assert a.step == b.step == c.step == 5
    for x, y, z in zip(
        jax.tree.leaves(a.params), jax.tree.leaves(b.params), jax.tree.leaves(c.params), strict=True
    ):
        np.testing.assert_allclose(np.asarray(x), np.asarray(z), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(y), np.asarray(z), rtol=1e-5, atol=1e-6)
    with pytest.raises(MnerfError, match="time_budget.minutes must be ≥ 0"):
        E.embed(
            tiny.fit, root / "b_bad", 2, 8, overrides=[*schedule, "watermark.time_budget.minutes=-1"], **args
        )


def test_recorded_watermark_settings_older_than_todays_are_named(
    tiny: TinyRuns, tmp_path: Path, mnerf
) -> None:
    # A fitted run records its day's [watermark] section and embed --from keeps it; after an upgrade that
    # changed a default, the command names what differs (and still uses the recorded values).
    assert E.watermark_defaults_drift(tiny.fit) == []
    old = tmp_path / "old_fit"
    shutil.copytree(tiny.fit, old)
    recorded = json.loads((old / "config.json").read_text())
    recorded["watermark"]["optim"]["lr_decoder"] = 1e-4
    (old / "config.json").write_text(json.dumps(recorded))
    assert E.watermark_defaults_drift(old) == ["optim.lr_decoder 0.0001 (today 0.001)"]
    assert (
        E.watermark_defaults_drift(old, ["watermark.optim.lr_decoder=0.002"]) == []
    )  # --set: neither value used
    assert E.watermark_defaults_drift(tmp_path / "missing") == []  # embed itself says what is wrong
    base = ["embed", "--num-ids", "2", "--bits", "8", "--decoder", tiny.decoder, "--steps", "0", "--quiet"]
    code, _, err = mnerf(*base, "--from", old, "--out", tmp_path / "wm", "--config", "run")
    assert code == 0 and "lr_decoder 0.0001 (today 0.001)" in err and "--config PRESET" in err
    assert (
        json.loads((tmp_path / "wm" / "config.json").read_text())["watermark"]["optim"]["lr_decoder"] == 1e-4
    )
    code, _, err = mnerf(
        *base,
        "--from",
        old,
        "--out",
        tmp_path / "w2",
        "--set",
        "watermark.optim.lr_decoder=2e-3",
        "--config",
        "run",
    )
    assert code == 0 and "note:" not in err, err
    # The default (--config auto) takes the fit preset's section of today, and says so.
    code, _, err = mnerf(*base, "--from", old, "--out", tmp_path / "w3")
    assert code == 0 and "note:" not in err and "the procedural preset's embedding" in err, err
    assert (
        json.loads((tmp_path / "w3" / "config.json").read_text())["watermark"]["optim"]["lr_decoder"] == 1e-3
    )
    # --config takes today's section (resolve_config is what the command calls with it).
    assert E.resolve_config(E.load_source(old), "procedural", [], 2, 8).watermark.optim.lr_decoder == 1e-3


# ------------------------------------------------------------------------------------------- bad input


def test_embed_refuses_bad_input_with_one_line(tiny: TinyRuns, tmp_path: Path, mnerf) -> None:
    base = ["embed", "--from", str(tiny.fit), "--decoder", str(tiny.decoder), "--quiet"]
    cases = [
        (
            [
                "embed",
                "--from",
                str(tmp_path),
                "--out",
                str(tmp_path / "o1"),
                "--num-ids",
                "2",
                "--bits",
                "8",
            ],
            "not a fitted TensoRF",
        ),
        (
            ["embed", "--from", str(tiny.wm), "--out", str(tmp_path / "o2"), "--num-ids", "2", "--bits", "8"],
            "'multinerf' run, not a fitted TensoRF",
        ),
        ([*base, "--out", str(tmp_path / "o3"), "--num-ids", "2", "--bits", "16"], "reads 8-bit messages"),
        ([*base, "--out", str(tmp_path / "o4"), "--num-ids", "300", "--bits", "8"], "more than 8 bits"),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o5"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "watermark.variant=waterf",
                "--set",
                "watermark.schedule.cache_source=false",  # the procedural run's cache needs a FiLM variant
                "--set",
                "watermark.schedule.jitter=true",
            ],
            "--num-ids 1",
        ),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o6"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "model.mlp_width=64",
            ],
            "may not change model",
        ),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o7"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "watermark.augment.strength=extreme",
            ],
            "augment.strength",
        ),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o8"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "watermark.augment.names=jpeg,crop",
            ],
            "unknown augmentation 'crop'",
        ),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o9"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "watermark.augment.names=jpeg",
            ],
            "cannot draw 2 distinct augmentations from 1",
        ),
        (
            [
                *base,
                "--out",
                str(tmp_path / "o11"),
                "--num-ids",
                "2",
                "--bits",
                "8",
                "--set",
                "watermark.fidelity.psnr=-3",
            ],
            "fidelity.psnr",
        ),
        ([*base, "--out", str(tiny.wm), "--num-ids", "2", "--bits", "8"], "--resume"),
    ]
    for argv, message in cases:
        code, _, err = mnerf(*argv)
        assert code == 2, (argv, err)
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("mnerf: error:") and message in lines[0], err
    for name in ("o1", "o2", "o3", "o4", "o5", "o6", "o7", "o8", "o9", "o10", "o11"):
        assert not (tmp_path / name).exists(), name


def test_watermarked_run_without_keys_or_with_foreign_keys_is_refused(
    tiny: TinyRuns, tmp_path: Path, mnerf
) -> None:
    from mnerf_jax.reader import keys as K

    copy = tmp_path / "wm"
    shutil.copytree(tiny.wm, copy)
    (copy / "keys.json").unlink()
    with pytest.raises(MnerfError, match="no keys.json"):
        wm_run.load_run(copy)
    code, _, err = mnerf(
        "embed",
        "--from",
        tiny.fit,
        "--out",
        copy,
        "--num-ids",
        "2",
        "--bits",
        "8",
        "--decoder",
        tiny.decoder,
        "--resume",
        "--quiet",
    )
    assert code == 2 and "no keys.json" in err
    # Keys of another bit length than the run's decoder.
    K.save_keys(copy, K.generate_keys(2, 16, 0, 0))
    with pytest.raises(MnerfError, match="16 bits but the decoder reads 8"):
        wm_run.load_run(copy)
    # Keys made for another decoder.
    K.save_keys(copy, K.generate_keys(2, 8, 0, 0, decoder_fingerprint="0" * 64))
    with pytest.raises(MnerfError, match="embedded for decoder"):
        wm_run.load_run(copy)


def test_non_rgb_images_are_refused() -> None:
    with pytest.raises(MnerfError, match="RGB"):
        EI.check_rgb_images(np.zeros((2, 8, 8, 4), np.float32), "scene")
    with pytest.raises(MnerfError, match="RGB"):
        EI.check_rgb_images(np.zeros((2, 8, 8), np.float32), "scene")
    assert EI.check_rgb_images(np.zeros((1, 8, 8, 3)), "scene").dtype == np.float32


# ------------------------------------------------------------------------------------------- optimiser


def _wm_params(variant: str) -> dict:
    from mnerf_jax.tensorf import field

    model = ModelConfig(density_ranks=(2, 2, 2), appearance_ranks=(2, 2, 2), app_features=4, mlp_width=8)
    cfg = wm_config(variant=variant, wm_ranks=(2, 2, 2), num_ids=1 if variant == "waterf" else 3)
    base = field.init_field(jax.random.PRNGKey(0), model, (5, 5, 5))
    return watermark.add_watermark(jax.random.PRNGKey(1), base, cfg, cfg.num_ids), cfg


@pytest.mark.parametrize("variant", ["multinerf", "frozen_geometry", "waterf"])
def test_optimizer_groups_and_learning_rates(variant: str) -> None:
    params, cfg = _wm_params(variant)
    dec = {"w": jnp.ones((3,))}
    tree = {"field": params, "decoder": dec}
    labels = S.param_labels(tree, cfg)
    flat = {jax.tree_util.keystr(p): v for p, v in jax.tree_util.tree_leaves_with_path(labels)}
    # frozen_geometry (the paper's G_σ frozen): neither geometry nor appearance adapts.
    frozen = variant == "frozen_geometry"
    density = {v for k, v in flat.items() if k.startswith("['field']['density']")}
    assert density == ({"frozen"} if frozen else {"source_grid"})
    assert {v for k, v in flat.items() if "['appearance']" in k} == (
        {"frozen"} if frozen else {"source_grid"}
    )
    fitted = [k for k in flat if ("['mlp']" in k and "_extra']" not in k) or "['basis']" in k]
    fitted_network = {flat[k] for k in fitted}
    assert fitted_network == ({"frozen"} if frozen else {"source_network"})
    if variant != "waterf":
        assert {v for k, v in flat.items() if "_extra']" in k} == {"network"}
        assert {v for k, v in flat.items() if "['wm']['grid']" in k} == {"grid"}
        assert {v for k, v in flat.items() if "['emb']" in k or "['mod']" in k} == {"embedding"}
    assert {v for k, v in flat.items() if k.startswith("['decoder']")} == {"decoder"}
    # One Adam step moves every trained leaf by about its group's learning rate; frozen leaves stay put.
    tx = S.make_optimizer(cfg)
    grads = jax.tree.map(jnp.ones_like, tree)
    updates, _ = tx.update(grads, tx.init(tree), tree)
    lr = {
        "grid": cfg.optim.lr_grid,
        "network": cfg.optim.lr_network,
        "embedding": cfg.optim.lr_embedding,
        "decoder": cfg.optim.lr_decoder,
        "frozen": 0.0,
        "source_grid": cfg.optim.lr_grid * cfg.optim.lr_source_scale,
        "source_network": cfg.optim.lr_network * cfg.optim.lr_source_scale,
    }
    pairs = zip(jax.tree_util.tree_leaves_with_path(updates), jax.tree.leaves(labels), strict=True)
    for (path, update), label in pairs:
        where = jax.tree_util.keystr(path)
        np.testing.assert_allclose(np.asarray(update), -lr[label], rtol=1e-4, err_msg=where)


def test_learning_rates_decay_exponentially() -> None:
    params, cfg = _wm_params("multinerf")
    tree = {"field": {"basis": params["basis"]}, "decoder": {}}
    tx = S.make_optimizer(cfg)
    state = tx.init(tree)
    grads = jax.tree.map(jnp.ones_like, tree)
    total = S.total_steps(cfg)
    steps = []
    for _ in range(3):
        updates, state = tx.update(grads, state, tree)
        steps.append(float(updates["field"]["basis"][0, 0]))
    ratio = cfg.optim.lr_decay_ratio ** (1.0 / total)
    assert steps[1] / steps[0] == pytest.approx(ratio, rel=1e-4)
    assert steps[2] / steps[1] == pytest.approx(ratio, rel=1e-4)
    # The decay's length may be traced (the compiled step takes it as an argument): the same schedule.
    traced = jax.jit(lambda n, st: S.make_optimizer(cfg, total=n).update(grads, st, tree))
    updates, _ = traced(jnp.asarray(total, jnp.int32), state)
    reference, _ = S.make_optimizer(cfg).update(grads, state, tree)
    np.testing.assert_allclose(updates["field"]["basis"], reference["field"]["basis"], rtol=1e-6)
    longer, _ = traced(jnp.asarray(2 * total, jnp.int32), state)
    assert float(longer["field"]["basis"][0, 0]) < float(reference["field"]["basis"][0, 0]) < 0  # decays less


def test_phases_and_step_choices_are_deterministic() -> None:

    cfg = wm_config(phase1_steps=3, phase2_steps=2)
    assert [S.phase_of(s, cfg) for s in range(5)] == [1, 1, 1, 2, 2]
    picks = [EI.step_choice(0, s, 4, 10) for s in range(400)]
    assert picks == [EI.step_choice(0, s, 4, 10) for s in range(400)]
    ids = np.array([p[0][0] for p in picks])
    assert set(ids) == {0, 1, 2, 3} and abs((ids == 0).mean() - 0.25) < 0.08
    # Several IDs per step: distinct, every ID about K/N of the steps, the same draws again.
    many = [EI.step_choice(0, s, 16, 10, ids_per_step=4) for s in range(400)]
    assert many == [EI.step_choice(0, s, 16, 10, ids_per_step=4) for s in range(400)]
    assert all(len(set(p[0])) == 4 for p in many)
    counts = np.bincount(np.concatenate([p[0] for p in many]), minlength=16)
    assert counts.min() > 0.6 * 100 and counts.max() < 1.4 * 100
    # ids_per_step is at most the run's IDs: with fewer, every ID renders on every step.
    four = dataclasses.replace(
        wm_config(), schedule=dataclasses.replace(wm_config().schedule, ids_per_step=4)
    )
    assert [watermark.ids_per_step_of(four, n) for n in (1, 2, 4, 16)] == [1, 2, 4, 4]
    assert [watermark.ids_per_step_of(wm_config(), n) for n in (2, 16, 64)] == [2, 16, 16]


def test_step_config_keeps_what_the_compiled_step_reads() -> None:
    # Runs that differ only in host-side fields (the schedule, seeds, checkpoints, the time budget) share one
    # compiled step (the decay's length is its argument); every loss weight still tells steps apart.

    base = wm_config(phase1_steps=40, phase2_steps=40)
    same = wm_config(
        phase1_steps=2, phase2_steps=78, seed=5, key_seed=3, checkpoint_every=7, time_budget_min=60.0
    )
    assert S.step_config(base) == S.step_config(same)
    assert S.step_config(base) == S.step_config(wm_config(phase1_steps=40, phase2_steps=41))
    heavier_rgb = wm_config(phase1_steps=40, phase2_steps=40, lambda_rgb=1.0)
    assert S.step_config(base) != S.step_config(heavier_rgb)
    fewer_attacks = wm_config(phase1_steps=40, phase2_steps=40, augment_names=("jpeg", "hue"))
    assert S.step_config(fewer_attacks).augment.names == ("jpeg", "hue")


def test_phase_two_draws_only_the_configured_augmentations(monkeypatch: pytest.MonkeyPatch) -> None:
    # watermark.augment.names reaches the policy inside the phase-2 image loss (traced, not run).
    from mnerf_jax.imaging import augment
    from mnerf_jax.reader import decoder

    seen: list[tuple[str, ...] | None] = []
    real = augment.random_policy

    def spy(key, images, strength="low", k=2, p=0.75, names=None):
        seen.append(None if names is None else tuple(names))
        return real(key, images, strength, k, p, names)

    monkeypatch.setattr(augment, "random_policy", spy)
    dec = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    image = jnp.full((16, 16, 3), 0.5)
    for names, expect in (((), None), (("jpeg", "hue"), ("jpeg", "hue"))):
        wm = wm_config(augment_names=names, lambda_key=0.0)
        spec = _image_loss_spec(wm, 2, 16)
        loss = S.make_image_loss(spec, jax.random.PRNGKey(1), jnp.zeros(8), image, dec, null=jnp.ones(8))
        seen.clear()
        jax.eval_shape(loss, image, dec["params"])
        assert seen == [expect, expect]  # the renders, and the ground truth of the clean term (lambda_clean)


def test_several_ids_per_step_give_the_mean_of_their_one_id_gradients() -> None:
    # schedule.ids_per_step: one deferred step on K IDs' renders of a view equals the mean over the K IDs of
    # the direct (full-graph) gradient of that ID's objective alone: the IDs share the render, not the loss.
    from mnerf_jax.reader import decoder

    # lambda_key = 0: the key cross-entropy depends on the set of IDs, so it is not a mean over them.
    cfg = wm_config(wm_ranks=(2, 2, 2), augment_per_step=0, jitter=False, lambda_ssim=0.0, lambda_key=0.0)
    h, w = 10, 9
    model, params, geometry, rays, targets = _small_watermarked_scene(cfg, 4, h, w)
    dec = decoder.init_decoder(jax.random.PRNGKey(3), 8)
    messages = jnp.array([[1, 0, 1, 1, 0, 0, 1, 0], [0, 0, 1, 0, 1, 1, 1, 0]], jnp.float32)
    ids = jnp.array([2, 0])
    spec = S.StepSpec(
        model=model,
        wm=cfg,
        adam_b1=0.9,
        adam_b2=0.99,
        phase=2,
        height=h,
        width=w,
        density_budget=None,
        colour_budget=None,
    )
    layout = D.patch_layout(h, w, 6)
    index, owner = jnp.asarray(layout.index), jnp.asarray(layout.owner)
    target_image = targets.reshape(h, w, 3)
    ploss = functools.partial(O.patch_loss, cfg)

    def objective(id_arr, message):
        fn = S.render_patch_fn(spec, geometry, id_arr)
        null = jnp.zeros(message.shape[-1])
        loss_fn = S.make_image_loss(spec, jax.random.PRNGKey(5), message, target_image, dec, null=null)
        return fn, loss_fn

    fn, loss_fn = objective(ids, messages)
    _, aux, image, g_params, g_dec = jax.jit(
        lambda p, d: D.deferred_grad(
            fn, loss_fn, ploss, p, d, rays, targets, index, owner, jax.random.PRNGKey(4), h, w
        )
    )(params, dec["params"])
    assert image.shape == (h, w, 6)

    def direct_one(p, d, id_k, message_k):
        fn_k, loss_k = objective(id_k, message_k)
        return D.direct_objective(
            fn_k, loss_k, ploss, p, d, rays, targets, index, owner, jax.random.PRNGKey(4), h, w
        )[0]

    direct_grad = jax.jit(jax.grad(direct_one, argnums=(0, 1)))  # one compilation for both IDs
    grads = [direct_grad(params, dec["params"], ids[k : k + 1], messages[k : k + 1]) for k in range(2)]
    ref_params = jax.tree.map(lambda a, b: 0.5 * (a + b), grads[0][0], grads[1][0])
    ref_dec = jax.tree.map(lambda a, b: 0.5 * (a + b), grads[0][1], grads[1][1])
    _assert_trees_close(g_params, ref_params)
    _assert_trees_close(g_dec, ref_dec)
    # Both IDs' rows of Emb learn on this one step; the two IDs never drawn get nothing.
    emb_rows = np.abs(np.asarray(g_params["wm"]["emb"]["w0"])).sum(1)
    assert emb_rows[0] > 0 and emb_rows[2] > 0 and emb_rows[1] == 0 and emb_rows[3] == 0


def test_id_loss_power_weights_the_renders_gradient_not_the_decoders() -> None:
    # losses.id_loss_power p: the renders' gradient is that of Σ_k w_k·BCE_k with w ∝ BCE^p held constant;
    # the decoder's gradient and the value stay the plain mean's. p = 0 is the plain mean throughout, and one
    # ID is its own BCE whatever p.
    from mnerf_jax.imaging import losses

    renders = jax.random.uniform(jax.random.PRNGKey(0), (4, 3, 3, 3))
    dec = jax.random.normal(jax.random.PRNGKey(1), (27, 8)) * 0.1
    message = (jax.random.uniform(jax.random.PRNGKey(2), (4, 8)) > 0.5).astype(jnp.float32)

    def decode(r: jax.Array, p: jax.Array) -> jax.Array:  # a non-linear stand-in for augment → LL2 → decoder
        return 3.0 * jnp.tanh(r.reshape(r.shape[0], -1) @ p)

    def weighted(r: jax.Array, p: jax.Array, w: np.ndarray) -> jax.Array:
        logits = decode(r, p)
        return sum(float(wk) * losses.bce_with_logits(logits[k], message[k]) for k, wk in enumerate(w))

    logits = decode(renders, dec)
    per_id = np.array([float(losses.bce_with_logits(z, m)) for z, m in zip(logits, message, strict=True)])
    assert per_id.max() > 1.2 * per_id.min()  # the IDs' losses differ, so the weighting shows
    uniform = np.full(4, 0.25)
    g_plain = jax.grad(weighted, argnums=(0, 1))(renders, dec, uniform)
    for power in (0.0, 1.0, 2.0):
        cfg = wm_config(id_loss_power=power, lambda_key=0.0)
        term, bce, key, logits = O.message_loss(cfg, decode, renders, dec, message)
        np.testing.assert_allclose(logits, decode(renders, dec), rtol=1e-6)
        np.testing.assert_allclose([term, bce], [per_id.mean()] * 2, rtol=1e-5)
        assert float(key) == 0.0  # lambda_key = 0: no key term
        g_r, g_p = jax.grad(lambda r, p, c=cfg: O.message_loss(c, decode, r, p, message)[0], argnums=(0, 1))(
            renders, dec
        )
        w = per_id**power / np.sum(per_id**power)
        np.testing.assert_allclose(g_r, jax.grad(weighted)(renders, dec, w), rtol=1e-4, atol=1e-8)
        np.testing.assert_allclose(g_p, g_plain[1], rtol=1e-4, atol=1e-8)
        if power:  # the worse-read IDs' renders get more of the gradient than the plain mean gives them
            worst, best = int(np.argmax(per_id)), int(np.argmin(per_id))
            ratio = np.abs(np.asarray(g_r)).sum((1, 2, 3)) / np.abs(np.asarray(g_plain[0])).sum((1, 2, 3))
            assert ratio[worst] > 1.0 > ratio[best]
    cfg = wm_config(id_loss_power=2.0, lambda_key=0.0)
    one = O.message_loss(cfg, decode, renders[:1], dec, message[:1]).term
    np.testing.assert_allclose(one, per_id[0], rtol=1e-5)
    with pytest.raises(MnerfError, match="id_loss_power"):
        wm_config(id_loss_power=-1.0)


def test_key_term_is_the_key_cross_entropy_with_its_gradient_to_renders_and_decoder() -> None:
    # losses.lambda_key: the same logits as the BCE, the gradient of key_cross_entropy(decode(r, p)) to
    # both sides, with the plain mean and with id_loss_power's two decoder passes alike.
    from mnerf_jax.imaging import losses

    renders = jax.random.uniform(jax.random.PRNGKey(0), (3, 3, 3, 3))
    dec = jax.random.normal(jax.random.PRNGKey(1), (27, 8)) * 0.1
    keys = (jax.random.uniform(jax.random.PRNGKey(2), (5, 8)) > 0.5).astype(jnp.float32)
    ids = jnp.array([4, 0, 2])

    def decode(r: jax.Array, p: jax.Array) -> jax.Array:
        return 3.0 * jnp.tanh(r.reshape(r.shape[0], -1) @ p)

    def direct(r: jax.Array, p: jax.Array) -> jax.Array:
        return losses.key_cross_entropy(decode(r, p), keys, ids)

    g_direct = jax.grad(direct, argnums=(0, 1))(renders, dec)
    for power in (0.0, 1.0):
        cfg = wm_config(id_loss_power=power, lambda_key=0.5)
        key = O.message_loss(cfg, decode, renders, dec, keys[ids], keys, ids)[2]
        np.testing.assert_allclose(key, direct(renders, dec), rtol=1e-5)
        g = jax.grad(
            lambda r, p, c=cfg: O.message_loss(c, decode, r, p, keys[ids], keys, ids)[2], argnums=(0, 1)
        )(renders, dec)
        for got, want in zip(g, g_direct, strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-8)
    with pytest.raises(ValueError, match="lambda_key"):
        O.message_loss(wm_config(lambda_key=0.5), decode, renders, dec, keys[ids])
    with pytest.raises(MnerfError, match="lambda_key"):
        wm_config(lambda_key=-1.0)


# ------------------------------------------------------------------------------------ quality budget


def test_fidelity_term_is_the_mse_beyond_the_budget_in_both_phases() -> None:
    # watermark.fidelity.psnr: + λ·mean_k relu(MSE(render_k, clean) / 10^(−psnr/10) − 1): zero inside.
    from mnerf_jax.reader import decoder

    dec = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    reference = jax.random.uniform(jax.random.PRNGKey(1), (24, 24, 3))
    target = jax.random.uniform(jax.random.PRNGKey(2), (24, 24, 3))
    renders = reference[..., None, :] + 0.03 * jax.random.normal(jax.random.PRNGKey(3), (24, 24, 2, 3))
    image = renders.reshape(24, 24, 6)  # two IDs' renders side by side
    messages = jnp.array([[1, 0, 1, 1, 0, 0, 1, 0], [0, 0, 1, 0, 1, 1, 1, 0]], jnp.float32)

    def loss_fn(psnr: float, phase: int, ref: jax.Array | None):
        cfg = wm_config(augment_per_step=0, fidelity_psnr=psnr, lambda_fidelity=4.0, lambda_key=0.0)
        spec = _image_loss_spec(cfg, phase, 24)
        null = jnp.zeros(8)
        return jax.jit(
            S.make_image_loss(spec, jax.random.PRNGKey(4), messages, target, dec, None, ref, null=null)
        )

    mse = jnp.mean(jnp.square(renders - reference[..., None, :]), axis=(0, 1, 3))  # per ID
    assert float(jnp.min(mse)) > 10 ** (-3.5)  # both renders outside a 35 dB budget (~30.5 dB)
    expected = 4.0 * jnp.mean(mse / 10 ** (-3.5) - 1.0)
    for phase in (1, 2):
        with_ref, aux = loss_fn(35.0, phase, reference)(image, dec["params"])
        without, _ = loss_fn(0.0, phase, None)(image, dec["params"])
        np.testing.assert_allclose(with_ref - without, expected, rtol=1e-4)
        np.testing.assert_allclose(aux["mse_clean"], jnp.mean(mse), rtol=1e-5)
        inside, _ = loss_fn(25.0, phase, reference)(image, dec["params"])  # a budget they are inside
        np.testing.assert_allclose(inside, without, rtol=1e-6)
    # Outside the budget its gradient pulls every render towards the clean one; inside, nothing.
    g0 = jax.grad(lambda x: loss_fn(0.0, 2, None)(x, dec["params"])[0])(image)
    g = jax.grad(lambda x: loss_fn(35.0, 2, reference)(x, dec["params"])[0])(image)
    assert float(jnp.sum((g - g0) * (image - jnp.tile(reference, (1, 1, 2))))) > 0
    g_inside = jax.grad(lambda x: loss_fn(25.0, 2, reference)(x, dec["params"])[0])(image)
    np.testing.assert_allclose(g_inside, g0, rtol=1e-5, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    start=st.floats(5.0, 40.0),
    rise=st.floats(0.0, 20.0),
    first=st.floats(0.0, 1.0),
    width=st.floats(0.0, 1.0),
    total=st.integers(1, 5000),
)
def test_fidelity_budget_ramps_linearly_in_db_over_the_schedule(
    start: float, rise: float, first: float, width: float, total: int
) -> None:
    # watermark.fidelity.psnr_start / fidelity_ramp: the start budget until the ramp, linear in dB across it,
    # the final budget after; never outside [start, final] and never loosening as the steps go on.

    last = min(first + width, 1.0)
    cfg = wm_config(fidelity_psnr=start + rise, fidelity_psnr_start=start, fidelity_ramp=(first, last))
    cfg.check_ids()
    budgets = [O.fidelity_budget_db(cfg, step, total) for step in range(0, total + 1, max(total // 97, 1))]
    assert all(b1 <= b2 + 1e-9 for b1, b2 in zip(budgets, budgets[1:], strict=False))
    assert all(start - 1e-9 <= b <= start + rise + 1e-9 for b in budgets)
    assert O.fidelity_budget_db(cfg, int(np.floor(first * total)), total) == start
    after = int(np.ceil(last * total))
    if after > first * total:
        assert O.fidelity_budget_db(cfg, after, total) == start + rise
    if last - first > 0.2 and total >= 100:
        middle = int(round((first + last) / 2 * total))
        expected = start + rise * (middle - first * total) / ((last - first) * total)
        assert abs(O.fidelity_budget_db(cfg, middle, total) - expected) < 1e-6
    plain = wm_config(fidelity_psnr=start)  # no ramp: the one budget throughout
    assert {O.fidelity_budget_db(plain, step, total) for step in (0, total // 2, total)} == {start}


@settings(deadline=None, max_examples=60)
@given(
    floor=st.floats(20.0, 45.0),
    over=st.floats(0.0, 12.0),
    source=st.floats(15.0, 40.0),
    step=st.integers(0, 1000),
)
def test_the_budget_ends_above_the_source_by_over_source_and_never_below_the_floor(
    floor: float, over: float, source: float, step: int
) -> None:
    # watermark.fidelity.over_source: the budget ends at max(psnr, source + over_source); 0 or no source
    # measured leaves fidelity.psnr; the ramp then rises to that end instead of to fidelity.psnr.
    cfg = wm_config(fidelity_psnr=floor, fidelity_psnr_start=10.0, fidelity_ramp=(0.2, 0.6))
    cfg = dataclasses.replace(cfg, fidelity=dataclasses.replace(cfg.fidelity, over_source=over))
    end = O.budget_end_db(cfg, source)
    if over:
        assert end == max(floor, source + over)
    else:
        assert end == floor
    assert O.budget_end_db(cfg, None) == floor
    assert end >= floor and O.budget_end_db(cfg, source + 1.0) >= end  # a sharper source, no looser budget
    assert O.fidelity_budget_db(cfg, 1000, 1000, end) == end
    assert O.fidelity_budget_db(cfg, 100, 1000, end) == 10.0
    assert 10.0 - 1e-9 <= O.fidelity_budget_db(cfg, step, 1000, end) <= end + 1e-9
    with pytest.raises(MnerfError, match="over_source"):
        dataclasses.replace(cfg.fidelity, over_source=-1.0)


def test_source_psnr_is_the_mean_of_the_per_view_psnrs() -> None:
    # Brute force: view v off by a uniform 0.1·(v+1) has MSE 0.01·(v+1)², so PSNR 20 − 20·log10(v+1).
    truth = np.full((3, 4, 5, 3), 0.5, np.float32)
    renders = (truth + 0.1 * np.arange(1, 4, dtype=np.float32)[:, None, None, None]).astype(np.float16)
    expected = np.mean([20.0 - 20.0 * np.log10(v + 1) for v in range(3)])
    assert abs(EI.source_psnr(renders, truth) - expected) < 0.01  # float16 holds 0.6 to 2.4e-4
    assert EI.source_psnr(truth.astype(np.float16), truth) >= 60.0  # identical views: the metric's cap


def test_fidelity_ramp_is_checked() -> None:

    with pytest.raises(MnerfError, match="fidelity.psnr_start"):
        wm_config(fidelity_psnr=30.0, fidelity_psnr_start=35.0)
    with pytest.raises(MnerfError, match="fidelity.psnr_start"):
        wm_config(fidelity_psnr_start=20.0)  # no budget to tighten to
    with pytest.raises(MnerfError, match="fidelity.ramp"):
        wm_config(fidelity_psnr=30.0, fidelity_psnr_start=20.0, fidelity_ramp=(0.8, 0.4))
    with pytest.raises(MnerfError, match="fidelity.ramp"):
        wm_config(fidelity_psnr=30.0, fidelity_psnr_start=20.0, fidelity_ramp=(0.5, 1.5))


def test_the_steps_budget_given_as_data_equals_the_configs_constant_one() -> None:
    # The ramp hands each step its MSE budget in the batch (no recompilation per value): a loss built with
    # fidelity_budget = the MSE of 35 dB equals one whose config says 35 dB, whatever the config says then.
    from mnerf_jax.reader import decoder

    dec = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    reference, target = (jax.random.uniform(jax.random.PRNGKey(i), (24, 24, 3)) for i in (1, 2))
    image = reference + 0.03 * jax.random.normal(jax.random.PRNGKey(3), (24, 24, 3))
    message = jnp.array([[1, 0, 1, 1, 0, 0, 1, 0]], jnp.float32)

    def loss(psnr: float, budget: jax.Array | None) -> jax.Array:
        cfg = wm_config(augment_per_step=0, fidelity_psnr=psnr, lambda_key=0.0)
        spec = _image_loss_spec(cfg, 2, 24)
        fn = S.make_image_loss(
            spec,
            jax.random.PRNGKey(4),
            message,
            target,
            dec,
            None,
            reference,
            None,
            None,
            budget,
            null=jnp.zeros(8),
        )
        return fn(image, dec["params"])[0]

    np.testing.assert_allclose(loss(20.0, np.float32(10**-3.5)), loss(35.0, None), rtol=1e-6)
    assert float(loss(35.0, None)) > float(loss(20.0, None)) + 1e-3  # the budget binds at 35 dB, not at 20


def test_embedding_steps_receive_the_ramps_budget(tiny: TinyRuns) -> None:
    # The host loop hands step s the ramp's budget at s (the step reports it back as psnr_budget).
    root = tiny.root
    # Phase 1 only: one step to compile (the ramp is the host loop's, whichever phase steps).
    overrides = [
        *tiny.embed_overrides,
        "watermark.schedule.phase1_steps=4",
        "watermark.schedule.phase2_steps=0",
        "watermark.fidelity.psnr=30",
        "watermark.fidelity.psnr_start=10",
        "watermark.fidelity.ramp=0.25,0.75",
    ]
    seen: dict[int, float] = {}
    E.embed(
        tiny.fit,
        root / "ramp",
        2,
        8,
        overrides=overrides,
        decoder_path=tiny.decoder,
        progress=False,
        on_step=lambda step, metrics: seen.__setitem__(step, metrics["psnr_budget"]),
    )
    assert sorted(seen) == [0, 1, 2, 3]
    np.testing.assert_allclose([seen[s] for s in range(4)], [10.0, 10.0, 20.0, 30.0], atol=1e-3)

    # With over_source the ramp ends at the source's training-view PSNR plus it (above the 30 dB floor),
    # measured on the clean model's renders of the training views; embed.json keeps that end.
    source = E.load_source(tiny.fit)
    split = source.load_scene(None, splits=("train",)).split("train")
    trained = EI.source_psnr(EI.clean_references(source, split), split.images)
    seen.clear()
    E.embed(
        tiny.fit,
        root / "ramp_over_source",
        2,
        8,
        overrides=[*overrides, "watermark.fidelity.over_source=20"],
        decoder_path=tiny.decoder,
        progress=False,
        on_step=lambda step, metrics: seen.__setitem__(step, metrics["psnr_budget"]),
    )
    end = json.loads((root / "ramp_over_source" / wm_run.META_FILE).read_text())["quality_budget_db"]
    assert trained + 20.0 > 30.0
    assert abs(end - (trained + 20.0)) < 0.05  # the cached samples' renders, float16 references
    np.testing.assert_allclose([seen[s] for s in range(4)], [10.0, 10.0, (10.0 + end) / 2, end], atol=1e-2)


def test_clean_term_reads_the_clean_models_render_when_asked() -> None:
    # losses.clean_negative = "clean_model": phase 2's clean term decodes the clean model's render of the
    # view instead of the ground-truth view; the rest of the loss is unchanged.
    from mnerf_jax.reader import decoder

    dec = decoder.init_decoder(jax.random.PRNGKey(0), 8)
    reference, target, image = (jax.random.uniform(jax.random.PRNGKey(i), (24, 24, 3)) for i in (1, 2, 3))
    message = jnp.array([[1, 0, 1, 1, 0, 0, 1, 0]], jnp.float32)

    def loss(negative: str, target_image: jax.Array, ref: jax.Array | None, phase: int = 2) -> float:
        cfg = wm_config(augment_per_step=0, lambda_clean=0.5, clean_negative=negative, lambda_key=0.0)
        spec = _image_loss_spec(cfg, phase, 24)
        fn = S.make_image_loss(
            spec, jax.random.PRNGKey(4), message, target_image, dec, None, ref, null=jnp.zeros(8)
        )
        return float(fn(image, dec["params"])[0])

    assert O.uses_clean_renders(wm_config(clean_negative="clean_model"))
    assert not O.uses_clean_renders(wm_config(clean_negative="clean_model", lambda_clean=0.0))
    assert not O.uses_clean_renders(WatermarkConfig())
    np.testing.assert_allclose(
        loss("clean_model", target, reference), loss("ground_truth", reference, None), rtol=1e-6
    )
    assert abs(loss("clean_model", target, reference) - loss("ground_truth", target, None)) > 1e-6
    # Phase 1 has no clean term, so the negative does not matter there.
    phase1 = loss("clean_model", target, reference, 1)
    np.testing.assert_allclose(phase1, loss("ground_truth", target, None, 1), rtol=1e-6)
    with pytest.raises(ValueError, match="clean model's render"):
        loss("clean_model", target, None)
    with pytest.raises(MnerfError, match="clean_negative"):
        wm_config(clean_negative="photographs")


def test_clean_references_are_the_clean_models_renders_of_the_training_views(tiny: TinyRuns) -> None:
    # The quality budget's reference: every training view of the source run, rendered once as evaluation
    # renders it, kept in float16; each step's batch carries its view's.
    from mnerf_jax.tensorf import run as runs

    source = E.load_source(tiny.fit)
    split = source.load_scene(None, splits=("train",)).split("train")
    references = EI.clean_references(source, split)
    assert references.dtype == np.float16 and references.shape == split.images.shape
    views = [0, len(split.images) - 1]
    renders = np.stack(runs.render_views(source, split.cameras, views))
    np.testing.assert_allclose(references[views].astype(np.float32), renders, atol=3e-4)
    messages = np.eye(2, 8, dtype=np.float32)
    batch = EI.step_batch(split, 3, messages, (1,), references)
    np.testing.assert_array_equal(batch["reference"], references[3].reshape(-1, 3).astype(np.float32))
    # The clean term's target: the word farthest from every key, the same however it is passed.
    np.testing.assert_array_equal(batch["null"], keys_lib.null_message(messages).astype(np.float32))
    given = EI.step_batch(split, 3, messages, (1,), references, keys_lib.null_message(messages))
    np.testing.assert_array_equal(given["null"], batch["null"])
    assert "reference" not in EI.step_batch(split, 3, messages, (1,))
