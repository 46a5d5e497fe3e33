"""Rendering: compositing laws, slab opacity, sampling, compaction vs dense, budgets, alpha mask, shrink."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mnerf_jax.core.config import ModelConfig
from mnerf_jax.tensorf import alpha_mask, budgets, chunked, field, grids, raymarch, render

SETTINGS = settings(max_examples=10, deadline=None)
CUBE = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], np.float32)

composite_cumsum = jax.jit(render.composite_cumsum)
composite_scan = jax.jit(render.composite_scan)


# --------------------------------------------------------------------------------------------------
# Analytic fields (FieldFns over normalised points; the cube maps world = 1.5 * normalised)
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SphereDensity:
    """σ = params["sigma"] inside a ball of radius params["radius"] (normalised units), else 0."""

    def __call__(self, params, xyz):
        return jnp.where(jnp.sum(xyz**2, -1) < params["radius"] ** 2, params["sigma"], 0.0)


@dataclasses.dataclass(frozen=True)
class SmoothColour:
    """A colour depending on position, view direction and an optional conditioning scalar."""

    def __call__(self, params, cond, xyz, viewdirs):
        shift = 0.0 if cond is None else cond
        return jax.nn.sigmoid(xyz @ params["w"] + viewdirs @ params["v"] + shift)


@dataclasses.dataclass(frozen=True)
class SlabDensity:
    """σ = params["sigma"] where params["x0"] <= world x < params["x1"] (cube aabb, so x = 1.5 u)."""

    def __call__(self, params, xyz):
        x = 1.5 * xyz[:, 0]
        return jnp.where((x >= params["x0"]) & (x < params["x1"]), params["sigma"], 0.0)


def numpy_field(cfg: ModelConfig, res, seed: int, scale: float = 1.0) -> dict:
    """A TensoRF params pytree drawn with numpy (no per-shape compilation of random kernels)."""
    rng = np.random.default_rng(seed)

    def vm(ranks):
        planes = [
            rng.normal(size=(res[a], res[b], r)) * scale
            for (a, b), r in zip(grids.MAT_MODES, ranks, strict=True)
        ]
        lines = [rng.normal(size=(res[c], r)) * scale for c, r in zip(grids.VEC_MODES, ranks, strict=True)]
        as32 = lambda xs: tuple(jnp.asarray(x, jnp.float32) for x in xs)
        return {"planes": as32(planes), "lines": as32(lines)}

    width, n_in = cfg.mlp_width, field.mlp_in_features(cfg)
    mlp_shapes = {
        "w0": (n_in, width),
        "b0": (width,),
        "w1": (width, width),
        "b1": (width,),
        "w2": (width, 3),
        "b2": (3,),
    }
    return {
        "density": vm(cfg.density_ranks),
        "appearance": vm(cfg.appearance_ranks),
        "basis": jnp.asarray(
            rng.normal(size=(sum(cfg.appearance_ranks), cfg.app_features)) * 0.3, jnp.float32
        ),
        "mlp": {k: jnp.asarray(rng.normal(size=v) * 0.3, jnp.float32) for k, v in mlp_shapes.items()},
    }


SPHERE = render.FieldFns(density=SphereDensity(), colour=SmoothColour())
SLAB = render.FieldFns(density=SlabDensity(), colour=SmoothColour())


def sphere_params(sigma=8.0, radius=0.4):
    rng = np.random.default_rng(0)
    return {
        "sigma": jnp.float32(sigma),
        "radius": jnp.float32(radius),
        "w": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32),
        "v": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32),
    }


def camera_rays(n: int, seed: int = 0, spread: float = 0.35):
    """Rays from a point on a sphere of radius 4 towards (around) the origin, unit directions."""
    rng = np.random.default_rng(seed)
    origin = np.array([0.3, -0.5, 4.0])
    target = rng.normal(size=(n, 3)) * spread
    d = target - origin
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return jnp.asarray(np.broadcast_to(origin, (n, 3)), jnp.float32), jnp.asarray(d, jnp.float32)


# --------------------------------------------------------------------------------------------------
# Compositing
# --------------------------------------------------------------------------------------------------


@SETTINGS
@given(seed=st.integers(0, 2**16), scale=st.sampled_from([0.1, 3.0, 200.0]))
@example(seed=236, scale=0.1)  # a case whose transmittance rises by 2 ulps
def test_compositing_laws_and_scan_equals_cumsum(seed, scale):
    rng = np.random.default_rng(seed)
    sigma = rng.exponential(scale, size=(6, 40)).astype(np.float32) * (rng.uniform(size=(6, 40)) < 0.6)
    dists = rng.uniform(0.001, 0.05, size=(6, 40)).astype(np.float32)
    w, trans = composite_cumsum(sigma, dists, 25.0)
    w_ref, trans_ref = composite_scan(sigma, dists, 25.0)
    w, trans = np.asarray(w), np.asarray(trans)
    assert np.all(w >= 0)
    assert np.all(w.sum(-1) <= 1 + 1e-6)
    # Transmittance never increases, up to float32 rounding: XLA's cumsum is a parallel scan, whose partial
    # sums are not monotone to the last ulp (seed 236 at scale 0.1 rises by 2 ulps).
    assert np.all(np.diff(trans, axis=-1) <= 8 * np.finfo(np.float32).eps)
    np.testing.assert_allclose(trans[:, 0], 1.0)
    np.testing.assert_allclose(w, np.asarray(w_ref), atol=1e-5)
    np.testing.assert_allclose(trans, np.asarray(trans_ref), atol=1e-5)
    # Total opacity is 1 - exp(-total optical depth).
    np.testing.assert_allclose(w.sum(-1), 1 - np.exp(-(sigma * dists * 25.0).sum(-1)), atol=1e-5)


def test_scan_and_cumsum_gradients_agree():
    rng = np.random.default_rng(1)
    sigma = jnp.asarray(rng.exponential(2.0, size=(4, 30)), jnp.float32)
    dists = jnp.full((4, 30), 0.02, jnp.float32)
    colours = jnp.asarray(rng.uniform(size=(4, 30)), jnp.float32)

    def loss(fn, s):
        return jnp.sum(fn(s, dists, 25.0)[0] * colours)

    g1 = jax.grad(lambda s: loss(render.composite_cumsum, s))(sigma)
    g2 = jax.grad(lambda s: loss(render.composite_scan, s))(sigma)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g2), atol=1e-5)


# --------------------------------------------------------------------------------------------------
# Sampling and a constant-density slab
# --------------------------------------------------------------------------------------------------


def _slab_geometry(n_samples=200, ndc=False):
    geo = raymarch.make_geometry(CUBE, (64, 64, 64), near=0.0, far=10.0, ndc=ndc, n_samples=n_samples)
    return geo


@SETTINGS
@given(seed=st.integers(0, 2**16), m=st.integers(1, 60), sigma=st.sampled_from([0.05, 0.5, 3.0]))
def test_slab_opacity(seed, m, sigma):
    """A slab crossed by exactly m samples (any jitter): acc = 1 - exp(-σ L s), L its length along the ray."""
    rng = np.random.default_rng(seed)
    geo = _slab_geometry()
    step = float(geo.step_size)
    d = np.array([1.0, rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)])  # stays in the box up to x = 1
    d /= np.linalg.norm(d)
    o = np.array([-4.0, rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)])
    length_along_ray = m * step
    x0 = -1.0 + rng.uniform(0, 0.2)
    params = dict(
        sphere_params(),
        x0=jnp.float32(x0),
        x1=jnp.float32(x0 + length_along_ray * d[0]),
        sigma=jnp.float32(sigma),
    )
    rays_o = jnp.asarray(np.tile(o, (3, 1)), jnp.float32)
    rays_d = jnp.asarray(np.tile(d, (3, 1)), jnp.float32)
    out = render.render_rays(
        SLAB,
        params,
        None,
        rays_o,
        rays_d,
        geo,
        jax.random.PRNGKey(seed),
        train=True,
        density_budget=None,
        colour_budget=None,
    )
    expected = 1 - np.exp(-sigma * length_along_ray * float(geo.distance_scale))
    np.testing.assert_allclose(np.asarray(out["acc"]), expected, atol=1e-5, rtol=1e-4)


def test_ndc_slab_scales_distances_by_direction_norm():
    geo = raymarch.make_geometry(
        np.array([[-1.5, -1.67, -1.0], [1.5, 1.67, 1.0]]),
        (32, 32, 32),
        near=0.0,
        far=1.0,
        ndc=True,
        n_samples=101,
    )
    # t_k = k / 100; ray o + t d with d = (2, 0, 0) * s: x(t) = -1 + 2 s t.
    for scale in (1.0, 0.7):
        d = jnp.asarray([[2.0 * scale, 0.0, 0.0]])
        o = jnp.asarray([[-1.0, 0.1, 0.0]])
        # Samples k = 20..49 (30 of them) fall in the slab.
        x0, x1 = -1 + 2 * scale * 0.195, -1 + 2 * scale * 0.495
        params = dict(sphere_params(), x0=jnp.float32(x0), x1=jnp.float32(x1), sigma=jnp.float32(0.2))
        out = render.render_rays(
            SLAB, params, None, o, d, geo, None, train=False, density_budget=None, colour_budget=None
        )
        optical = 0.2 * 30 * 0.01 * (2.0 * scale) * 25.0
        np.testing.assert_allclose(float(out["acc"][0]), 1 - np.exp(-optical), rtol=1e-4)
        compact = render.render_rays(
            SLAB, params, None, o, d, geo, None, train=False, density_budget=128, colour_budget=48
        )
        np.testing.assert_allclose(np.asarray(compact["rgb"]), np.asarray(out["rgb"]), atol=1e-6)
        assert int(compact["density_overflow"]) == 0 and int(compact["colour_overflow"]) == 0


def test_sample_along_rays_bounded_and_ndc():
    geo = _slab_geometry(n_samples=50)
    rays_o, rays_d = camera_rays(5)
    t, dists, vd = raymarch.sample_along_rays(rays_o, rays_d, geo, None)
    t_in, _ = raymarch.aabb_entry_exit(rays_o, rays_d, geo.aabb)
    np.testing.assert_allclose(np.asarray(t[:, 0]), np.clip(np.asarray(t_in), 0.0, 10.0), rtol=1e-6)
    np.testing.assert_allclose(np.diff(np.asarray(t), axis=-1), float(geo.step_size), rtol=1e-4)
    assert np.all(np.asarray(dists[:, -1]) == 0)
    tj, _, _ = raymarch.sample_along_rays(rays_o, rays_d, geo, jax.random.PRNGKey(0))
    shift = np.asarray(tj - t) / float(geo.step_size)
    assert np.all((shift >= 0) & (shift < 1))
    np.testing.assert_allclose(shift, np.broadcast_to(shift[:, :1], shift.shape), atol=1e-3)  # one per ray
    assert np.ptp(shift[:, 0]) > 0
    # NDC: one jitter row shared by all rays.
    ndc = raymarch.make_geometry(CUBE, (8, 8, 8), near=0.0, far=1.0, ndc=True, n_samples=16)
    tn, _, vdn = raymarch.sample_along_rays(rays_o, 2.0 * rays_d, ndc, jax.random.PRNGKey(1))
    np.testing.assert_allclose(np.asarray(tn), np.asarray(tn[:1]).repeat(5, 0))
    base = np.linspace(0, 1, 16)
    assert np.all((np.asarray(tn[0]) - base >= 0) & (np.asarray(tn[0]) - base < 1 / 16))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(vdn), axis=-1), 1.0, rtol=1e-6)


# --------------------------------------------------------------------------------------------------
# Compaction
# --------------------------------------------------------------------------------------------------


def _render(fns, params, geo, rays_o, rays_d, db, cb, cond=None, train=False, bg=None):
    return render.render_rays(
        fns,
        params,
        cond,
        rays_o,
        rays_d,
        geo,
        jax.random.PRNGKey(3),
        train=train,
        density_budget=db,
        colour_budget=cb,
        bg=bg,
    )


def test_compaction_equals_dense_with_sufficient_budget():
    geo = _slab_geometry(n_samples=160)
    params = sphere_params()
    rays_o, rays_d = camera_rays(64)
    dense = _render(SPHERE, params, geo, rays_o, rays_d, None, None, cond=jnp.float32(0.3), train=True)
    n_density, n_colour = int(dense["density_count"]), int(dense["colour_count"])
    assert 0 < n_colour < n_density < 64 * 160
    comp = _render(
        SPHERE, params, geo, rays_o, rays_d, n_density + 7, n_colour + 5, cond=jnp.float32(0.3), train=True
    )
    for name in ("rgb", "depth", "acc"):
        np.testing.assert_allclose(np.asarray(comp[name]), np.asarray(dense[name]), atol=1e-5)
    assert int(comp["density_overflow"]) == 0 and int(comp["colour_overflow"]) == 0
    assert int(comp["density_count"]) == n_density and int(comp["colour_count"]) == n_colour
    assert float(jnp.min(dense["acc"])) < 0.01 < 0.9 < float(jnp.max(dense["acc"]))

    def loss(p, db, cb):
        out = _render(SPHERE, p, geo, rays_o, rays_d, db, cb, cond=jnp.float32(0.3), train=True)
        return jnp.sum(out["rgb"] * jnp.arange(3.0))

    g_dense = jax.grad(loss)(params, None, None)
    g_comp = jax.grad(loss)(params, n_density + 7, n_colour + 5)
    for name in ("sigma", "w", "v"):
        np.testing.assert_allclose(np.asarray(g_comp[name]), np.asarray(g_dense[name]), atol=1e-4, rtol=1e-4)


def test_overflow_is_reported():
    geo = _slab_geometry(n_samples=160)
    params = sphere_params()
    rays_o, rays_d = camera_rays(64)
    out = _render(SPHERE, params, geo, rays_o, rays_d, 1024, 16)
    d_count = int(out["density_count"])
    assert int(out["density_overflow"]) == d_count - 1024 > 0
    full = 64 * 160  # cannot overflow
    out = _render(SPHERE, params, geo, rays_o, rays_d, full, 16)
    c_count = int(out["colour_count"])
    assert int(out["density_overflow"]) == 0
    assert int(out["colour_overflow"]) == c_count - 16 > 0


def test_tensorf_field_compaction_matches_dense():
    cfg = ModelConfig(
        density_ranks=(2, 2, 2),
        appearance_ranks=(3, 3, 3),
        app_features=5,
        mlp_width=16,
        density_shift=-1.0,
        init_scale=1.0,
    )
    params = numpy_field(cfg, (9, 9, 9), 4)
    fns = render.tensorf_field_fns(cfg)
    assert fns == render.tensorf_field_fns(cfg)  # equal fields share compilations
    geo = _slab_geometry(n_samples=96)
    rays_o, rays_d = camera_rays(32)
    dense = _render(fns, params, geo, rays_o, rays_d, None, None)
    comp = _render(fns, params, geo, rays_o, rays_d, int(dense["density_count"]), int(dense["colour_count"]))
    assert int(dense["colour_count"]) > 0
    np.testing.assert_allclose(np.asarray(comp["rgb"]), np.asarray(dense["rgb"]), atol=1e-5)


def test_budget_policy_never_drops_samples():
    geo = _slab_geometry(n_samples=160)
    params = sphere_params(radius=0.8)
    rays_o, rays_d = camera_rays(64, spread=2.0)  # many rays cross little of the box
    dense = _render(SPHERE, params, geo, rays_o, rays_d, None, None)
    # The first colour budget (8) is too small: the first call overflows and is re-run.
    policy = budgets.BudgetPolicy(minimum=8, colour_fraction=0.0, patience=2, min_shrink=0)
    for _ in range(4):
        out = chunked.render_rays_exact(
            SPHERE, params, None, rays_o, rays_d, geo, None, train=False, policy=policy, site="t"
        )
        np.testing.assert_allclose(np.asarray(out["rgb"]), np.asarray(dense["rgb"]), atol=1e-5)
    db, cb = policy.budgets("t", 64, 160)
    # Shrunk to fit the observed counts (with headroom), never below them.
    n_density, n_colour = int(dense["density_count"]), int(dense["colour_count"])
    assert n_density <= db <= 1.6 * n_density < 64 * 160
    assert 8 < n_colour <= cb <= 1.6 * n_colour


def test_budget_policy_grows_shrinks_and_rescales():
    policy = budgets.BudgetPolicy(minimum=8, patience=3, colour_fraction=0.1, min_shrink=0)
    ladder = lambda x: budgets.ladder_budget(x, 4, 8)
    assert policy.budgets("s", 10, 100) == (1000, ladder(100))
    counts = {"density_count": 300, "colour_count": 200}
    assert policy.update("s", counts, 10, 100)  # colour overflowed: re-run
    assert policy.budgets("s", 10, 100) == (1000, ladder(240))
    for _ in range(3):
        assert not policy.update("s", counts, 10, 100)
    # Density shrank to fit (with headroom); colour was already snug.
    assert policy.budgets("s", 10, 100) == (ladder(360), ladder(240))
    # Twice the samples per ray (after upsampling): budgets scale instead of restarting dense.
    assert policy.budgets("s", 10, 200) == (ladder(2 * ladder(360)), ladder(2 * ladder(240)))
    assert policy.budgets("other", 10, 100)[0] == 1000


def test_budget_policy_keeps_budgets_when_a_shrink_frees_little():
    policy = budgets.BudgetPolicy(minimum=8, patience=2, colour_fraction=1.0, min_shrink=500)
    counts = {"density_count": 300, "colour_count": 200}
    assert policy.budgets("s", 10, 100) == (1000, 1000)  # colour starts as large as density: no overflow
    for _ in range(2):
        assert not policy.update("s", counts, 10, 100)
    # Density 1000 -> 384 frees 616 slots: worth a compilation; colour 1000 -> 240 as well.
    expected = (budgets.ladder_budget(360, 4, 8), budgets.ladder_budget(240, 4, 8))
    assert policy.budgets("s", 10, 100) == expected
    small = budgets.BudgetPolicy(minimum=8, patience=2, colour_fraction=1.0, min_shrink=800)
    small.budgets("s", 10, 100)
    for _ in range(2):
        assert not small.update("s", counts, 10, 100)
    assert small.budgets("s", 10, 100) == (1000, 1000)  # neither frees 800 slots


def test_ladder_budget():
    assert budgets.ladder_budget(1000, 4, 1) == 1024
    assert budgets.ladder_budget(1025, 4, 1) == 1280
    assert budgets.ladder_budget(5, 1, 1) == 8
    for needed in (1, 17, 999, 123457):
        b = budgets.ladder_budget(needed, 4, 1)
        assert needed <= b <= 1.25 * needed + 4


def test_backgrounds():
    geo = _slab_geometry(n_samples=64)
    params = sphere_params(sigma=0.0)  # empty space: acc = 0
    rays_o, rays_d = camera_rays(4)
    white = _render(SPHERE, params, geo, rays_o, rays_d, None, None)
    np.testing.assert_allclose(np.asarray(white["rgb"]), 1.0)
    black = _render(SPHERE, params, dataclasses.replace(geo, white_bg=False), rays_o, rays_d, None, None)
    np.testing.assert_allclose(np.asarray(black["rgb"]), 0.0)
    per_ray = jnp.asarray(np.random.default_rng(0).uniform(size=(4, 3)), jnp.float32)
    custom = _render(SPHERE, params, geo, rays_o, rays_d, None, None, bg=per_ray)
    np.testing.assert_allclose(np.asarray(custom["rgb"]), np.asarray(per_ray), atol=1e-6)


# --------------------------------------------------------------------------------------------------
# Alpha mask, shrink, filtering, images
# --------------------------------------------------------------------------------------------------


def test_alpha_mask_skips_empty_space_and_keeps_the_image():
    geo = _slab_geometry(n_samples=160)
    params = sphere_params(radius=0.4)
    mask = alpha_mask.compute_alpha_mask(SPHERE, params, geo, (24, 24, 24))
    nodes = np.stack(np.meshgrid(*[np.linspace(-1, 1, 24)] * 3, indexing="ij"), -1)
    r = np.linalg.norm(nodes, axis=-1)
    assert np.all(mask[r < 0.38]) and not np.any(mask[r > 0.4 + 2 * np.sqrt(3) * 2 / 23])
    masked = raymarch.with_alpha_mask(geo, mask, geo.aabb)
    rays_o, rays_d = camera_rays(64)
    before = _render(SPHERE, params, geo, rays_o, rays_d, None, None)
    after = _render(SPHERE, params, masked, rays_o, rays_d, None, None)
    np.testing.assert_allclose(np.asarray(after["rgb"]), np.asarray(before["rgb"]), atol=1e-5)
    assert int(after["density_count"]) < 0.5 * int(before["density_count"])
    compact = _render(
        SPHERE, params, masked, rays_o, rays_d, int(after["density_count"]), int(after["colour_count"])
    )
    np.testing.assert_allclose(np.asarray(compact["rgb"]), np.asarray(after["rgb"]), atol=1e-5)

    box = alpha_mask.shrink_box_from_mask(mask, geo.aabb)
    occupied = nodes[mask] * 1.5
    np.testing.assert_allclose(box, np.stack([occupied.min(0), occupied.max(0)]), atol=1e-5)
    assert np.all(box[0] <= -0.4 * 1.5) and np.all(box[1] >= 0.4 * 1.5)

    keep = alpha_mask.filter_rays(masked, rays_o, rays_d, chunk=40)
    hits = np.asarray(before["acc"]) > 1e-3
    assert np.all(keep[hits]) and keep.shape == (64,)
    far_o = jnp.asarray([[0.0, 1.2, 4.0], [0.0, 0.0, 4.0]])
    down = jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    np.testing.assert_array_equal(alpha_mask.filter_rays(masked, far_o, down), [False, True])
    np.testing.assert_array_equal(alpha_mask.filter_rays(masked, far_o, down, bbox_only=True), [True, True])
    miss = jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    np.testing.assert_array_equal(alpha_mask.filter_rays(masked, far_o, miss, bbox_only=True), [False, False])


def test_shrink_field_preserves_density_inside_new_box():
    cfg = ModelConfig(
        density_ranks=(2, 2, 2), appearance_ranks=(2, 2, 2), app_features=4, mlp_width=8, init_scale=1.0
    )
    params = numpy_field(cfg, (16, 16, 16), 5)
    new_box = np.array([[-0.7, -0.2, -1.1], [0.9, 1.3, 0.1]], np.float32)
    small, aligned = alpha_mask.shrink_field(params, CUBE, new_box)
    assert grids.vm_resolution(small["density"]) == grids.vm_resolution(small["appearance"])
    assert grids.vm_resolution(small["density"])[0] < 16
    assert small["mlp"]["w0"] is params["mlp"]["w0"] and small["basis"] is params["basis"]
    pts = aligned[0] + np.random.default_rng(0).uniform(size=(50, 3)) * (aligned[1] - aligned[0])
    pts = jnp.asarray(pts, jnp.float32)
    density = jax.jit(field.density, static_argnums=2)
    before = density(params, grids.normalize_points(pts, jnp.asarray(CUBE)), cfg)
    after = density(small, grids.normalize_points(pts, jnp.asarray(aligned)), cfg)
    np.testing.assert_allclose(np.asarray(after), np.asarray(before), rtol=1e-4, atol=1e-6)


def test_render_image_matches_render_rays():
    geo = _slab_geometry(n_samples=96)
    params = sphere_params()
    rays_o, rays_d = camera_rays(7 * 9)
    img = chunked.render_image(SPHERE, params, None, rays_o, rays_d, geo, 7, 9, chunk=16)
    ref = _render(SPHERE, params, geo, rays_o, rays_d, None, None)
    assert img["rgb"].shape == (7, 9, 3) and img["depth"].shape == (7, 9) and img["acc"].shape == (7, 9)
    np.testing.assert_allclose(img["rgb"].reshape(-1, 3), np.asarray(ref["rgb"]), atol=1e-5)
    np.testing.assert_allclose(img["depth"].reshape(-1), np.asarray(ref["depth"]), atol=1e-4)
    with pytest.raises(ValueError):
        chunked.render_image(SPHERE, params, None, rays_o, rays_d, geo, 8, 9)


def test_geometry_is_a_pytree_with_static_shape_fields():
    geo = _slab_geometry(n_samples=33)
    leaves, treedef = jax.tree_util.tree_flatten(geo)
    assert len(leaves) == 8
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert rebuilt.n_samples == 33 and rebuilt.white_bg and not rebuilt.ndc
    with pytest.raises(ValueError):
        raymarch.with_alpha_mask(geo, np.ones((1, 4, 4), bool), CUBE)


@pytest.mark.parametrize("count", [0, 5, 16, 17, 40, 64])
def test_colour_in_chunks_skips_only_padding(count):
    """Chunks past the count are skipped (zeros), the others equal one call, in value and gradient."""
    fns = render.FieldFns(density=SphereDensity(), colour=SmoothColour())
    rng = np.random.default_rng(count)
    xyz = jnp.asarray(rng.uniform(-1, 1, (64, 3)), jnp.float32)
    vd = jnp.asarray(rng.normal(size=(64, 3)), jnp.float32)
    cot = jnp.asarray(rng.normal(size=(64, 3)), jnp.float32)
    params = {
        "w": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32),
        "v": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32),
    }
    cond = jnp.float32(0.3)
    live = (np.arange(64) < -(-count // 16) * 16)[:, None]  # the rows of chunks holding a sample

    def loss(p, c, chunked):
        if chunked:
            rgb = render.colour_in_chunks(fns, p, c, xyz, vd, jnp.int32(count), chunk=16)
        else:
            rgb = jnp.where(live, fns.colour(p, c, xyz, vd), 0.0)
        return jnp.sum(cot * rgb), rgb

    def value_and_grad(chunked):
        return jax.value_and_grad(lambda p, c: loss(p, c, chunked), argnums=(0, 1), has_aux=True)(
            params, cond
        )

    (_, got), g_got = jax.jit(lambda: value_and_grad(True))()
    (_, want), g_want = value_and_grad(False)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6, atol=1e-6)
    assert not np.any(np.asarray(got)[~live[:, 0]])
    for a, b in zip(jax.tree.leaves(g_got), jax.tree.leaves(g_want), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)
