"""Convert a PyTorch HiDDeN decoder (stable-signature / WateRF TorchScript or torch.save zip), without torch.

The archive is read by :func:`mnerf_jax.core.torch_state.read_torch_zip` (a restricted unpickler: no
code in the file runs).

The module tree (TorchScript) or state dict (``torch.save``) is flattened to dotted names in registration
order (``0.layers.3.layers.0.weight`` for stable-signature's whitened ``Sequential(HiddenDecoder, Linear)``).
The mapping to Flax is by structure, not by names: the 4-D weights in order are the convolutions (OIHW →
HWIO), the modules holding ``running_mean`` in order are the BatchNorms (eps 1e-3, as HiDDeN builds them:
TorchScript keeps ``eps`` in code, not data), the first 2-D weight is ``linear`` and a second one, if
present, is the whitening layer (absent: identity).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.torch_state import read_torch_zip
from mnerf_jax.reader import decoder_io

__all__ = ["convert_torchscript_decoder", "read_torch_zip", "state_dict_to_variables"]


def state_dict_to_variables(state: Mapping[str, np.ndarray]) -> tuple[dict[str, Any], bool]:
    """Map a HiDDeN decoder state dict (any naming, registration order) to Flax variables.

    Returns ``(variables, has_whitening)``. Raises MnerfError when the tensors do not form a HiDDeN decoder.
    """
    convs = [(k[: -len("weight")], v) for k, v in state.items() if k.endswith("weight") and v.ndim == 4]
    bns = [k[: -len("running_mean")] for k in state if k.endswith("running_mean")]
    linears = [(k[: -len("weight")], v) for k, v in state.items() if k.endswith("weight") and v.ndim == 2]
    if len(convs) < 2 or len(convs) != len(bns):
        raise MnerfError(f"not a HiDDeN decoder: {len(convs)} convolutions and {len(bns)} BatchNorm layers")
    if not 1 <= len(linears) <= 2:
        raise MnerfError(f"not a HiDDeN decoder: expected 1 or 2 linear layers, found {len(linears)}")
    bits = int(convs[-1][1].shape[0])
    channels = int(convs[0][1].shape[0])
    depth = len(convs) - 1
    params: dict[str, Any] = {}
    stats: dict[str, Any] = {}
    for i, ((cprefix, weight), bprefix) in enumerate(zip(convs, bns, strict=True)):
        if weight.shape[2:] != (3, 3):
            raise MnerfError(f"{cprefix}weight: expected 3×3 kernels, got {weight.shape}")
        bias = state.get(f"{cprefix}bias", np.zeros(weight.shape[0], np.float32))
        block = {
            "conv": {"kernel": weight.transpose(2, 3, 1, 0), "bias": bias},
            "bn": {
                "scale": state.get(f"{bprefix}weight", np.ones(weight.shape[0], np.float32)),
                "bias": state.get(f"{bprefix}bias", np.zeros(weight.shape[0], np.float32)),
            },
        }
        params[f"block_{i}"] = block
        stats[f"block_{i}"] = {
            "bn": {"mean": state[f"{bprefix}running_mean"], "var": state[f"{bprefix}running_var"]}
        }
    (lprefix, lweight) = linears[0]
    params["linear"] = {"kernel": lweight.T, "bias": state.get(f"{lprefix}bias", np.zeros(bits, np.float32))}
    if len(linears) == 2:
        (wprefix, wweight) = linears[1]
        params["whiten"] = {
            "kernel": wweight.T,
            "bias": state.get(f"{wprefix}bias", np.zeros(bits, np.float32)),
        }
    else:
        params["whiten"] = {"kernel": np.eye(bits, dtype=np.float32), "bias": np.zeros(bits, np.float32)}
    variables = {"params": params, "batch_stats": stats}
    expected = decoder_io._expected_shapes(bits, channels, depth)
    for name, value in decoder_io._flatten(variables).items():
        if name not in expected or tuple(value.shape) != expected[name]:
            raise MnerfError(
                f"not a HiDDeN decoder: {name} has shape {tuple(value.shape)}, expected {expected.get(name)}"
            )
    variables = jax.tree.map(lambda a: jnp.asarray(np.asarray(a, np.float32)), variables)
    return variables, len(linears) == 2


def convert_torchscript_decoder(
    zip_path: str | Path, out_path: str | Path, wavelet: str = "bior4.4"
) -> dict[str, Any]:
    """Convert a stable-signature / WateRF decoder zip (TorchScript or torch.save) to an mnerf decoder file.

    The result is read with :func:`mnerf_jax.reader.decoder_io.load_decoder`. ``wavelet`` is recorded as the
    sub-band the decoder reads (WateRF feeds it LL2 of ``bior4.4``). Returns the written metadata.
    """
    state = read_torch_zip(zip_path)
    variables, whitened = state_dict_to_variables(state)
    meta = {
        "whitened": whitened,
        "training": {"recipe": "converted", "source": Path(zip_path).name, "tensors": len(state)},
    }
    return decoder_io.save_decoder(out_path, variables, meta, wavelet=wavelet)
