"""Convert a PyTorch HiDDeN decoder (stable-signature / WateRF TorchScript or torch.save zip), without torch.

A PyTorch zip archive holds ``<root>/data.pkl`` (a pickle whose tensors refer to storages by persistent
id) and ``<root>/data/<key>`` (each storage's raw little-endian bytes). The pickle is read with a restricted
unpickler that knows only what such a file needs:

- ``torch._utils._rebuild_tensor_v2`` / ``_rebuild_tensor`` / ``_rebuild_parameter`` → NumPy arrays (copies of
  strided views into the storage bytes);
- ``torch.<Dtype>Storage`` → the storage's NumPy dtype; ``collections.OrderedDict`` → ``dict``;
- ``__torch__.*`` classes (TorchScript modules) → plain attribute holders;
- ``torch.jit._pickle`` list builders → lists.

Any other global (``os.system``, ``builtins.eval``, ...) is refused, so a hostile file cannot run code.

The module tree (TorchScript) or state dict (``torch.save``) is flattened to dotted names in registration
order (``0.layers.3.layers.0.weight`` for stable-signature's whitened ``Sequential(HiddenDecoder, Linear)``).
The mapping to Flax is by structure, not by names: the 4-D weights in order are the convolutions (OIHW →
HWIO), the modules holding ``running_mean`` in order are the BatchNorms (eps 1e-3, as HiDDeN builds them:
TorchScript keeps ``eps`` in code, not data), the first 2-D weight is ``linear`` and a second one, if
present, is the whitening layer (absent: identity).
"""

from __future__ import annotations

import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import decoder_io

_STORAGE_DTYPES = {
    "FloatStorage": np.float32,
    "DoubleStorage": np.float64,
    "HalfStorage": np.float16,
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class ScriptObject:
    """A TorchScript module or object from the pickle: its class name and attribute dict."""

    torch_class = "__torch__.object"

    def __setstate__(self, state: Any) -> None:
        self.__dict__["_state"] = state if isinstance(state, dict) else {"state": state}

    @property
    def attributes(self) -> dict[str, Any]:
        return self.__dict__.get("_state", {})


class _StorageType:
    def __init__(self, name: str):
        self.name = name
        self.dtype = np.dtype(_STORAGE_DTYPES[name])


def _rebuild_tensor(storage: np.ndarray, offset: int, size: tuple, stride: tuple, *_: Any) -> np.ndarray:
    size = tuple(int(s) for s in size)
    stride = tuple(int(s) for s in stride)
    count = int(np.prod(size)) if size else 1
    if count == 0:
        return np.zeros(size, storage.dtype)
    last = offset + sum((n - 1) * s for n, s in zip(size, stride, strict=True))
    if offset < 0 or last >= storage.size or any(s < 0 for s in stride):
        raise MnerfError("tensor reaches outside its storage (corrupt file)")
    view = np.lib.stride_tricks.as_strided(
        storage[offset:], shape=size, strides=tuple(s * storage.itemsize for s in stride)
    )
    return np.array(view)


class _StateDict(dict):
    """``collections.OrderedDict`` stand-in; ``torch.save`` state dicts carry a ``_metadata`` attribute."""

    def __setstate__(self, state: Any) -> None:
        self.__dict__["_state"] = state


def _rebuild_parameter(data: Any, *_: Any) -> Any:
    return data


def _restore_type_tag(value: Any, *_: Any) -> Any:
    return value


def _build_list(values: Any) -> list:
    return list(values)


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: Any, archive: zipfile.ZipFile, root: str, byteorder: str):
        super().__init__(file)
        self._archive = archive
        self._root = root
        self._byteorder = byteorder
        self._storages: dict[str, np.ndarray] = {}

    def find_class(self, module: str, name: str) -> Any:
        if module == "torch._utils" and name in ("_rebuild_tensor_v2", "_rebuild_tensor"):
            return _rebuild_tensor
        if module == "torch._utils" and name == "_rebuild_parameter":
            return _rebuild_parameter
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        if module == "collections" and name == "OrderedDict":
            return _StateDict
        if module == "torch.jit._pickle" and name == "restore_type_tag":
            return _restore_type_tag
        if module == "torch.jit._pickle" and name.startswith("build_") and name.endswith("list"):
            return _build_list
        if module.startswith("__torch__"):
            return type(name, (ScriptObject,), {"torch_class": f"{module}.{name}"})
        raise MnerfError(f"refusing to load {module}.{name} from the pickle (not a tensor or module type)")

    def persistent_load(self, pid: Any) -> np.ndarray:
        if not (isinstance(pid, tuple) and len(pid) >= 5 and pid[0] == "storage"):
            raise MnerfError(f"unsupported persistent id {pid!r} in the pickle")
        storage_type, key, _location, numel = pid[1], str(pid[2]), pid[3], int(pid[4])
        if not isinstance(storage_type, _StorageType):
            raise MnerfError(f"unsupported storage type {storage_type!r}")
        if key not in self._storages:
            name = f"{self._root}data/{key}"
            try:
                raw = self._archive.read(name)
            except KeyError:
                raise MnerfError(f"storage {name} is missing from the archive") from None
            dtype = storage_type.dtype.newbyteorder("<" if self._byteorder == "little" else ">")
            if len(raw) < numel * dtype.itemsize:
                raise MnerfError(f"storage {name} is truncated ({len(raw)} bytes for {numel} values)")
            self._storages[key] = np.frombuffer(raw, dtype, count=numel).astype(storage_type.dtype)
        return self._storages[key]


def read_torch_zip(zip_path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a PyTorch zip archive as ``{dotted name: array}`` in registration order (no torch)."""
    zip_path = Path(zip_path)
    if not zip_path.is_file():
        raise MnerfError(f"{zip_path} does not exist")
    try:
        with zipfile.ZipFile(zip_path) as archive:
            names = archive.namelist()
            pickles = sorted(n for n in names if n.endswith("/data.pkl") and n.count("/") == 1)
            if not pickles:
                raise MnerfError(f"{zip_path} is not a PyTorch zip archive (no <root>/data.pkl)")
            root = pickles[0][: -len("data.pkl")]
            byteorder = "little"
            if f"{root}byteorder" in names:
                byteorder = archive.read(f"{root}byteorder").decode().strip() or "little"
            with archive.open(pickles[0]) as file:
                obj = _RestrictedUnpickler(file, archive, root, byteorder).load()
    except zipfile.BadZipFile as err:
        raise MnerfError(f"{zip_path} is not a readable zip archive ({err})") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as err:
        raise MnerfError(f"{zip_path}: unreadable pickle ({type(err).__name__}: {err})") from None
    flat: dict[str, np.ndarray] = {}
    _flatten_tree(obj, "", flat)
    if not flat:
        raise MnerfError(f"{zip_path} holds no tensors")
    return flat


def _flatten_tree(obj: Any, prefix: str, out: dict[str, np.ndarray]) -> None:
    if isinstance(obj, np.ndarray):
        out[prefix.rstrip(".")] = obj
    elif isinstance(obj, ScriptObject):
        _flatten_tree(obj.attributes, prefix, out)
    elif isinstance(obj, Mapping):
        for key, value in obj.items():
            _flatten_tree(value, f"{prefix}{key}.", out)


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
