"""Benchmarks of the renderer's hot paths on CPU.

1. Compositing, forward+backward: cumulative sum vs ``lax.scan`` (4096 rays x 443 samples).
2. VM plane sampling, forward and forward+backward: channels-last gather table vs
   ``jax.scipy.ndimage.map_coordinates`` (1 M points x 16 components, 128^2 plane).
3. The density feature (sum of a rank-16 x 3 VM grid's component products), forward and
   forward+backward, at points along random rays: per-mode gathers vs the dense trilinear volume
   vs the default (gather forward, volume backward; ``grid_volume.sample_vm_sum``), at 128^3 and 300^3
   with 0.52 M and 1.57 M points.
4. The colour MLP (TensoRF's MLP_Fea, 150 -> 128 -> 128 -> 3) forward+backward at 1 M points, in
   float32 and with bfloat16 operands, beside a 4096^3 float32 matrix product (the machine's matmul
   rate): the floor of a training step whose samples all need colour.
5. ``render_rays`` on a synthetic occupied field (a TensoRF VM-192 field at 128^3 that is empty except
   a ball): training step (forward+backward of an MSE loss) and evaluation, dense evaluation vs
   compaction (without and with the alpha mask).

Each figure is the best of ``--repeats`` runs after a warm-up (compilation excluded): the machine may
be shared, and the minimum is the least disturbed reading. ``--json`` prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mnerf_jax.cli.process import reexec_with_huge_pages

# glibc huge pages for XLA's buffers, as the mnerf command uses (see mnerf_jax.cli.fit).
reexec_with_huge_pages([sys.executable, str(Path(__file__).resolve()), *sys.argv[1:]])

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.scipy.ndimage import map_coordinates  # noqa: E402

from mnerf_jax.core import xla_cpu  # noqa: E402
from mnerf_jax.core.config import ModelConfig  # noqa: E402
from mnerf_jax.tensorf import alpha_mask, budgets, field, grid_volume, grids, raymarch, render  # noqa: E402


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Seconds of the fastest of ``repeats`` calls after one warm-up call."""
    jax.block_until_ready(fn())
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


# --------------------------------------------------------------------------------------------------


def bench_compositing(repeats: int, options: dict, rays: int = 4096, samples: int = 443) -> dict[str, float]:
    """Compositing weights, forward and forward+backward of Σ w c (arrays passed as arguments)."""
    rng = np.random.default_rng(0)
    occupied = rng.uniform(size=(rays, samples)) < 0.3
    sigma = jnp.asarray(rng.exponential(1.0, (rays, samples)) * occupied, jnp.float32)
    dists = jnp.full((rays, samples), 0.0118, jnp.float32)
    colour = jnp.asarray(rng.uniform(size=(rays, samples)), jnp.float32)
    out: dict[str, float] = {}
    for name, fn in (("cumsum", render.composite_cumsum), ("scan", render.composite_scan)):
        fwd = jax.jit(lambda s, d, fn=fn: fn(s, d, 25.0)[0], compiler_options=options)
        grad = jax.jit(
            jax.grad(lambda s, d, c, fn=fn: jnp.sum(fn(s, d, 25.0)[0] * c)), compiler_options=options
        )
        out[f"composite_{name}_fwd_ms"] = 1e3 * best_time(lambda f=fwd: f(sigma, dists), repeats)
        out[f"composite_{name}_fwdbwd_ms"] = 1e3 * best_time(lambda g=grad: g(sigma, dists, colour), repeats)
    return out


