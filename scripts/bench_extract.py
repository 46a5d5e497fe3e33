"""Extraction throughput: images/s of image → LL2 → HiDDeN decoder, JAX beside PyTorch, on this machine.

    python scripts/bench_extract.py [--bits 16] [--repeats 5] [--sizes 100 200 800] [--batches 1 32] [--json]

Each row is one (image side, batch) pair: JAX (``reader.extract.decode``, jitted, eval mode) and the same
decoder with the same weights in PyTorch (eval mode, ``torch.inference_mode``, LL2 as the same two matrix
products), both timed best-of-``repeats`` after a warm-up call. PyTorch is imported here only; without it the
PyTorch column is skipped with a message. ``--json`` prints one JSON object per row.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io, dwt, extract


def best_of(fn: Callable[[], object], repeats: int, min_time: float = 0.2) -> float:
    """Best seconds per call over ``repeats`` timings (each repeats the call until ``min_time`` passes)."""
    fn()  # warm-up / compile
    time.sleep(0.5)  # let the other library's idle worker threads stop spinning
    best = float("inf")
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while True:
            fn()
            calls += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_time:
                break
        best = min(best, elapsed / calls)
    return best


def jax_runner(variables: dict, images: np.ndarray, wavelet: str) -> Callable[[], object]:
    x = jnp.asarray(images)
    return lambda: extract.decode(variables, x, wavelet, batch_size=images.shape[0]).block_until_ready()


def torch_runner(torch, variables: dict, images: np.ndarray, wavelet: str) -> Callable[[], object]:  # noqa: ANN001
    """The HiDDeN decoder in PyTorch (NCHW) with the same weights, plus LL2 as two matrix products."""
    nn = torch.nn
    params, stats = variables["params"], variables["batch_stats"]
    bits, channels, depth = dec.architecture(variables)
    layers: list = []
    cin = 3
    for i in range(depth + 1):
        cout = channels if i < depth else bits
        conv = nn.Conv2d(cin, cout, 3, padding=1)
        bn = nn.BatchNorm2d(cout, eps=1e-3)
        p, s = params[f"block_{i}"], stats[f"block_{i}"]
        conv.weight.data = torch.from_numpy(np.asarray(p["conv"]["kernel"]).transpose(3, 2, 0, 1).copy())
        conv.bias.data = torch.from_numpy(np.asarray(p["conv"]["bias"]).copy())
        bn.weight.data = torch.from_numpy(np.asarray(p["bn"]["scale"]).copy())
        bn.bias.data = torch.from_numpy(np.asarray(p["bn"]["bias"]).copy())
        bn.running_mean = torch.from_numpy(np.asarray(s["bn"]["mean"]).copy())
        bn.running_var = torch.from_numpy(np.asarray(s["bn"]["var"]).copy())
        layers += [conv, bn, nn.GELU()]
        cin = cout
    linear, whiten = nn.Linear(bits, bits), nn.Linear(bits, bits)
    for layer, name in ((linear, "linear"), (whiten, "whiten")):
        layer.weight.data = torch.from_numpy(np.asarray(params[name]["kernel"]).T.copy())
        layer.bias.data = torch.from_numpy(np.asarray(params[name]["bias"]).copy())
    body = nn.Sequential(*layers).eval()
    h, w = images.shape[1:3]
    a_h = torch.from_numpy(dwt.ll2_matrix(h, wavelet).copy())
    a_w = torch.from_numpy(dwt.ll2_matrix(w, wavelet).copy())
    x = torch.from_numpy(images.transpose(0, 3, 1, 2).copy())

    def run() -> object:
        with torch.inference_mode():
            ll2 = torch.einsum("ph,bchw,qw->bcpq", a_h, x, a_w)
            return whiten(linear(body(ll2).mean(dim=(2, 3))))

    # The two implementations must agree before their speeds are compared.
    ours = np.asarray(extract.decode(variables, images, wavelet, batch_size=images.shape[0]))
    theirs = run().numpy()
    if not np.allclose(ours, theirs, rtol=1e-3, atol=1e-3):
        raise SystemExit(f"JAX and PyTorch disagree (max |Δ| = {np.abs(ours - theirs).max():.2e})")
    return run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bits", type=int, default=16, help="shipped decoder to time (8, 16, 32 or 48)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 200, 800], help="image sides (pixels)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32], help="batch sizes")
    parser.add_argument("--repeats", type=int, default=5, help="timings per row; the best is kept")
    parser.add_argument("--json", action="store_true", help="one JSON object per row")
    args = parser.parse_args(argv)

    loaded = decoder_io.load_shipped_decoder(args.bits)
    try:
        import torch

        torch.set_num_threads(os.cpu_count() or 1)
        torch_version = torch.__version__
    except ImportError:
        torch = None
        torch_version = None
        print("PyTorch is not installed: the PyTorch column is skipped", file=sys.stderr)
    header = {
        "jax": jax.__version__,
        "torch": torch_version,
        "backend": jax.default_backend(),
        "cpus": os.cpu_count(),
        "decoder_bits": args.bits,
    }
    if not args.json:
        print(" ".join(f"{k}={v}" for k, v in header.items()))
        print(f"{'image':>9} {'LL2':>9} {'batch':>5} {'JAX img/s':>10} {'torch img/s':>12} {'JAX/torch':>9}")
    rng = np.random.default_rng(0)
    for size in args.sizes:
        h2, w2 = dwt.ll2_shape(size, size, loaded.wavelet)
        for batch in args.batches:
            images = rng.uniform(0, 1, (batch, size, size, 3)).astype(np.float32)
            torch_s = None
            if torch is not None:
                torch_s = best_of(torch_runner(torch, loaded.variables, images, loaded.wavelet), args.repeats)
            jax_s = best_of(jax_runner(loaded.variables, images, loaded.wavelet), args.repeats)
            row = {
                "image": f"{size}x{size}",
                "ll2": f"{h2}x{w2}",
                "batch": batch,
                "jax_images_per_s": round(batch / jax_s, 2),
                "torch_images_per_s": None if torch_s is None else round(batch / torch_s, 2),
                "jax_over_torch": None if torch_s is None else round(torch_s / jax_s, 2),
                **header,
            }
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                t = "-" if torch_s is None else f"{row['torch_images_per_s']:.1f}"
                r = "-" if torch_s is None else f"{row['jax_over_torch']:.2f}x"
                print(
                    f"{row['image']:>9} {row['ll2']:>9} {batch:>5} {row['jax_images_per_s']:>10.1f} {t:>12} "
                    f"{r:>9}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
