"""PyTorch ``torch.save`` files (zip, TorchScript zip, legacy) read without torch or running their pickle.

A PyTorch zip archive holds ``<root>/data.pkl`` (a pickle whose tensors refer to storages by persistent
id) and ``<root>/data/<key>`` (each storage's raw little-endian bytes). The pickle is read with a restricted
unpickler that knows only what such a file needs:

- ``torch._utils._rebuild_tensor_v2`` / ``_rebuild_tensor`` / ``_rebuild_parameter`` → NumPy arrays (copies of
  strided views into the storage bytes);
- ``torch.<Dtype>Storage`` → the storage's NumPy dtype; ``collections.OrderedDict`` → ``dict``;
- ``__torch__.*`` classes (TorchScript modules) → plain attribute holders;
- ``torch.jit._pickle`` list builders → lists.

Any other global (``os.system``, ``builtins.eval``, ...) is refused, so a hostile file cannot run code.
:func:`read_torch_zip` flattens what the pickle holds to ``{dotted name: array}`` in registration order;
:func:`read_torch_legacy` reads torch's legacy (pre-1.6) single-pickle format with the same unpickler, and
:func:`read_state_dict` any of those or a NumPy ``.npz`` of the same names. Used by the decoder converter
(``reader.convert``) and the compression models that regenerate images (``imaging.compression_models``).
"""

from __future__ import annotations

import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.core.errors import MnerfError

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


class _PendingStorage:
    """A legacy file's storage: its values follow the pickle, so tensors over it wait for them."""

    def __init__(self, dtype: np.dtype, numel: int):
        self.dtype, self.numel = dtype, numel
        self.data: np.ndarray | None = None


class _StorageView:
    """``size`` values of a pending storage from ``offset`` (legacy files' storage views)."""

    def __init__(self, root: _PendingStorage, offset: int, size: int):
        self.root, self.offset, self.size = root, offset, size

    def resolve(self) -> np.ndarray:
        if self.root.data is None:
            raise MnerfError("a storage the pickle refers to is not in the file (corrupt file)")
        if self.offset < 0 or self.offset + self.size > self.root.data.size:
            raise MnerfError("a storage view reaches outside its storage (corrupt file)")
        return self.root.data[self.offset : self.offset + self.size]


class _PendingTensor:
    """A legacy file's tensor, built once its storage's values are read."""

    def __init__(self, storage: _StorageView, offset: int, size: tuple, stride: tuple):
        self.args = (storage, offset, size, stride)

    def resolve(self) -> np.ndarray:
        storage, offset, size, stride = self.args
        return _rebuild_tensor(storage.resolve(), offset, size, stride)


def _rebuild_tensor(storage: Any, offset: int, size: tuple, stride: tuple, *_: Any) -> Any:
    if isinstance(storage, _StorageView):
        return _PendingTensor(storage, offset, size, stride)
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
    return _tensors_of(obj, zip_path)


def _tensors_of(obj: Any, path: str | Path) -> dict[str, np.ndarray]:
    """The unpickled ``obj``'s tensors by dotted name; MnerfError when it holds none."""
    flat: dict[str, np.ndarray] = {}
    _flatten_tree(obj, "", flat)
    if not flat:
        raise MnerfError(f"{path} holds no tensors")
    return flat


def _flatten_tree(obj: Any, prefix: str, out: dict[str, np.ndarray]) -> None:
    if isinstance(obj, _PendingTensor):
        obj = obj.resolve()
    if isinstance(obj, np.ndarray):
        out[prefix.rstrip(".")] = obj
    elif isinstance(obj, ScriptObject):
        _flatten_tree(obj.attributes, prefix, out)
    elif isinstance(obj, Mapping):
        for key, value in obj.items():
            _flatten_tree(value, f"{prefix}{key}.", out)


# ------------------------------------------------------------------------ torch's legacy (pre-zip) format

LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
LEGACY_PROTOCOL = 1001


class _DataOnlyUnpickler(pickle.Unpickler):
    """For the legacy file's plain records (magic number, version, system info, storage keys): no globals."""

    def find_class(self, module: str, name: str) -> Any:
        raise MnerfError(f"refusing to load {module}.{name} from the pickle (not a tensor or module type)")

    def persistent_load(self, pid: Any) -> Any:
        raise MnerfError(f"unexpected persistent id {pid!r} in the pickle")