def bench_sampling(
    repeats: int, options: dict, points: int = 1_000_000, comps: int = 16, size: int = 128
) -> dict[str, float]:
    """One plane: channels-last gather table (grids.sample_plane) vs map_coordinates per channel."""
    key = jax.random.PRNGKey(0)
    plane = 0.1 * jax.random.normal(key, (size, size, comps))
    uv = jax.random.uniform(jax.random.PRNGKey(1), (points, 2), minval=-1, maxval=1)
    w = jax.random.normal(jax.random.PRNGKey(2), (points, comps))

    def table(p, q):
        return grids.sample_plane(p, q[:, 0], q[:, 1])

    def mapc(p, q):
        g = (q + 1.0) * (0.5 * (size - 1))
        per_channel = lambda ch: map_coordinates(ch, [g[:, 0], g[:, 1]], order=1, mode="constant", cval=0.0)
        return jax.vmap(per_channel, in_axes=-1, out_axes=-1)(p)

    err = float(jnp.max(jnp.abs(jax.jit(table)(plane, uv) - jax.jit(mapc)(plane, uv))))
    out: dict[str, float] = {"sampling_max_abs_diff": err}
    for name, fn in (("table", table), ("map_coordinates", mapc)):
        fwd = jax.jit(fn, compiler_options=options)
        grad = jax.jit(jax.grad(lambda p, q, c, fn=fn: jnp.sum(fn(p, q) * c)), compiler_options=options)
        out[f"sample_{name}_fwd_ms"] = 1e3 * best_time(lambda f=fwd: f(plane, uv), repeats)
        out[f"sample_{name}_fwdbwd_ms"] = 1e3 * best_time(lambda g=grad: g(plane, uv, w), repeats)
    return out


# --------------------------------------------------------------------------------------------------


def ball_field(cfg: ModelConfig, res: int, radius: float = 0.5) -> dict:
    """A VM-192 field, random as at initialisation, plus one density component A exp(-|x|^2 / s^2).

    With A = 40 and s chosen so the feature crosses the softplus shift (10) at ``radius``
    (normalised units), density is ~30 inside the ball and ~softplus(-10) outside: an opaque ball.
    """
    params = field.init_field(jax.random.PRNGKey(0), cfg, (res, res, res))
    s2 = radius**2 / np.log(40.0 / -cfg.density_shift)
    u = np.linspace(-1, 1, res)
    gauss = np.exp(-(u**2) / s2)
    plane = 40.0 * gauss[:, None] * gauss[None, :]
    planes = list(params["density"]["planes"])
    lines = list(params["density"]["lines"])
    planes[0] = planes[0].at[:, :, 0].set(jnp.asarray(plane, jnp.float32))
    lines[0] = lines[0].at[:, 0].set(jnp.asarray(gauss, jnp.float32))
    params["density"] = {"planes": tuple(planes), "lines": tuple(lines)}
    return params


def orbit_rays(n: int, seed: int, radius: float = 4.0, fov_deg: float = 40.0) -> tuple[jax.Array, jax.Array]:
    """Rays of random pixels of random cameras on a sphere, looking at the origin (Blender-like)."""
    rng = np.random.default_rng(seed)
    cams = rng.normal(size=(n, 3))
    cams = radius * cams / np.linalg.norm(cams, axis=-1, keepdims=True)
    forward = -cams / radius
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    true_up = np.cross(right, forward)
    half = np.tan(np.deg2rad(fov_deg) / 2)
    px = rng.uniform(-half, half, (n, 1))
    py = rng.uniform(-half, half, (n, 1))
    d = forward + px * right + py * true_up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return jnp.asarray(cams, jnp.float32), jnp.asarray(d, jnp.float32)


