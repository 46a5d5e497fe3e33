"""CompressAI's bmshj2018-factorized and cheng2020 codecs in JAX, with small random weights the tests make.

Weights files are written in ``torch.save``'s zip format without torch: ``archive/data.pkl`` is pickled by a
``pickle._Pickler`` whose stand-ins for torch's globals write torch's names (``GLOBAL torch._utils
_rebuild_tensor_v2``, ``torch FloatStorage``) and whose ``persistent_id`` emits the tuples torch writes,
``("storage", torch.FloatStorage, key, "cpu", numel)``; the storages are ``archive/data/<key>``, raw
little-endian. The layers are checked against brute-force NumPy references of PyTorch's definitions.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
import zipfile
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.core.torch_state import read_state_dict
from mnerf_jax.imaging import attack_suites as S
from mnerf_jax.imaging import compression_models as C

# -------------------------------------------------------------------------- torch.save's zip, written here


class _TorchGlobal:
    """A stand-in the pickler writes as ``GLOBAL module name`` (``torch_name``)."""

    torch_name: tuple[str, str] = ("", "")


class RebuildTensorV2(_TorchGlobal):
    torch_name = ("torch._utils", "_rebuild_tensor_v2")


_STORAGE_CLASSES = {
    np.dtype(dt): type(name, (_TorchGlobal,), {"torch_name": ("torch", name)})
    for dt, name in (
        (np.float32, "FloatStorage"),
        (np.float16, "HalfStorage"),
        (np.float64, "DoubleStorage"),
        (np.int32, "IntStorage"),
        (np.int64, "LongStorage"),
    )
}


class Storage:
    """A storage: its key and flat contents (written to ``archive/data/<key>``)."""

    def __init__(self, key: str, flat: np.ndarray):
        self.key, self.flat = key, flat


class Tensor:
    """A tensor as ``Tensor.__reduce_ex__`` pickles it: ``_rebuild_tensor_v2(storage, offset, size, stride,
    requires_grad, backward_hooks)``."""

    def __init__(self, storage: Storage, offset: int, size: tuple, stride: tuple):
        self.args = (storage, offset, size, stride, False, collections.OrderedDict())

    def __reduce__(self) -> tuple:
        return (RebuildTensorV2, self.args)


class TorchPickler(pickle._Pickler):  # the Python pickler: its save_global can be replaced
    def persistent_id(self, obj: object) -> tuple | None:
        if isinstance(obj, Storage):
            return ("storage", _STORAGE_CLASSES[obj.flat.dtype], obj.key, "cpu", int(obj.flat.size))
        return None

    def save_global(self, obj: object, name: str | None = None) -> None:
        if isinstance(obj, type) and issubclass(obj, _TorchGlobal):
            module, qualname = obj.torch_name
            self.write(pickle.GLOBAL + f"{module}\n{qualname}\n".encode())
            self.memoize(obj)
        else:
            super().save_global(obj, name)

    dispatch = dict(pickle._Pickler.dispatch)
    dispatch[type] = save_global


def contiguous_tensors(state: dict, storages: list[Storage]) -> dict:
    """``state`` (nested dicts of arrays) with each array a tensor over a storage of its own."""
    out = collections.OrderedDict()
    for key, value in state.items():
        if isinstance(value, dict):
            out[key] = contiguous_tensors(value, storages)
        else:
            a = np.ascontiguousarray(value)
            storage = Storage(str(len(storages)), a.reshape(-1))
            storages.append(storage)
            strides = tuple(s // a.itemsize for s in a.strides) if a.ndim else ()
            out[key] = Tensor(storage, 0, a.shape, strides)
    return out


def write_torch_zip(path: Path, obj: object, storages: list[Storage]) -> None:
    buffer = io.BytesIO()
    TorchPickler(buffer, protocol=2).dump(obj)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", buffer.getvalue())
        z.writestr("archive/byteorder", "little")
        for s in storages:
            z.writestr(f"archive/data/{s.key}", s.flat.astype(s.flat.dtype.newbyteorder("<")).tobytes())
        z.writestr("archive/version", "3\n")


class StorageView:
    """``size`` values of ``root`` from ``offset``: a legacy file's storage view."""

    def __init__(self, key: str, root: Storage, offset: int, size: int):
        self.key, self.root, self.offset, self.size = key, root, offset, size


