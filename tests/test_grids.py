"""VM factor grids: exact sampling of linear fields, zero padding, resampling, cropping, schedules."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mnerf_jax.tensorf import grid_volume, grids

SETTINGS = settings(max_examples=10, deadline=None)

# Jitted once per shape: eager op-by-op dispatch would compile every primitive for every new shape.
sample_vm = jax.jit(grids.sample_vm)
sample_vm_sum = jax.jit(grid_volume.sample_vm_sum)
upsample_vm = jax.jit(grids.upsample_vm, static_argnums=1)


def _nodes(g: int) -> np.ndarray:
    return np.linspace(-1.0, 1.0, g)


def linear_vm(res, coeffs) -> tuple[dict, callable]:
    """A rank-1-per-mode grid whose modes are (a u + b v + e)(d w + f): bilinear sampling is exact."""
    planes, lines, funcs = [], [], []
    for m, ((ia, ib), ic) in enumerate(zip(grids.MAT_MODES, grids.VEC_MODES, strict=True)):
        a, b, e, d, f = coeffs[m]
        u, v = np.meshgrid(_nodes(res[ia]), _nodes(res[ib]), indexing="ij")
        planes.append(jnp.asarray((a * u + b * v + e)[..., None], jnp.float32))
        lines.append(jnp.asarray((d * _nodes(res[ic]) + f)[:, None], jnp.float32))
        funcs.append((ia, ib, ic, a, b, e, d, f))

    def exact(xyz: np.ndarray) -> np.ndarray:
        cols = []
        for ia, ib, ic, a, b, e, d, f in funcs:
            cols.append((a * xyz[:, ia] + b * xyz[:, ib] + e) * (d * xyz[:, ic] + f))
        return np.stack(cols, -1)

    return {"planes": tuple(planes), "lines": tuple(lines)}, exact


def random_vm(seed: int, res, ranks) -> dict:
    """Standard-normal factors from numpy (cheap: no per-shape compilation)."""
    rng = np.random.default_rng(seed)
    planes = tuple(
        jnp.asarray(rng.normal(size=(res[a], res[b], r)), jnp.float32)
        for (a, b), r in zip(grids.MAT_MODES, ranks, strict=True)
    )
    lines = tuple(
        jnp.asarray(rng.normal(size=(res[c], r)), jnp.float32)
        for c, r in zip(grids.VEC_MODES, ranks, strict=True)
    )
    return {"planes": planes, "lines": lines}


def reference_sample(grid: dict, xyz: np.ndarray) -> np.ndarray:
    """grid_sample(align_corners=True, padding zeros) written with explicit corner validity."""

    def lin_taps(coord: np.ndarray, size: int):
        g = (coord + 1.0) / 2.0 * (size - 1)
        i0 = np.floor(g).astype(np.int64)
        f = g - i0
        return [(i0, 1.0 - f), (i0 + 1, f)]

    out = []
    for plane, line, (ia, ib), ic in zip(
        grid["planes"], grid["lines"], grids.MAT_MODES, grids.VEC_MODES, strict=True
    ):
        plane, line = np.asarray(plane, np.float64), np.asarray(line, np.float64)
        pv = np.zeros((xyz.shape[0], plane.shape[-1]))
        for i, wi in lin_taps(xyz[:, ia], plane.shape[0]):
            for j, wj in lin_taps(xyz[:, ib], plane.shape[1]):
                ok = (i >= 0) & (i < plane.shape[0]) & (j >= 0) & (j < plane.shape[1])
                vals = plane[np.clip(i, 0, plane.shape[0] - 1), np.clip(j, 0, plane.shape[1] - 1)]
                pv += np.where(ok[:, None], vals * (wi * wj)[:, None], 0.0)
        lv = np.zeros((xyz.shape[0], line.shape[-1]))
        for k, wk in lin_taps(xyz[:, ic], line.shape[0]):
            ok = (k >= 0) & (k < line.shape[0])
            lv += np.where(ok[:, None], line[np.clip(k, 0, line.shape[0] - 1)] * wk[:, None], 0.0)
        out.append(pv * lv)
    return np.concatenate(out, -1)


# A few shapes (each compiles once), including the smallest grid and unequal sizes.
res_st = st.sampled_from([(2, 2, 2), (3, 5, 4), (8, 6, 9)])
coef_st = st.lists(st.tuples(*[st.floats(-2, 2)] * 5), min_size=3, max_size=3)


@SETTINGS
@given(res=res_st, coeffs=coef_st, seed=st.integers(0, 2**16))
def test_sampling_exact_on_linear_fields(res, coeffs, seed):
    grid, exact = linear_vm(res, coeffs)
    xyz = np.random.default_rng(seed).uniform(-1, 1, (64, 3))
    xyz[:3] = [[-1, -1, -1], [1, 1, 1], [-1, 1, 0]]  # the corners are inside (align_corners=True)
    got = np.asarray(sample_vm(grid, jnp.asarray(xyz, jnp.float32)))
    np.testing.assert_allclose(got, exact(xyz), atol=2e-5, rtol=1e-5)
    total = np.asarray(sample_vm_sum(grid, jnp.asarray(xyz, jnp.float32)))
    np.testing.assert_allclose(total, exact(xyz).sum(-1), atol=6e-5, rtol=1e-5)


@SETTINGS
@given(res=res_st, ranks=st.sampled_from([(1, 1, 1), (2, 3, 4)]), seed=st.integers(0, 2**16))
def test_sampling_matches_grid_sample_with_zero_padding(res, ranks, seed):
    grid = random_vm(seed, res, ranks)
    # Points inside, in the padding band just outside, and far outside the box.
    xyz = np.random.default_rng(seed).uniform(-1.6, 1.6, (96, 3))
    got = np.asarray(sample_vm(grid, jnp.asarray(xyz, jnp.float32)))
    np.testing.assert_allclose(got, reference_sample(grid, xyz), atol=1e-5, rtol=1e-5)


def test_far_outside_is_zero():
    grid = grids.init_vm(jax.random.PRNGKey(0), (5, 6, 7), (2, 3, 4), 1.0)
    xyz = jnp.asarray([[3.0, 0.0, 0.0], [0.0, -5.0, 0.2], [0.1, 0.2, 9.0]])
    feats = np.asarray(sample_vm(grid, xyz))
    # Each point is outside along one axis: every mode has a plane or line factor along it.
    assert np.all(feats == 0.0)


def test_init_shapes_and_scale():
    grid = grids.init_vm(jax.random.PRNGKey(1), (20, 30, 40), (4, 5, 6), 0.1)
    assert [p.shape for p in grid["planes"]] == [(20, 30, 4), (20, 40, 5), (30, 40, 6)]
    assert [l.shape for l in grid["lines"]] == [(40, 4), (30, 5), (20, 6)]
    assert grids.vm_resolution(grid) == (20, 30, 40)
    assert grids.vm_ranks(grid) == (4, 5, 6)
    std = float(jnp.std(grid["planes"][2]))
    assert 0.09 < std < 0.11


def test_gradients_flow_to_factors_only():
    grid = grids.init_vm(jax.random.PRNGKey(2), (4, 5, 6), (2, 2, 2), 1.0)
    xyz = jax.random.uniform(jax.random.PRNGKey(3), (10, 3), minval=-1, maxval=1)
    g_grid, g_xyz = jax.grad(lambda g, x: jnp.sum(sample_vm(g, x) ** 2), argnums=(0, 1))(grid, xyz)
    assert float(jnp.abs(g_grid["planes"][0]).sum()) > 0
    assert float(jnp.abs(g_xyz).sum()) == 0.0  # coordinates are detached, as TensoRF's


@SETTINGS
@given(
    res=res_st,
    new=st.sampled_from([(2, 3, 2), (7, 11, 5), (12, 12, 12)]),
    coeffs=coef_st,
    seed=st.integers(0, 2**16),
)
def test_upsample_keeps_linear_fields(res, new, coeffs, seed):
    grid, exact = linear_vm(res, coeffs)
    up = upsample_vm(grid, new)
    assert grids.vm_resolution(up) == tuple(new)
    xyz = np.random.default_rng(seed).uniform(-1, 1, (48, 3))
    np.testing.assert_allclose(
        np.asarray(sample_vm(up, jnp.asarray(xyz, jnp.float32))), exact(xyz), atol=3e-5, rtol=1e-5
    )


@SETTINGS
@given(res=res_st, factor=st.sampled_from([1, 3]), seed=st.integers(0, 2**16))
def test_upsample_preserves_old_nodes(res, factor, seed):
    grid = random_vm(seed, res, (2, 3, 2))
    new = tuple(factor * (g - 1) + 1 for g in res)
    up = upsample_vm(grid, new)
    # Every old node is a new node: the field there is unchanged.
    nodes = np.stack(np.meshgrid(*[_nodes(g) for g in res], indexing="ij"), -1).reshape(-1, 3)
    nodes = jnp.asarray(nodes, jnp.float32)
    np.testing.assert_allclose(
        np.asarray(sample_vm(up, nodes)), np.asarray(sample_vm(grid, nodes)), atol=1e-5
    )


@SETTINGS
@given(
    res=st.sampled_from([(4, 4, 4), (9, 12, 7)]),
    box=st.tuples(*[st.floats(0.0, 1.0)] * 6),
    seed=st.integers(0, 2**16),
)
def test_shrink_preserves_field_inside_new_box(res, box, seed):
    rng = np.random.default_rng(seed)
    aabb = np.array([[-1.5, -1.2, -1.0], [1.5, 1.4, 0.8]])
    grid = random_vm(seed, res, (2, 2, 3))
    lo_f = np.minimum(box[:3], box[3:])
    hi_f = np.maximum(box[:3], box[3:])
    new_box = aabb[0] + np.stack([lo_f, hi_f]) * (aabb[1] - aabb[0])
    lo, hi, aligned = grids.shrink_indices(aabb, res, new_box)
    small = grids.shrink_vm(grid, lo, hi)
    assert grids.vm_resolution(small) == tuple(h - l for l, h in zip(lo, hi, strict=True))
    # The aligned box sits on old nodes and contains the requested box up to half a voxel.
    unit = (aabb[1] - aabb[0]) / (np.asarray(res) - 1)
    assert np.all(aligned[0] <= new_box[0] + 0.5 * unit + 1e-5)
    assert np.all(aligned[1] >= np.minimum(new_box[1], aabb[1]) - 0.5 * unit - 1e-5)
    world = aligned[0] + rng.uniform(0, 1, (64, 3)) * (aligned[1] - aligned[0])
    old = sample_vm(
        grid, grids.normalize_points(jnp.asarray(world, jnp.float32), jnp.asarray(aabb, jnp.float32))
    )
    new = sample_vm(small, grids.normalize_points(jnp.asarray(world, jnp.float32), jnp.asarray(aligned)))
    np.testing.assert_allclose(np.asarray(new), np.asarray(old), atol=2e-5, rtol=1e-4)


def test_tensorf_resolution_schedule():
    cube = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    counts = grids.voxel_schedule(128**3, 300**3, (2000, 3000, 4000, 5500, 7000))
    assert len(counts) == 5 and counts[-1] == 300**3
    assert all(a < b for a, b in zip(counts, counts[1:], strict=False))
    # Log-linear: constant ratio between consecutive counts.
    ratios = np.diff(np.log(np.asarray([128**3] + counts, np.float64)))
    np.testing.assert_allclose(ratios, ratios[0], rtol=1e-5)
    resos = [grids.resolution_from_voxels(cube, n)[0] for n in [128**3] + counts]
    # TensoRF truncates (N_to_reso's .long()): 151.77 -> 151, 179.96 -> 179, ...
    assert resos == [128, 151, 179, 213, 253, 300]
    assert grids.n_samples_for((128, 128, 128), 0.5) == 443
    assert grids.n_samples_for((300, 300, 300), 0.5) == 1039
    assert grids.step_size_for(cube, (128, 128, 128), 0.5) == pytest.approx(3.0 / 127 * 0.5)


def test_resolution_follows_aspect_ratio():
    aabb = np.array([[-1.5, -1.67, -1.0], [1.5, 1.67, 1.0]])
    res = grids.resolution_from_voxels(aabb, 128**3)
    size = aabb[1] - aabb[0]
    voxel = (np.prod(size) / 128**3) ** (1 / 3)
    assert res == tuple(int(s / voxel) for s in size)
    assert res[1] > res[0] > res[2]
    assert abs(math.prod(res) / 128**3 - 1) < 0.03


def test_l1_and_tv_regularisers():
    res = (5, 6, 7)
    slopes = [(0.5, -1.0), (2.0, 0.0), (0.0, 3.0)]
    planes, lines = [], []
    for (ia, ib), ic, (sa, sb) in zip(grids.MAT_MODES, grids.VEC_MODES, slopes, strict=True):
        i, j = np.meshgrid(np.arange(res[ia]), np.arange(res[ib]), indexing="ij")
        planes.append(jnp.asarray(np.stack([sa * i + sb * j, -(sa * i + sb * j)], -1), jnp.float32))
        lines.append(jnp.full((res[ic], 2), -2.0))
    grid = {"planes": tuple(planes), "lines": tuple(lines)}
    # TVLoss of a plane with constant steps (sa, sb) is 2 (sa^2 + sb^2).
    expected_tv = sum(2 * (sa**2 + sb**2) for sa, sb in slopes)
    assert float(grids.tv_plane(grid, scale=1.0)) == pytest.approx(expected_tv, rel=1e-5)
    assert float(grids.tv_plane(grid)) == pytest.approx(1e-2 * expected_tv, rel=1e-5)
    expected_l1 = sum(float(np.mean(np.abs(np.asarray(p)))) + 2.0 for p in planes)
    assert float(grids.l1_density(grid)) == pytest.approx(expected_l1, rel=1e-5)


def test_rejects_bad_resolution():
    with pytest.raises(ValueError):
        grids.init_vm(jax.random.PRNGKey(0), (1, 4, 4), (1, 1, 1))


@SETTINGS
@given(res=res_st, ranks=st.sampled_from([(1, 1, 1), (2, 3, 4)]), seed=st.integers(0, 2**16))
def test_density_volume_path_equals_gather_path(res, ranks, seed):
    """The dense-volume evaluation of the density feature (and the default, which differentiates through it)
    equals the per-mode gathers, value and gradient."""
    grid = random_vm(seed, res, ranks)
    # Inside, in the zero-padding band and far outside.
    xyz = jnp.asarray(np.random.default_rng(seed).uniform(-1.6, 1.6, (96, 3)), jnp.float32)
    cot = jnp.asarray(np.random.default_rng(seed + 1).normal(size=96), jnp.float32)

    def value_and_grad(method):
        return jax.value_and_grad(lambda g: jnp.sum(cot * grid_volume.sample_vm_sum(g, xyz, method)))(grid)

    by_gather = jax.jit(lambda: value_and_grad("gather"))()
    # 96 points: "auto" takes the volume's backward pass on these grids.
    for method in ("volume", "auto"):
        got = jax.jit(lambda m=method: value_and_grad(m))()
        np.testing.assert_allclose(got[0], by_gather[0], rtol=1e-5, atol=1e-4)
        for g, want in zip(jax.tree.leaves(got[1]), jax.tree.leaves(by_gather[1]), strict=True):
            np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-4)


@SETTINGS
@given(res=res_st, ranks=st.sampled_from([(1, 1, 1), (2, 3, 4)]), seed=st.integers(0, 2**16))
def test_projected_volume_backward_equals_gather_path(res, ranks, seed):
    """The appearance feature's dense-volume backward pass (a trilinear splat of the [P, K] cotangent
    and two matrix products per mode) gives the gathers' gradients for the factors and the basis."""
    grid = random_vm(seed, res, ranks)
    rng = np.random.default_rng(seed)
    basis = jnp.asarray(rng.normal(size=(sum(ranks), 5)), jnp.float32)
    xyz = jnp.asarray(rng.uniform(-1.6, 1.6, (128, 3)), jnp.float32)
    cot = jnp.asarray(rng.normal(size=(128, 5)), jnp.float32)
    cells = int(np.prod(res))
    assert cells <= grid_volume.PROJECTED_CELLS_PER_POINT * 128  # "auto" takes the volume's backward pass

    def value_and_grad(method):
        fn = lambda g, b: jnp.sum(cot * grid_volume.sample_vm_projected(g, b, xyz, method))  # noqa: E731
        return jax.value_and_grad(fn, argnums=(0, 1))(grid, basis)

    want = jax.jit(lambda: value_and_grad("gather"))()
    got = jax.jit(lambda: value_and_grad("auto"))()
    np.testing.assert_allclose(got[0], want[0], rtol=1e-5, atol=1e-4)
    for g, w in zip(jax.tree.leaves(got[1]), jax.tree.leaves(want[1]), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-4)


@SETTINGS
@given(res=res_st, seed=st.integers(0, 2**16))
def test_splat_volume_is_the_transpose_of_trilinear_sampling(res, seed):
    """<splat(v), V> = <v, sample(V)> for any volume V: the row scatters are the exact adjoint."""
    rng = np.random.default_rng(seed)
    xyz = jnp.asarray(rng.uniform(-1.6, 1.6, (64, 3)), jnp.float32)
    values = jnp.asarray(rng.normal(size=(64, 3)), jnp.float32)
    volume = jnp.asarray(rng.normal(size=(*res, 3)), jnp.float32)
    splat = grid_volume.splat_volume(values, xyz, tuple(res)).reshape(*res, 3)
    lhs = float(jnp.sum(splat * volume))
    rhs = float(jnp.sum(values * grid_volume.sample_volume(volume, xyz)))
    assert lhs == pytest.approx(rhs, rel=1e-4, abs=1e-3)