def bench_render(repeats: int, options: dict, res: int = 128, rays: int = 4096) -> dict[str, float]:
    cfg = ModelConfig()
    fns = render.tensorf_field_fns(cfg)
    params = ball_field(cfg, res)
    aabb = np.array([[-1.5] * 3, [1.5] * 3], np.float32)
    geo = raymarch.make_geometry(aabb, (res, res, res), distance_scale=cfg.distance_scale)
    t0 = time.perf_counter()
    mask = alpha_mask.compute_alpha_mask(fns, params, geo, (res, res, res))
    mask_s = time.perf_counter() - t0
    masked = raymarch.with_alpha_mask(geo, mask, geo.aabb)
    rays_o, rays_d = orbit_rays(rays, 0)
    target = jnp.full((rays, 3), 0.5, jnp.float32)
    key = jax.random.PRNGKey(0)

    # Everything is an argument: closed-over arrays would be constant-folded at compile time.
    def loss(p, g, ro, rd, tgt, k, db, cb):
        out = render.render_rays(fns, p, None, ro, rd, g, k, train=True, density_budget=db, colour_budget=cb)
        return jnp.mean((out["rgb"] - tgt) ** 2), out

    train_step = jax.jit(
        jax.value_and_grad(loss, has_aux=True), static_argnums=(6, 7), compiler_options=options
    )

    def _evaluate(p, g, ro, rd, db, cb):
        return render.render_rays(
            fns, p, None, ro, rd, g, None, train=False, density_budget=db, colour_budget=cb
        )

    evaluate_jit = jax.jit(_evaluate, static_argnums=(4, 5), compiler_options=options)

    def evaluate(g, db, cb):
        return evaluate_jit(params, g, rays_o, rays_d, db, cb)

    n_samples = rays * geo.n_samples
    out: dict[str, float] = {
        "alpha_mask_s": mask_s,
        "occupied_fraction": float(mask.mean()),
        "n_samples": geo.n_samples,
        "rays": rays,
    }
    reference = {"": evaluate(geo, None, None), "_mask": evaluate(masked, None, None)}
    out["density_fraction_aabb"] = int(reference[""]["density_count"]) / n_samples
    out["density_fraction_mask"] = int(reference["_mask"]["density_count"]) / n_samples
    out["colour_samples_per_ray"] = int(reference[""]["colour_count"]) / rays
    # The alpha mask itself (TensoRF's threshold on α without the distance scale) changes the image a
    # little where density ramps up softly; compaction must not change it at all.
    out["alpha_mask_max_rgb_diff"] = float(jnp.max(jnp.abs(reference["_mask"]["rgb"] - reference[""]["rgb"])))
    cases = {}
    for suffix, g in (("", geo), ("_mask", masked)):
        c = reference[suffix]
        cases["dense" + suffix] = (g, None, None, suffix)
        sizes = (
            budgets.ladder_budget(int(c["density_count"]) * 1.2),
            budgets.ladder_budget(int(c["colour_count"]) * 1.2),
        )
        cases["compact" + suffix] = (g, *sizes, suffix)
    for name, (g, db, cb, suffix) in cases.items():
        t_train = best_time(
            lambda g=g, db=db, cb=cb: train_step(params, g, rays_o, rays_d, target, key, db, cb), repeats
        )
        t_eval = best_time(lambda g=g, db=db, cb=cb: evaluate(g, db, cb), repeats)
        out[f"{name}_train_ms"] = 1e3 * t_train
        out[f"{name}_train_rays_per_s"] = rays / t_train
        out[f"{name}_eval_ms"] = 1e3 * t_eval
        out[f"{name}_eval_rays_per_s"] = rays / t_eval
        out[f"{name}_max_rgb_diff"] = float(
            jnp.max(jnp.abs(evaluate(g, db, cb)["rgb"] - reference[suffix]["rgb"]))
        )
    for suffix in ("", "_mask"):
        for phase in ("train", "eval"):
            out[f"compact{suffix}_{phase}_speedup"] = (
                out[f"dense{suffix}_{phase}_ms"] / out[f"compact{suffix}_{phase}_ms"]
            )
    out["compact_mask_vs_dense_train_speedup"] = out["dense_train_ms"] / out["compact_mask_train_ms"]
    out["compact_mask_vs_dense_eval_speedup"] = out["dense_eval_ms"] / out["compact_mask_eval_ms"]
    return out


def points_along_rays(key: jax.Array, rays: int, samples: int, res: int) -> jax.Array:
    """``[rays * samples, 3]`` points at half-voxel spacing along random rays through [-1, 1]^3."""
    k1, k2 = jax.random.split(key)
    o = jax.random.uniform(k1, (rays, 3), minval=-1, maxval=1)
    d = jax.random.normal(k2, (rays, 3))
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    t = (jnp.arange(samples) - samples / 2) * (1.0 / res)
    return jnp.clip(o[:, None] + d[:, None] * t[None, :, None], -1.02, 1.02).reshape(-1, 3)