class LegacyPickler(TorchPickler):
    """Persistent ids as torch's legacy format writes them: ``(..., root numel, view metadata)``."""

    def persistent_id(self, obj: object) -> tuple | None:
        if isinstance(obj, Storage):
            return ("storage", _STORAGE_CLASSES[obj.flat.dtype], obj.key, "cpu", int(obj.flat.size), None)
        if isinstance(obj, StorageView):
            root = obj.root
            kind = _STORAGE_CLASSES[root.flat.dtype]
            return ("storage", kind, root.key, "cpu", int(root.flat.size), (obj.key, obj.offset, obj.size))
        return None


def write_torch_legacy(path: Path, obj: object, storages: list[Storage]) -> None:
    """torch's legacy ``torch.save``: magic number, protocol, system info, the object, the sorted storage
    keys, then each storage as an int64 count and its values."""
    buffer = io.BytesIO()
    sys_info = {
        "protocol_version": 1001,
        "little_endian": True,
        "type_sizes": {"short": 2, "int": 4, "long": 4},
    }
    for record in (0x1950A86A20F9469CFC6C, 1001, sys_info):
        pickle.dump(record, buffer, protocol=2)
    LegacyPickler(buffer, protocol=2).dump(obj)
    keys = sorted(s.key for s in storages)
    pickle.dump(keys, buffer, protocol=2)
    by_key = {s.key: s for s in storages}
    for key in keys:
        flat = by_key[key].flat
        buffer.write(struct.pack("<q", flat.size) + flat.astype(flat.dtype.newbyteorder("<")).tobytes())
    path.write_bytes(buffer.getvalue())


def save_state_dict(path: Path, state: dict) -> Path:
    storages: list[Storage] = []
    write_torch_zip(path, contiguous_tensors(state, storages), storages)
    return path


# --------------------------------------------------------------------------- small random CompressAI models


