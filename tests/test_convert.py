"""TorchScript / torch.save decoder conversion without torch: the test writes the zip format itself.

The pickle is emitted opcode by opcode, the way PyTorch's pickler writes it: modules as ``__torch__`` classes
built with ``EMPTY_TUPLE NEWOBJ`` + attribute dict + ``BUILD``; tensors as ``torch._utils._rebuild_tensor_v2``
over a ``BINPERSID`` storage reference ``("storage", torch.FloatStorage, key, "cpu", numel)``.
"""

from __future__ import annotations

import io
import math
import struct
import zipfile
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import convert, decoder_io
from mnerf_jax.reader import decoder as dec

# ------------------------------------------------------------------------------------------------------------
# A minimal pickle writer (protocol 2 opcodes)


class Obj:
    """A TorchScript object: ``__torch__.<module>.<name>`` with ordered attributes."""

    def __init__(self, module: str, name: str, attrs: dict):
        self.module, self.name, self.attrs = module, name, attrs


class StateDict:
    """``collections.OrderedDict`` as ``torch.save`` writes a state dict."""

    def __init__(self, items: dict):
        self.items = items


class PickleWriter:
    def __init__(self) -> None:
        self.out = io.BytesIO()
        self.storages: dict[str, bytes] = {}
        self.out.write(b"\x80\x02")  # PROTO 2

    def global_(self, module: str, name: str) -> None:
        self.out.write(b"c" + module.encode() + b"\n" + name.encode() + b"\n")

    def value(self, v) -> None:
        w = self.out.write
        if v is None:
            w(b"N")
        elif v is True or v is False:
            w(b"\x88" if v else b"\x89")
        elif isinstance(v, int):
            w(b"J" + struct.pack("<i", v))  # BININT
        elif isinstance(v, float):
            w(b"G" + struct.pack(">d", v))  # BINFLOAT
        elif isinstance(v, str):
            data = v.encode()
            w(b"X" + struct.pack("<I", len(data)) + data)  # BINUNICODE
        elif isinstance(v, tuple):
            w(b"(")
            for item in v:
                self.value(item)
            w(b"t")
        elif isinstance(v, np.ndarray):
            self.tensor(v)
        elif isinstance(v, Obj):
            self.global_(v.module, v.name)
            w(b")\x81")  # EMPTY_TUPLE NEWOBJ
            self.dict_(v.attrs)
            w(b"b")  # BUILD
        elif isinstance(v, StateDict):
            self.global_("collections", "OrderedDict")
            w(b")R")  # EMPTY_TUPLE REDUCE
            w(b"(")
            for key, item in v.items.items():
                self.value(key)
                self.value(item)
            w(b"u")  # SETITEMS
        elif isinstance(v, dict):
            self.dict_(v)
        else:
            raise TypeError(type(v))

    def dict_(self, d: dict) -> None:
        self.out.write(b"}(")
        for key, item in d.items():
            self.value(key)
            self.value(item)
        self.out.write(b"u")

    def tensor(self, a: np.ndarray) -> None:
        key = str(len(self.storages))
        kind = {np.dtype(np.float32): "FloatStorage", np.dtype(np.int64): "LongStorage"}[a.dtype]
        self.storages[key] = np.require(a, requirements="C").astype(a.dtype.newbyteorder("<")).tobytes()
        strides = tuple(s // a.itemsize for s in np.require(a, requirements="C").strides)
        self.global_("torch._utils", "_rebuild_tensor_v2")
        w = self.out.write
        w(b"(")  # MARK of the argument tuple
        w(b"(")  # persistent id tuple
        self.value("storage")
        self.global_("torch", kind)
        self.value(key)
        self.value("cpu")
        self.value(int(a.size))
        w(b"tQ")  # TUPLE BINPERSID
        self.value(0)
        self.value(tuple(int(s) for s in a.shape))
        self.value(strides)
        self.value(False)
        self.global_("collections", "OrderedDict")
        w(b")R")
        w(b"tR")  # TUPLE REDUCE

    def finish(self) -> bytes:
        self.out.write(b".")
        return self.out.getvalue()


def write_zip(path: Path, root_obj, root: str = "archive") -> None:
    writer = PickleWriter()
    writer.value(root_obj)
    data = writer.finish()
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{root}/data.pkl", data)
        z.writestr(f"{root}/byteorder", "little")
        for key, raw in writer.storages.items():
            z.writestr(f"{root}/data/{key}", raw)
        z.writestr(f"{root}/version", "3\n")


# ------------------------------------------------------------------------------------------------------------
# A small random HiDDeN decoder in PyTorch layout, and a NumPy reference forward


def random_torch_decoder(rng: np.random.Generator, bits: int = 8, channels: int = 4, depth: int = 2) -> list:
    """``[(conv_w OIHW, conv_b, bn_w, bn_b, mean, var), ...]`` blocks plus linear and whitening weights."""
    blocks = []
    cin = 3
    for i in range(depth + 1):
        cout = channels if i < depth else bits
        f = np.float32
        blocks.append(
            (
                rng.normal(0, 0.4, (cout, cin, 3, 3)).astype(f),
                rng.normal(0, 0.1, cout).astype(f),
                rng.uniform(0.5, 1.5, cout).astype(f),
                rng.normal(0, 0.1, cout).astype(f),
                rng.normal(0, 0.3, cout).astype(f),
                rng.uniform(0.5, 2.0, cout).astype(f),
            )
        )
        cin = cout
    linear = (
        rng.normal(0, 0.5, (bits, bits)).astype(np.float32),
        rng.normal(0, 0.1, bits).astype(np.float32),
    )
    whiten = (
        rng.normal(0, 0.5, (bits, bits)).astype(np.float32),
        rng.normal(0, 0.1, bits).astype(np.float32),
    )
    return [blocks, linear, whiten]


def scripted_module(model: list) -> Obj:
    """``Sequential(HiddenDecoder, Linear)`` as TorchScript pickles it (stable-signature's whitened one)."""
    blocks, linear, whiten = model
    nn = "__torch__.torch.nn.modules"
    layers = {"training": False}
    for i, (w, b, g, beta, mean, var) in enumerate(blocks):
        conv = Obj(f"{nn}.conv", "Conv2d", {"training": False, "weight": w, "bias": b})
        bn = Obj(
            f"{nn}.batchnorm",
            "BatchNorm2d",
            {
                "training": False,
                "weight": g,
                "bias": beta,
                "running_mean": mean,
                "running_var": var,
                "num_batches_tracked": np.array(7, np.int64),
            },
        )
        gelu = Obj(f"{nn}.activation", "GELU", {"training": False})
        inner = Obj(f"{nn}.container", "Sequential", {"training": False, "0": conv, "1": bn, "2": gelu})
        layers[str(i)] = Obj("__torch__.models", "ConvBNRelu", {"training": False, "layers": inner})
    layers[str(len(blocks))] = Obj(f"{nn}.pooling", "AdaptiveAvgPool2d", {"training": False})
    decoder = Obj(
        "__torch__.models",
        "HiddenDecoder",
        {
            "training": False,
            "layers": Obj(f"{nn}.container", "Sequential", layers),
            "linear": Obj(
                f"{nn}.linear", "Linear", {"training": False, "weight": linear[0], "bias": linear[1]}
            ),
        },
    )
    white = Obj(f"{nn}.linear", "Linear", {"training": False, "weight": whiten[0], "bias": whiten[1]})
    return Obj(f"{nn}.container", "Sequential", {"training": False, "0": decoder, "1": white})


def state_dict(model: list, prefix: str = "hidden_decoder.", whitening: bool = False) -> StateDict:
    """A ``torch.save`` state dict with other names (``hidden_decoder.layers.0.conv.weight`` ...)."""
    blocks, linear, whiten = model
    items = {}
    for i, (w, b, g, beta, mean, var) in enumerate(blocks):
        p = f"{prefix}layers.{i}."
        items.update(
            {
                f"{p}conv.weight": w,
                f"{p}conv.bias": b,
                f"{p}bn.weight": g,
                f"{p}bn.bias": beta,
                f"{p}bn.running_mean": mean,
                f"{p}bn.running_var": var,
                f"{p}bn.num_batches_tracked": np.array(3, np.int64),
            }
        )
    items[f"{prefix}linear.weight"], items[f"{prefix}linear.bias"] = linear
    if whitening:
        items["whitening.weight"], items["whitening.bias"] = whiten
    return StateDict(items)


def reference_forward(model: list, ll2: np.ndarray, whitening: bool = True) -> np.ndarray:
    """NumPy forward in PyTorch layout: ``ll2 [B, h, w, 3]`` → logits ``[B, L]`` (float64)."""
    blocks, linear, whiten = model
    x = ll2.transpose(0, 3, 1, 2).astype(np.float64)  # NCHW
    erf = np.vectorize(math.erf)
    for w, b, g, beta, mean, var in blocks:
        _, _, h, wd = x.shape
        xp = np.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)))
        out = np.zeros((x.shape[0], w.shape[0], h, wd))
        for dy in range(3):
            for dx in range(3):
                out += np.einsum("bchw,oc->bohw", xp[:, :, dy : dy + h, dx : dx + wd], w[:, :, dy, dx])
        out += b[None, :, None, None]
        out = (out - mean[None, :, None, None]) / np.sqrt(var[None, :, None, None] + 1e-3)
        out = out * g[None, :, None, None] + beta[None, :, None, None]
        x = 0.5 * out * (1.0 + erf(out / math.sqrt(2.0)))
    y = x.mean(axis=(2, 3)) @ linear[0].T + linear[1]
    return y @ whiten[0].T + whiten[1] if whitening else y