def bench_density(repeats: int, options: dict) -> dict[str, float]:
    """``grid_volume.sample_vm_sum`` by method, grid size and point count."""
    out: dict[str, float] = {}
    for res in (128, 300):
        grid = grids.init_vm(jax.random.PRNGKey(0), (res, res, res), (16, 16, 16), 0.1)
        for points in (524_288, 1_572_864):
            xyz = points_along_rays(jax.random.PRNGKey(1), points // 384, 384, res)
            for method in ("gather", "volume", "auto"):
                fwd = jax.jit(
                    lambda g, x, m=method: grid_volume.sample_vm_sum(g, x, m), compiler_options=options
                )
                loss = lambda g, x, m=method: jnp.sum(jnp.sin(grid_volume.sample_vm_sum(g, x, m)))
                grad = jax.jit(jax.grad(loss), compiler_options=options)
                name = f"density_{method}_{res}^3_{points // 1000}k"
                out[f"{name}_fwd_ms"] = 1e3 * best_time(lambda f=fwd, g=grid, x=xyz: f(g, x), repeats)
                out[f"{name}_fwdbwd_ms"] = 1e3 * best_time(lambda f=grad, g=grid, x=xyz: f(g, x), repeats)
    return out


def bench_mlp(repeats: int, options: dict, points: int = 1 << 20) -> dict[str, float]:
    """MLP_Fea forward+backward at ``points`` points (f32, bf16 operands) and a large matmul's GFLOP/s."""
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    x = jax.random.normal(keys[0], (points, 150))
    shapes = [(150, 128), (128, 128), (128, 3)]
    weights = [0.1 * jax.random.normal(k, shape) for k, shape in zip(keys[1:], shapes, strict=True)]
    flops = 2 * points * (150 * 128 + 128 * 128 + 128 * 3)  # forward; backward about twice that

    def mlp(ws: list, h: jax.Array, dtype: jnp.dtype) -> jax.Array:
        for i, w in enumerate(ws):
            h = jnp.dot(h.astype(dtype), w.astype(dtype), preferred_element_type=jnp.float32)
            h = jax.nn.relu(h) if i < 2 else jax.nn.sigmoid(h)
        return jnp.sum(h)

    out: dict[str, float] = {"mlp_points": float(points)}
    for name, dtype in (("f32", jnp.float32), ("bf16", jnp.bfloat16)):
        grad = jax.jit(
            jax.grad(lambda ws, h, d=dtype: mlp(ws, h, d), argnums=(0, 1)), compiler_options=options
        )
        seconds = best_time(lambda g=grad: g(weights, x), repeats)
        out[f"mlp_{name}_fwdbwd_ms"] = 1e3 * seconds
        out[f"mlp_{name}_gflops"] = 3 * flops / seconds / 1e9
    a = jax.random.normal(keys[0], (4096, 4096))
    matmul = jax.jit(lambda p, q: p @ q, compiler_options=options)
    out["matmul_4096_f32_gflops"] = 2 * 4096**3 / best_time(lambda: matmul(a, a), repeats) / 1e9
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--res", type=int, default=128, help="grid resolution for the render benchmark")
    parser.add_argument("--rays", type=int, default=4096)
    parser.add_argument(
        "--only", choices=["compositing", "sampling", "density", "mlp", "render"], action="append"
    )
    parser.add_argument("--json", action="store_true", help="print one JSON line")
    parser.add_argument(
        "--xla-defaults",
        action="store_true",
        help="compile without xla_cpu.xla_compiler_options() (for comparison)",
    )
    args = parser.parse_args()
    options = {} if args.xla_defaults else xla_cpu.xla_compiler_options()
    parts = args.only or ["compositing", "sampling", "density", "mlp", "render"]
    results: dict[str, object] = {
        "jax": jax.__version__,
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "device": str(jax.devices()[0]),
        "repeats": args.repeats,
        "load_avg_1min": os.getloadavg()[0],
        "compiler_options": json.dumps(options),
        "glibc_tunables": os.environ.get("GLIBC_TUNABLES", ""),
    }
    if "compositing" in parts:
        results.update(bench_compositing(args.repeats, options))
    if "sampling" in parts:
        results.update(bench_sampling(args.repeats, options))
    if "density" in parts:
        results.update(bench_density(args.repeats, options))
    if "mlp" in parts:
        results.update(bench_mlp(args.repeats, options))
    if "render" in parts:
        results.update(bench_render(args.repeats, options, args.res, args.rays))
    if args.json:
        print(json.dumps(results))
        return
    for k, v in results.items():
        print(f"{k:36s} {v:.4g}" if isinstance(v, float) else f"{k:36s} {v}")


if __name__ == "__main__":
    main()