class _LegacyUnpickler(_RestrictedUnpickler):
    """The legacy file's object: the same names allowed; storages are ``("storage", type, root key,
    location, root numel, view)``, ``view`` None or ``(view key, offset, size)``; values after the pickle."""

    def __init__(self, file: Any):
        pickle.Unpickler.__init__(self, file)
        self.roots: dict[str, _PendingStorage] = {}

    def persistent_load(self, pid: Any) -> _StorageView:  # type: ignore[override]
        if not (isinstance(pid, tuple) and len(pid) == 6 and pid[0] == "storage"):
            raise MnerfError(f"unsupported persistent id {pid!r} in the pickle")
        storage_type, key, numel, view = pid[1], str(pid[2]), int(pid[4]), pid[5]
        if not isinstance(storage_type, _StorageType):
            raise MnerfError(f"unsupported storage type {storage_type!r}")
        root = self.roots.setdefault(key, _PendingStorage(storage_type.dtype, numel))
        if view is None:
            return _StorageView(root, 0, numel)
        return _StorageView(root, int(view[1]), int(view[2]))


def read_torch_legacy(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a file in torch's legacy format (``torch.save`` before 1.6, or with
    ``_use_new_zipfile_serialization=False``): pickled magic number, protocol version and system info, the
    object, the sorted storage keys, then each storage as an int64 count and its raw values."""
    path = Path(path)
    try:
        with path.open("rb") as file:
            if _DataOnlyUnpickler(file).load() != LEGACY_MAGIC:
                raise MnerfError(f"{path} is a pickle but not a PyTorch file (no torch.save magic number)")
            version = _DataOnlyUnpickler(file).load()
            if version != LEGACY_PROTOCOL:
                raise MnerfError(f"{path}: torch's legacy format version {version!r} is not read here")
            sys_info = _DataOnlyUnpickler(file).load()
            little = not isinstance(sys_info, dict) or sys_info.get("little_endian", True)
            order = "little" if little else "big"
            unpickler = _LegacyUnpickler(file)
            obj = unpickler.load()
            for key in _DataOnlyUnpickler(file).load():
                root = unpickler.roots.get(str(key))
                if root is None:
                    raise MnerfError(f"{path}: storage {key} is listed but no tensor uses it (corrupt file)")
                numel = int.from_bytes(file.read(8), order)
                dtype = root.dtype.newbyteorder("<" if little else ">")
                raw = file.read(numel * dtype.itemsize)
                if numel < root.numel or len(raw) < numel * dtype.itemsize:
                    raise MnerfError(f"{path}: storage {key} is truncated")
                root.data = np.frombuffer(raw, dtype, count=numel).astype(root.dtype)
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as err:
        raise MnerfError(f"{path}: unreadable pickle ({type(err).__name__}: {err})") from None
    return _tensors_of(obj, path)


LEGACY_HINT = (
    "re-save it in the zip format from Python with torch ≥ 1.6: "
    "torch.save(torch.load(OLD, map_location='cpu'), NEW)"
)


def read_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """``{dotted name: array}`` of a weights file: a PyTorch zip archive (``torch.save`` since torch 1.6,
    :func:`read_torch_zip`), torch's legacy pickle format (:func:`read_torch_legacy`) or a NumPy ``.npz`` of
    the same names (read without pickle). Nesting is kept in the names (a checkpoint's ``{"state_dict":
    ...}`` gives ``state_dict.<name>``). MnerfError, in one line, for a missing file, torch's oldest (tar)
    format, or anything else."""
    path = Path(path)
    if not path.is_file():
        raise MnerfError(f"{path} does not exist")
    with path.open("rb") as file:
        head = file.read(512)
    if head[257:262] == b"ustar":
        raise MnerfError(f"{path} is in torch's oldest (tar) format, which is not read here: {LEGACY_HINT}")
    if head[:1] == b"\x80":
        return read_torch_legacy(path)
    if head[:4] != b"PK\x03\x04":
        raise MnerfError(f"{path} is neither a PyTorch zip archive (torch.save) nor a NumPy .npz")
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except zipfile.BadZipFile as err:
        raise MnerfError(f"{path} is not a readable zip archive ({err})") from None
    if names and all(n.endswith(".npy") for n in names):
        try:
            with np.load(path, allow_pickle=False) as npz:
                return {name: np.asarray(npz[name]) for name in npz.files}
        except (ValueError, OSError, zipfile.BadZipFile) as err:
            raise MnerfError(f"{path}: unreadable .npz ({err})") from None
    return read_torch_zip(path)