def _conv_weights(rng: np.random.Generator, out: int, inp: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    w = rng.normal(0, 1 / np.sqrt(inp * k * k), (out, inp, k, k)).astype(np.float32)
    return w, rng.normal(0, 0.05, out).astype(np.float32)


def _gdn_weights(rng: np.random.Generator, c: int) -> tuple[np.ndarray, np.ndarray]:
    """Stored (reparametrised) beta and gamma, a few below the lower bound."""
    beta = rng.uniform(0.6, 1.4, c).astype(np.float32)
    gamma = (np.abs(rng.normal(0, 0.05, (c, c))) + 0.3 * np.eye(c)).astype(np.float32)
    gamma[0, -1] = -0.2  # bounded to 2⁻¹⁸: weight 0
    return beta, gamma


def _add_conv(state: dict, rng: np.random.Generator, name: str, out: int, inp: int, k: int) -> None:
    state[f"{name}.weight"], state[f"{name}.bias"] = _conv_weights(rng, out, inp, k)


def _add_gdn(state: dict, rng: np.random.Generator, name: str, c: int) -> None:
    state[f"{name}.beta"], state[f"{name}.gamma"] = _gdn_weights(rng, c)
    # CompressAI's buffers, in every real state dict (the model recomputes them).
    state[f"{name}.beta_reparam.pedestal"] = np.array([C.PEDESTAL], np.float32)
    state[f"{name}.beta_reparam.lower_bound.bound"] = np.array([(1e-6 + C.PEDESTAL) ** 0.5], np.float32)


def random_factorized(rng: np.random.Generator, n: int = 8, m: int = 12) -> dict:
    state: dict = {}
    for i, (cin, cout) in enumerate([(3, n), (n, n), (n, n), (n, m)]):
        _add_conv(state, rng, f"g_a.{2 * i}", cout, cin, 5)
        if i < 3:
            _add_gdn(state, rng, f"g_a.{2 * i + 1}", cout)
    for i, (cin, cout) in enumerate([(m, n), (n, n), (n, n), (n, 3)]):
        w, b = _conv_weights(rng, cout, cin, 5)
        state[f"g_s.{2 * i}.weight"], state[f"g_s.{2 * i}.bias"] = w.transpose(1, 0, 2, 3).copy(), b
        if i < 3:
            _add_gdn(state, rng, f"g_s.{2 * i + 1}", cout)
    quantiles = np.stack([-10 + rng.normal(size=m), rng.uniform(-0.5, 0.5, m), 10 + rng.normal(size=m)], -1)
    state["entropy_bottleneck.quantiles"] = quantiles[:, None, :].astype(np.float32)
    state["entropy_bottleneck._matrix0"] = rng.normal(size=(m, 3, 1)).astype(np.float32)
    state["entropy_bottleneck._offset"] = np.arange(m, dtype=np.int32)
    return state


def _add_block(state: dict, rng: np.random.Generator, kind: str, name: str, n: int, cin: int) -> None:
    if kind == "stride":
        _add_conv(state, rng, f"{name}.conv1", n, cin, 3)
        _add_conv(state, rng, f"{name}.conv2", n, n, 3)
        _add_gdn(state, rng, f"{name}.gdn", n)
        _add_conv(state, rng, f"{name}.skip", n, cin, 1)
    elif kind == "res":
        _add_conv(state, rng, f"{name}.conv1", n, n, 3)
        _add_conv(state, rng, f"{name}.conv2", n, n, 3)
    elif kind == "up":
        _add_conv(state, rng, f"{name}.subpel_conv.0", 4 * n, n, 3)
        _add_conv(state, rng, f"{name}.conv", n, n, 3)
        _add_gdn(state, rng, f"{name}.igdn", n)
        _add_conv(state, rng, f"{name}.upsample.0", 4 * n, n, 3)
    elif kind == "attn":
        for branch in ("conv_a", "conv_b"):
            for u in range(3):
                _add_conv(state, rng, f"{name}.{branch}.{u}.conv.0", n // 2, n, 1)
                _add_conv(state, rng, f"{name}.{branch}.{u}.conv.2", n // 2, n // 2, 3)
                _add_conv(state, rng, f"{name}.{branch}.{u}.conv.4", n, n // 2, 1)
        _add_conv(state, rng, f"{name}.conv_b.3", n, n, 1)
    elif kind == "conv_s2":
        _add_conv(state, rng, name, n, n, 3)
    elif kind == "subpel":
        _add_conv(state, rng, f"{name}.0", 3 * 4, n, 3)


def random_cheng(rng: np.random.Generator, n: int = 8, attn: bool = False) -> dict:
    layout = C._CHENG_ATTN if attn else C._CHENG_ANCHOR
    state: dict = {}
    for prefix, kinds in zip(("g_a", "g_s"), layout, strict=True):
        for i, kind in enumerate(kinds):
            _add_block(state, rng, kind, f"{prefix}.{i}", n, 3 if (prefix, i) == ("g_a", 0) else n)
    _add_conv(state, rng, "h_a.0", n, n, 3)  # the hyperprior: read, not run
    state["entropy_bottleneck.quantiles"] = np.zeros((n, 1, 3), np.float32)
    return state


# ------------------------------------------------------------------------ brute-force NumPy references


def ref_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int = 1) -> np.ndarray:
    """PyTorch Conv2d (padding k // 2) by sliding windows: ``x [B, Cin, H, W]``, ``w [Cout, Cin, k, k]``."""
    k = w.shape[-1]
    p = k // 2
    xp = np.pad(x.astype(np.float64), ((0, 0), (0, 0), (p, p), (p, p)))
    windows = np.lib.stride_tricks.sliding_window_view(xp, (k, k), axis=(2, 3))[:, :, ::stride, ::stride]
    return np.einsum("bchwij,ocij->bohw", windows, w) + b[None, :, None, None]


def ref_conv_transpose(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, padding: int, op: int):
    """PyTorch ConvTranspose2d by scattering each input pixel: ``out[o, h·s − p + i, w·s − p + j] +=
    x[c, h, w] · w[c, o, i, j]``, ``w [Cin, Cout, k, k]``, output ``(H − 1)·s − 2p + k + op``."""
    bsz, _, h, wd = x.shape
    k = w.shape[-1]
    oh, ow = (h - 1) * stride - 2 * padding + k + op, (wd - 1) * stride - 2 * padding + k + op
    out = np.zeros((bsz, w.shape[1], oh, ow))
    for y in range(h):
        for xx in range(wd):
            contrib = np.einsum("bc,coij->boij", x[:, :, y, xx], w)
            for i in range(k):
                for j in range(k):
                    r, c = y * stride - padding + i, xx * stride - padding + j
                    if 0 <= r < oh and 0 <= c < ow:
                        out[:, :, r, c] += contrib[:, :, i, j]
    return out + b[None, :, None, None]


def ref_gdn(x: np.ndarray, beta: np.ndarray, gamma: np.ndarray, inverse: bool) -> np.ndarray:
    """CompressAI's GDN with the reparametrisation written out, pixel by pixel."""
    pedestal = (2.0**-18) ** 2
    beta = np.maximum(beta.astype(np.float64), (1e-6 + pedestal) ** 0.5) ** 2 - pedestal
    gamma = np.maximum(gamma.astype(np.float64), pedestal**0.5) ** 2 - pedestal
    out = np.empty_like(x, dtype=np.float64)
    for i in range(x.shape[1]):
        norm = beta[i] + sum(gamma[i, j] * x[:, j] ** 2 for j in range(x.shape[1]))
        out[:, i] = x[:, i] * np.sqrt(norm) if inverse else x[:, i] / np.sqrt(norm)
    return out


def ref_pixel_shuffle(x: np.ndarray, r: int) -> np.ndarray:
    b, c, h, w = x.shape
    out = np.empty((b, c // (r * r), h * r, w * r), x.dtype)
    for ch in range(c // (r * r)):
        for i in range(r):
            for j in range(r):
                out[:, ch, i::r, j::r] = x[:, ch * r * r + i * r + j]
    return out


def _leaky(x: np.ndarray) -> np.ndarray:
    return np.where(x >= 0, x, 0.01 * x)


def ref_cheng_anchor_analysis(s: dict, x: np.ndarray) -> np.ndarray:
    def conv(name: str, y: np.ndarray, stride: int = 1) -> np.ndarray:
        return ref_conv(y, s[f"{name}.weight"], s[f"{name}.bias"], stride)

    for i in (0, 2, 4):
        a = f"g_a.{i}"
        out = ref_gdn(
            conv(f"{a}.conv2", _leaky(conv(f"{a}.conv1", x, 2))),
            s[f"{a}.gdn.beta"],
            s[f"{a}.gdn.gamma"],
            False,
        )
        x = out + conv(f"{a}.skip", x, 2)
        r = f"g_a.{i + 1}"
        x = _leaky(conv(f"{r}.conv2", _leaky(conv(f"{r}.conv1", x)))) + x
    return conv("g_a.6", x, 2)


def ref_cheng_anchor_synthesis(s: dict, y: np.ndarray) -> np.ndarray:
    def conv(name: str, z: np.ndarray) -> np.ndarray:
        return ref_conv(z, s[f"{name}.weight"], s[f"{name}.bias"])

    for i in range(7):
        g = f"g_s.{i}"
        if i % 2 == 0:
            y = _leaky(conv(f"{g}.conv2", _leaky(conv(f"{g}.conv1", y)))) + y
        else:
            out = conv(f"{g}.conv", _leaky(ref_pixel_shuffle(conv(f"{g}.subpel_conv.0", y), 2)))
            out = ref_gdn(out, s[f"{g}.igdn.beta"], s[f"{g}.igdn.gamma"], True)
            y = out + ref_pixel_shuffle(conv(f"{g}.upsample.0", y), 2)
    return ref_pixel_shuffle(conv("g_s.7.0", y), 2)


def ref_factorized(s: dict, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(y, g_s of round(y) from the reference)``; the medians applied as CompressAI's forward does."""
    y = x
    for i in (0, 2, 4, 6):
        y = ref_conv(y, s[f"g_a.{i}.weight"], s[f"g_a.{i}.bias"], 2)
        if i < 6:
            y = ref_gdn(y, s[f"g_a.{i + 1}.beta"], s[f"g_a.{i + 1}.gamma"], False)
    return y, ref_factorized_synthesis(s, np.round(y))


def ref_factorized_synthesis(s: dict, y: np.ndarray) -> np.ndarray:
    for i in (0, 2, 4, 6):
        y = ref_conv_transpose(y, s[f"g_s.{i}.weight"], s[f"g_s.{i}.bias"], 2, 2, 1)
        if i < 6:
            y = ref_gdn(y, s[f"g_s.{i + 1}.beta"], s[f"g_s.{i + 1}.gamma"], True)
    return y


def _params(state: dict) -> dict:
    return {k: jnp.asarray(v, jnp.float32) for k, v in state.items() if v.dtype.kind == "f"}


# ---------------------------------------------------------------------------------------------- the layers


def test_gdn_and_inverse_gdn_match_compressai_definition() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 5, 4, 6)).astype(np.float32)
    beta, gamma = _gdn_weights(rng, 5)
    beta[1] = -0.5  # below beta's bound (1e-6 + pedestal)^½
    for inverse in (False, True):
        got = np.asarray(C.gdn(jnp.asarray(x), jnp.asarray(beta), jnp.asarray(gamma), inverse))
        np.testing.assert_allclose(got, ref_gdn(x, beta, gamma, inverse), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("h", "w", "k"), [(4, 6, 5), (5, 3, 5), (3, 4, 3)])
def test_transposed_conv_matches_pytorch_scatter(h: int, w: int, k: int) -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(2, 3, h, w)).astype(np.float32)
    weight = rng.normal(size=(3, 4, k, k)).astype(np.float32)  # [in, out, kH, kW]
    bias = rng.normal(size=4).astype(np.float32)
    got = np.asarray(C.conv_transpose2d(jnp.asarray(x), jnp.asarray(weight), jnp.asarray(bias)))
    ref = ref_conv_transpose(x, weight, bias, stride=2, padding=k // 2, op=1)
    assert got.shape == ref.shape == (2, 4, 2 * h, 2 * w)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def test_strided_conv_and_pixel_shuffle_match_pytorch() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(size=(1, 3, 8, 6)).astype(np.float32)
    for k, stride in ((5, 2), (3, 2), (3, 1), (1, 2)):
        weight, bias = _conv_weights(rng, 4, 3, k)
        got = np.asarray(C.conv2d(jnp.asarray(x), jnp.asarray(weight), jnp.asarray(bias), stride))
        np.testing.assert_allclose(got, ref_conv(x, weight, bias, stride), rtol=1e-5, atol=1e-5)
    y = rng.normal(size=(2, 12, 3, 5)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(C.pixel_shuffle(jnp.asarray(y), 2)), ref_pixel_shuffle(y, 2))


def test_median_quantisation_rounds_around_the_medians_half_to_even() -> None:
    quantiles = np.zeros((2, 1, 3), np.float32)
    quantiles[:, 0, 1] = [0.25, -1.0]
    y = np.array([[0.75, 1.75, 0.8, -0.3], [0.5, -1.5, 2.2, -1.0]], np.float32).reshape(1, 2, 1, 4)
    got = np.asarray(C.median_quantise(jnp.asarray(y), jnp.asarray(quantiles)))[0, :, 0]
    # 0.75 − 0.25 = 0.5 → 0 and 1.75 − 0.25 = 1.5 → 2 (torch.round: half to even); −1.5 + 1 = −0.5 → −0.
    np.testing.assert_array_equal(got, [[0.25, 2.25, 1.25, -0.75], [1.0, -1.0, 2.0, -1.0]])


# ------------------------------------------------------------------------------------------ the models


def test_factorized_layers_match_the_reference(tmp_path: Path) -> None:
    state = random_factorized(np.random.default_rng(3))
    params = _params(state)
    x = np.random.default_rng(4).uniform(size=(1, 3, 64, 64)).astype(np.float32)
    y_ref, _ = ref_factorized(state, x)
    y = np.asarray(C.analysis("bmshj2018-factorized", params, jnp.asarray(x)))
    assert y.shape == (1, 12, 4, 4)
    np.testing.assert_allclose(y, y_ref, rtol=1e-4, atol=1e-4)
    y_hat = np.round(y_ref)
    got = np.asarray(C.synthesis("bmshj2018-factorized", params, jnp.asarray(y_hat, jnp.float32)))
    np.testing.assert_allclose(got, ref_factorized_synthesis(state, y_hat), rtol=1e-4, atol=1e-4)
    # The forward is g_s of the median-quantised latent.
    medians = state["entropy_bottleneck.quantiles"][:, 0, 1][None, :, None, None]
    expected = C.synthesis("bmshj2018-factorized", params, jnp.round(jnp.asarray(y) - medians) + medians)
    out = C.forward("bmshj2018-factorized", params, jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected), rtol=1e-5, atol=1e-5)


def test_cheng2020_anchor_layers_match_the_reference() -> None:
    state = random_cheng(np.random.default_rng(5))
    params = _params(state)
    x = np.random.default_rng(6).uniform(size=(1, 3, 64, 64)).astype(np.float32)
    y = np.asarray(C.analysis("cheng2020-anchor", params, jnp.asarray(x)))
    np.testing.assert_allclose(y, ref_cheng_anchor_analysis(state, x), rtol=1e-4, atol=1e-4)
    y_hat = np.round(y)
    got = np.asarray(C.synthesis("cheng2020-anchor", params, jnp.asarray(y_hat)))
    assert got.shape == (1, 3, 64, 64)
    np.testing.assert_allclose(got, ref_cheng_anchor_synthesis(state, y_hat), rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(C.quantise("cheng2020-anchor", params, jnp.asarray(y))), y_hat)


# ------------------------------------------------------------------------------------------ the files


def test_torch_zip_reads_back_what_was_written(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    plain = {
        "a.weight": rng.normal(size=(4, 3, 2, 2)).astype(np.float32),
        "a.half": rng.normal(size=(3, 5)).astype(np.float16),
        "a.double": rng.normal(size=(2,)).astype(np.float64),
        "a.ints": np.arange(6, dtype=np.int64),
    }
    storages: list[Storage] = []
    tensors = contiguous_tensors({"state_dict": plain}, storages)
    # A transposed view and a slice at an offset, sharing one storage.
    base = rng.normal(size=(3, 4)).astype(np.float32)
    shared = Storage(str(len(storages)), base.reshape(-1))
    storages.append(shared)
    tensors["state_dict"]["b.transposed"] = Tensor(shared, 0, (4, 3), (1, 4))
    tensors["state_dict"]["b.row"] = Tensor(shared, 4, (4,), (1,))
    tensors["epoch"] = 3  # a checkpoint's other entries are not tensors
    write_torch_zip(tmp_path / "w.pth.tar", tensors, storages)
    flat = read_state_dict(tmp_path / "w.pth.tar")
    assert list(flat) == [f"state_dict.{k}" for k in plain] + ["state_dict.b.transposed", "state_dict.b.row"]
    for key, value in plain.items():
        assert flat[f"state_dict.{key}"].dtype == value.dtype
        np.testing.assert_array_equal(flat[f"state_dict.{key}"], value)
    np.testing.assert_array_equal(flat["state_dict.b.transposed"], base.T)
    np.testing.assert_array_equal(flat["state_dict.b.row"], base[1])
    # The same in torch's legacy format, the row a view of a storage as legacy files write them.
    tensors["state_dict"]["b.row"] = Tensor(StorageView("view", shared, 4, 4), 0, (4,), (1,))
    write_torch_legacy(tmp_path / "legacy.pth.tar", tensors, storages)
    legacy = read_state_dict(tmp_path / "legacy.pth.tar")
    assert list(legacy) == list(flat) and all(np.array_equal(legacy[k], v) for k, v in flat.items())
    # A .npz of the same names reads the same.
    np.savez(tmp_path / "w.npz", **plain)
    npz = read_state_dict(tmp_path / "w.npz")
    assert all(np.array_equal(npz[k], v) for k, v in plain.items())


def test_hostile_legacy_and_foreign_files_are_refused_in_one_line(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    command = f"touch {marker}".encode()
    evil = b"\x80\x02cos\nsystem\nX" + struct.pack("<I", len(command)) + command + b"\x85R."
    with zipfile.ZipFile(tmp_path / "evil.pth.tar", "w") as z:
        z.writestr("archive/data.pkl", evil)
    for call in (
        lambda: read_state_dict(tmp_path / "evil.pth.tar"),
        lambda: C.load("bmshj2018-factorized", tmp_path / "evil.pth.tar"),
    ):
        with pytest.raises(MnerfError, match="refusing to load os.system") as err:
            call()
        assert len(str(err.value).splitlines()) == 1
    assert not marker.exists()
    # In the legacy format too: the object's pickle may not name os.system.
    legacy = io.BytesIO()
    for record in (0x1950A86A20F9469CFC6C, 1001, {"little_endian": True}):
        pickle.dump(record, legacy, protocol=2)
    (tmp_path / "evil-legacy.pth").write_bytes(legacy.getvalue() + evil)
    with pytest.raises(MnerfError, match="refusing to load os.system"):
        read_state_dict(tmp_path / "evil-legacy.pth")
    assert not marker.exists()
    (tmp_path / "tar.pth").write_bytes(b"\0" * 257 + b"ustar" + b"\0" * 250)
    with pytest.raises(MnerfError, match="oldest .tar. format.*torch.save"):
        read_state_dict(tmp_path / "tar.pth")
    (tmp_path / "pickled.pth").write_bytes(pickle.dumps([1, 2], protocol=2))
    with pytest.raises(MnerfError, match="not a PyTorch file"):
        read_state_dict(tmp_path / "pickled.pth")
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(MnerfError, match="neither a PyTorch zip"):
        read_state_dict(tmp_path / "text.pth")
    with pytest.raises(MnerfError, match="does not exist"):
        C.load("cheng2020-anchor", tmp_path / "absent.pth")


def test_missing_or_misshapen_weights_and_unknown_models_are_named(tmp_path: Path) -> None:
    state = random_factorized(np.random.default_rng(8))
    partial = {k: v for k, v in state.items() if k not in ("g_a.2.bias", "g_s.5.gamma")}
    path = save_state_dict(tmp_path / "partial.pth", partial)
    with pytest.raises(C.CompressionModelError, match=r"lack g_a\.2\.bias, which bmshj2018-factorized needs"):
        C.load("bmshj2018-factorized", path)
    with pytest.raises(C.CompressionModelError, match=r"lack g_a\.0\.conv1\.weight, which cheng2020-anchor"):
        C.load("cheng2020-anchor", save_state_dict(tmp_path / "full.pth", state))
    bad = dict(state, **{"g_s.3.gamma": np.ones((5, 5), np.float32)})
    with pytest.raises(C.CompressionModelError, match="wrong shapes for bmshj2018-factorized") as err:
        C.load("bmshj2018-factorized", save_state_dict(tmp_path / "bad.pth", bad))
    assert len(str(err.value).splitlines()) == 1
    with pytest.raises(S.AttackError, match="unknown compression model 'mbt2018'"):
        C.load("mbt2018", path)


def test_models_with_random_weights_take_and_return_uint8(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    images = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    odd = rng.integers(0, 256, (1, 50, 70, 3), dtype=np.uint8)
    for arch, state, batches in (
        ("bmshj2018-factorized", random_factorized(rng), (images, odd)),
        ("cheng2020-attn", random_cheng(rng, attn=True), (odd,)),
    ):
        # Nested and DataParallel-prefixed, with CompressAI's older ``downsample`` name for ``skip``.
        renamed = {f"module.{k.replace('.skip.', '.downsample.')}": v for k, v in state.items()}
        model = C.load(arch, save_state_dict(tmp_path / f"{arch}.pth.tar", {"state_dict": renamed}))
        assert (model.n, model.m) == ((8, 12) if arch == "bmshj2018-factorized" else (8, 8))
        for batch in batches:
            out = model(batch)
            assert out.dtype == np.uint8 and out.shape == batch.shape
    # The factorized model's 50×70 image: the forward on it zero-padded to 64×128 (centred), cropped back.
    x = np.zeros((1, 3, 64, 128), np.float32)
    x[:, :, 7:57, 29:99] = odd.transpose(0, 3, 1, 2) / np.float32(255)
    params = C.load("bmshj2018-factorized", tmp_path / "bmshj2018-factorized.pth.tar").params
    expected = np.clip(np.asarray(C._run("bmshj2018-factorized", params, jnp.asarray(x))), 0, 1)
    expected = (expected[:, :, 7:57, 29:99].transpose(0, 2, 3, 1) * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(C.regenerate("bmshj2018-factorized", params, odd), expected)


def test_quality_labels_of_file_names() -> None:
    assert C.quality_label("w/bmshj2018-factorized-prior-3-5c6f152b.pth.tar") == "q3"
    assert C.quality_label("cheng2020-anchor-6-4c052b1a.pth.tar") == "q6"
    assert C.quality_label("cheng_q2.pth") == "q2"
    assert C.quality_label("my-weights.npz") == "my-weights"


def test_codec_model_attack_rows(tmp_path: Path) -> None:
    path = save_state_dict(
        tmp_path / "bmshj2018-factorized-prior-3-5c6f152b.pth.tar",
        random_factorized(np.random.default_rng(10)),
    )
    attack = S.codec_model_attack(f"bmshj2018-factorized={path}")
    assert attack.name == "bmshj2018-factorized-q3" and attack.family == "regen"
    assert "N 8, M 12" in attack.description
    images = np.random.default_rng(11).integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    out = attack(images, seed=0)
    assert out.dtype == np.uint8 and out.shape == images.shape
    for spec, message in (
        ("bmshj2018-factorized", "ARCHITECTURE=PATH"),
        (f"jpeg={path}", "unknown compression model 'jpeg'"),
        ("cheng2020-anchor=/no/such/file.pth", "does not exist"),
    ):
        with pytest.raises(MnerfError, match=message):
            S.codec_model_attack(spec)
    assert "--codec-model" in S.listing() and "cheng2020-anchor" in S.listing()