# ------------------------------------------------------------------------------------------------------------


def test_torchscript_zip_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    model = random_torch_decoder(rng)
    zip_path = tmp_path / "dec_8b_whit.torchscript.pt"
    write_zip(zip_path, scripted_module(model), root="dec_8b_whit.torchscript")

    flat = convert.read_torch_zip(zip_path)
    assert list(flat)[:2] == ["0.layers.0.layers.0.weight", "0.layers.0.layers.0.bias"]
    np.testing.assert_array_equal(flat["0.layers.1.layers.1.running_var"], model[0][1][5])
    assert flat["0.layers.0.layers.1.num_batches_tracked"].dtype == np.int64

    meta = convert.convert_torchscript_decoder(zip_path, tmp_path / "converted.npz")
    assert meta["whitened"] is True and meta["bits"] == 8
    loaded = decoder_io.load_decoder(tmp_path / "converted.npz", expect_bits=8)
    params, stats = loaded.variables["params"], loaded.variables["batch_stats"]
    w, b, g, beta, mean, var = model[0][2]
    np.testing.assert_array_equal(params["block_2"]["conv"]["kernel"], w.transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(params["block_2"]["conv"]["bias"], b)
    np.testing.assert_array_equal(params["block_2"]["bn"]["scale"], g)
    np.testing.assert_array_equal(stats["block_2"]["bn"]["mean"], mean)
    np.testing.assert_array_equal(stats["block_2"]["bn"]["var"], var)
    np.testing.assert_array_equal(params["linear"]["kernel"], model[1][0].T)
    np.testing.assert_array_equal(params["whiten"]["kernel"], model[2][0].T)

    ll2 = rng.uniform(0, 4, (3, 7, 9, 3)).astype(np.float32)
    ours = np.asarray(dec.apply_ll2(loaded.variables, jnp.asarray(ll2)))
    np.testing.assert_allclose(ours, reference_forward(model, ll2), rtol=1e-4, atol=1e-4)


def test_state_dict_zip_with_other_names(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    model = random_torch_decoder(rng, bits=16, channels=4, depth=3)
    zip_path = tmp_path / "checkpoint.pth"
    write_zip(zip_path, state_dict(model), root="archive")
    meta = convert.convert_torchscript_decoder(zip_path, tmp_path / "converted.npz")
    assert meta["whitened"] is False and meta["bits"] == 16 and meta["depth"] == 3
    loaded = decoder_io.load_decoder(tmp_path / "converted.npz")
    np.testing.assert_array_equal(
        loaded.variables["params"]["whiten"]["kernel"], np.eye(16, dtype=np.float32)
    )
    ll2 = rng.uniform(0, 4, (2, 6, 6, 3)).astype(np.float32)
    ours = np.asarray(dec.apply_ll2(loaded.variables, jnp.asarray(ll2)))
    np.testing.assert_allclose(ours, reference_forward(model, ll2, whitening=False), rtol=1e-4, atol=1e-4)

    # With a whitening layer saved beside it, the second linear layer becomes the whitening.
    write_zip(zip_path, state_dict(model, whitening=True))
    assert convert.convert_torchscript_decoder(zip_path, tmp_path / "whitened.npz")["whitened"] is True


def _raw_pickle_zip(path: Path, payload: bytes) -> None:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", payload)


def test_hostile_and_broken_files_are_refused(tmp_path: Path) -> None:
    # A pickle that would call os.system: refused by the restricted unpickler, nothing runs.
    marker = tmp_path / "ran"
    evil = b"\x80\x02cos\nsystem\nX" + struct.pack("<I", len(f"touch {marker}")) + f"touch {marker}".encode()
    evil += b"\x85R."
    _raw_pickle_zip(tmp_path / "evil.pt", evil)
    with pytest.raises(MnerfError, match="refusing to load os.system"):
        convert.read_torch_zip(tmp_path / "evil.pt")
    assert not marker.exists()

    (tmp_path / "plain.pt").write_bytes(b"not a zip at all")
    with pytest.raises(MnerfError, match="not a readable zip"):
        convert.read_torch_zip(tmp_path / "plain.pt")
    with pytest.raises(MnerfError, match="does not exist"):
        convert.read_torch_zip(tmp_path / "absent.pt")

    # A storage missing from the archive.
    rng = np.random.default_rng(2)
    good = tmp_path / "good.pt"
    write_zip(good, scripted_module(random_torch_decoder(rng)))
    broken = tmp_path / "broken.pt"
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(broken, "w") as dst:
        for name in src.namelist():
            if name != "archive/data/3":
                dst.writestr(name, src.read(name))
    with pytest.raises(MnerfError, match="storage archive/data/3 is missing"):
        convert.read_torch_zip(broken)

    # Tensors that do not form a HiDDeN decoder.
    write_zip(tmp_path / "other.pt", StateDict({"fc.weight": np.ones((4, 4), np.float32)}))
    with pytest.raises(MnerfError, match="not a HiDDeN decoder"):
        convert.convert_torchscript_decoder(tmp_path / "other.pt", tmp_path / "x.npz")
