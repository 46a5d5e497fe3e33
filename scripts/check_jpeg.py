"""Compare mnerf_jax's differentiable JPEG with Pillow's codec on natural photographs.

For each quality and each of scikit-image's bundled colour photographs, prints the PSNR (dB) between this
module's JPEG round trip and Pillow's (same quality, 4:2:0 subsampling), the PSNR of Pillow's output against
the original (for scale), and the gradient gain ``‖∇ₓ⟨jpeg(x), r⟩‖ / ‖r‖`` for a fixed random ``r`` (an
identity map gives 1; a zero gradient gives 0). Exits with status 1 if any PSNR is below ``--min-psnr`` or
any gradient is zero or not finite.

    python scripts/check_jpeg.py [--qualities 10 30 50 90] [--json]
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image
from skimage import data as skdata

try:
    from mnerf_jax.imaging.jpeg import jpeg
except ImportError:  # run from a checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from mnerf_jax.imaging.jpeg import jpeg

PHOTOS = ("astronaut", "coffee", "chelsea", "rocket")


def pillow_jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """Pillow JPEG round trip of a ``[H, W, 3]`` uint8 image → float32 in [0, 1]."""
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality, subsampling=2)
    buffer.seek(0)
    return np.asarray(Image.open(buffer).convert("RGB"), np.float32) / 255.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


@jax.jit
def _ours_and_gradient(x: jax.Array, quality: jax.Array, probe: jax.Array) -> tuple[jax.Array, jax.Array]:
    out, vjp = jax.vjp(lambda y: jpeg(y, quality), x)
    return out, vjp(probe)[0]


def measure(name: str, quality: int, seed: int = 0) -> dict[str, float | int | str]:
    image = getattr(skdata, name)()[..., :3]
    x = image.astype(np.float32) / 255.0
    probe = np.random.default_rng(seed).standard_normal(x.shape).astype(np.float32)
    ours, grad = _ours_and_gradient(jnp.asarray(x), jnp.float32(quality), jnp.asarray(probe))
    ours, grad = np.asarray(ours), np.asarray(grad)
    reference = pillow_jpeg(image, quality)
    return {
        "photo": name,
        "height": int(x.shape[0]),
        "width": int(x.shape[1]),
        "quality": int(quality),
        "psnr_vs_pillow_db": psnr(ours, reference),
        "pillow_psnr_vs_original_db": psnr(reference, x),
        "gradient_gain": float(np.linalg.norm(grad) / np.linalg.norm(probe)),
        "gradient_finite": bool(np.isfinite(grad).all()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--qualities", type=int, nargs="+", default=[10, 30, 50, 90])
    parser.add_argument("--photos", nargs="+", default=list(PHOTOS))
    parser.add_argument("--min-psnr", type=float, default=30.0, help="acceptance threshold in dB")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of a table")
    args = parser.parse_args(argv)

    rows = [measure(name, q) for q in args.qualities for name in args.photos]
    ok = all(
        r["psnr_vs_pillow_db"] >= args.min_psnr and r["gradient_finite"] and r["gradient_gain"] > 0
        for r in rows
    )
    if args.json:
        print(json.dumps({"min_psnr_db": args.min_psnr, "pass": ok, "rows": rows}, indent=2))
    else:
        header = ("photo", "size", "q", "PSNR vs Pillow", "Pillow vs orig", "grad gain")
        print("{:<10} {:>9} {:>3} {:>15} {:>15} {:>10}".format(*header))
        for r in rows:
            size = f"{r['height']}x{r['width']}"
            print(
                f"{r['photo']:<10} {size:>9} {r['quality']:>3} {r['psnr_vs_pillow_db']:>12.2f} dB"
                f" {r['pillow_psnr_vs_original_db']:>12.2f} dB {r['gradient_gain']:>10.4f}"
            )
        verdict = "PASS" if ok else "FAIL"
        print(f"{verdict}: every PSNR vs Pillow >= {args.min_psnr} dB and every gradient non-zero")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
