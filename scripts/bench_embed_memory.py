"""Peak memory of embedding steps at several image sizes: deferred back-propagation vs the direct gradient.

    python scripts/bench_embed_memory.py --run RUN [--sizes 128 256 512] [--patch 64] [--steps 2]
                                         [--modes deferred direct] [--json]

RUN is a fitted TensoRF (``mnerf fit``, or ``DIR/run`` after ``mnerf demo --out DIR``). Its first training
camera is rescaled to each image side (same field of view), the watermark modules are added as ``mnerf embed``
adds them (4 IDs × 16 bits, random-init decoder) and ``--steps`` phase-2 steps run on that view:

- ``deferred``: ``wm_step.embed_step``, the path ``mnerf embed`` takes (the image is rendered without a graph,
  then square patches of ``--patch`` px are re-rendered one at a time with ``jax.vjp``);
- ``direct``: ``jax.grad`` of ``deferred.direct_objective``: the same loss with every patch on the graph.

Every (mode, size) runs in its own process, so each peak RSS (``ru_maxrss``) is that configuration's alone;
``base_rss_mb`` is the RSS after loading the run, before the first step. Deferred memory should stay nearly
flat as the image grows (only image-sized buffers and the decoder's activations grow); direct memory grows
with the number of pixels.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def child(run: str, size: int, patch: int, steps: int, mode: str) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mnerf_jax.data.rays import camera_rays
    from mnerf_jax.reader import decoder as decoder_lib
    from mnerf_jax.reader import keys as keys_lib
    from mnerf_jax.tensorf import budgets
    from mnerf_jax.watermark import deferred, embed
    from mnerf_jax.watermark import model as watermark
    from mnerf_jax.watermark import step as wm_step

    source = embed.load_source(run)
    config = embed.resolve_config(
        source, None, [f"watermark.schedule.patch_size={patch}"], num_ids=4, bits=16
    )
    cfg = config.watermark
    cams = source.load_scene(None, splits=("train",)).split("train").cameras
    k = size / cams.width
    height = int(round(cams.height * k))
    cams = dataclasses.replace(
        cams, fx=cams.fx * k, fy=cams.fy * k, cx=cams.cx * k, cy=cams.cy * k, width=size, height=height
    )
    rays_o, rays_d = camera_rays(cams, 0)
    layout = deferred.patch_layout(
        height, size, deferred.tiling_patch_size(height, size, cfg.schedule.patch_size, 11)
    )
    index, owner = jnp.asarray(layout.index), jnp.asarray(layout.owner)
    root = jax.random.key(0)
    params = watermark.add_watermark(jax.random.fold_in(root, 1), source.params, cfg, 4)
    dec = decoder_lib.init_decoder(jax.random.PRNGKey(0), 16)
    dec_vars = dict(dec)
    tx = wm_step.make_optimizer(cfg, config.train.adam_b1, config.train.adam_b2)
    state = wm_step.EmbedState(
        params=params,
        decoder=dec_vars,
        opt_state=tx.init({"field": params, "decoder": dec_vars["params"]}),
        step=jnp.zeros((), jnp.int32),
        key=jax.random.fold_in(root, 2),
    )
    keys = jnp.asarray(np.random.default_rng(0).integers(0, 2, (4, 16)), jnp.float32)  # the 4 IDs' messages
    batch = {
        "rays_o": jnp.asarray(rays_o),
        "rays_d": jnp.asarray(rays_d),
        "target": jnp.full((height * size, 3), 0.5, jnp.float32),
        "message": keys[1:2],
        "id": jnp.asarray([1], jnp.int32),
        "keys": keys,
        "null": jnp.asarray(keys_lib.null_message(np.asarray(keys)), jnp.float32),
    }
    geometry = source.geometry
    policy = budgets.BudgetPolicy()
    site, n_rays, n_samples = "bench", layout.size**2, geometry.n_samples

    def spec() -> wm_step.StepSpec:
        db, cb = policy.budgets(site, n_rays, n_samples)
        return wm_step.StepSpec(
            model=config.model,
            wm=cfg,
            adam_b1=config.train.adam_b1,
            adam_b2=config.train.adam_b2,
            phase=2,
            height=height,
            width=size,
            density_budget=db,
            colour_budget=cb,
        )

    total = jnp.asarray(wm_step.total_steps(cfg), jnp.int32)
    base = _rss_mb()
    start = time.perf_counter()
    if mode == "deferred":
        done = 0
        while done < steps:
            new_state, metrics = wm_step.embed_step(
                state, geometry, batch, index, owner, None, total, spec=spec()
            )
            counts = {k: int(metrics[k]) for k in ("density_count", "colour_count")}
            if not policy.update(site, counts, n_rays, n_samples):
                state, done = new_state, done + 1
    else:
        # Budgets from a forward-only pass (patch by patch, small), then the direct gradient.
        while True:
            s = spec()
            fn = wm_step.render_patch_fn(s, geometry, batch["id"])
            rays = (batch["rays_o"], batch["rays_d"])
            key = jax.random.key(3)
            _, stats = deferred.render_image(fn, state.params, rays, index, owner, key, height, size)
            if not policy.update(site, {k: int(v) for k, v in stats.items()}, n_rays, n_samples):
                break
        s = spec()
        fn = wm_step.render_patch_fn(s, geometry, batch["id"])
        target = batch["target"].reshape(height, size, 3)
        image_loss = wm_step.make_image_loss(
            s,
            jax.random.key(4),
            batch["message"],
            target,
            dec_vars,
            keys=batch["keys"],
            ids=batch["id"],
            null=batch["null"],
        )

        @jax.jit
        def direct(params: dict, dec_params: dict) -> tuple:
            def objective(p: dict, d: dict) -> jax.Array:
                loss, _ = deferred.direct_objective(
                    fn,
                    image_loss,
                    lambda r, t: objective.patch_loss(cfg, r, t),
                    p,
                    d,
                    (batch["rays_o"], batch["rays_d"]),
                    batch["target"],
                    index,
                    owner,
                    jax.random.key(5),
                    height,
                    size,
                )
                return loss

            return jax.grad(objective, argnums=(0, 1))(params, dec_params)

        for _ in range(steps):
            jax.block_until_ready(direct(state.params, dec_vars["params"]))
    seconds = time.perf_counter() - start
    return {
        "mode": mode,
        "image": f"{height}x{size}",
        "pixels": height * size,
        "patch": layout.size,
        "patches": int(layout.index.shape[0]),
        "steps": steps,
        "seconds": round(seconds, 2),
        "base_rss_mb": round(base),
        "peak_rss_mb": round(_rss_mb()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", required=True, help="a fitted TensoRF run (mnerf fit)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="image sides (px)")
    parser.add_argument("--patch", type=int, default=64, help="patch side (px) of the deferred path")
    parser.add_argument("--steps", type=int, default=2, help="steps per configuration (after compilation)")
    parser.add_argument("--modes", nargs="+", default=["deferred", "direct"], choices=["deferred", "direct"])
    parser.add_argument("--json", action="store_true", help="one JSON object per configuration")
    parser.add_argument("--child", nargs=2, metavar=("MODE", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        mode, size = args.child
        print(json.dumps(child(args.run, int(size), args.patch, args.steps, mode)))
        return
    for mode in args.modes:
        for size in args.sizes:
            cmd = [
                sys.executable,
                __file__,
                "--run",
                args.run,
                "--patch",
                str(args.patch),
                "--steps",
                str(args.steps),
                "--child",
                mode,
                str(size),
            ]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
            if proc.returncode != 0 or not lines:
                tail = proc.stderr.strip().splitlines()[-1:] or ["(no output)"]
                row = {"mode": mode, "image": f"{size}", "error": tail[0]}
            else:
                row = json.loads(lines[-1])
            if args.json:
                print(json.dumps(row), flush=True)
            elif "error" in row:
                print(f"{mode:9s} {size:>5d} px  failed: {row['error']}", flush=True)
            else:
                print(
                    f"{mode:9s} {row['image']:>9s} ({row['patches']} patches of {row['patch']}²): peak RSS "
                    f"{row['peak_rss_mb']:,} MB (after loading {row['base_rss_mb']:,} MB), "
                    f"{row['seconds']} s for {row['steps']} steps",
                    flush=True,
                )


if __name__ == "__main__":
    main()
