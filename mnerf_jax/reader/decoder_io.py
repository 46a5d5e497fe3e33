"""Decoder weights files: writing and reading them, the decoders shipped with the package, fresh decoders.

Files are ``.npz`` archives (read with ``allow_pickle=False``) holding one array per leaf plus a JSON metadata
entry: bits, wavelet, pooling margin, training information and a fingerprint (sha256 of the weight bytes)
that :func:`load_decoder` verifies. A decoder from any source (a file, the shipped one, a fresh one) comes as
a :class:`LoadedDecoder`. The model itself (architecture, apply, whitening) is :mod:`.decoder`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import dwt
from mnerf_jax.reader.decoder import (
    HiddenDecoder,
    Variables,
    architecture,
    calibrate_batch_norm,
    fit_whitening,
    init_decoder,
    pool_margin,
    with_pool_margin,
)

SHIPPED_BITS = (8, 16, 32, 48)
FORMAT = "mnerf-hidden-decoder"
FORMAT_VERSION = 1
_META_KEY = "__metadata__"
ASSET_DIR = Path(__file__).resolve().parents[1] / "assets" / "decoders"


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for key in sorted(tree):
        value = tree[key]
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten(value, name + "/"))
        else:
            out[name] = np.asarray(value)
    return out


def _unflatten(flat: Mapping[str, np.ndarray]) -> Variables:
    tree: dict[str, Any] = {}
    for name, value in flat.items():
        node = tree
        parts = name.split("/")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return tree


def fingerprint(variables: Mapping[str, Any]) -> str:
    """sha256 over the leaves' names, dtypes, shapes and little-endian bytes, in sorted order (and the pooling
    margin when there is one, so fingerprints of decoders without one are unchanged)."""
    digest = hashlib.sha256()
    margin = pool_margin(variables)
    if margin:
        digest.update(f"pool_margin|{margin}\n".encode())
    for name, value in _flatten(
        {"params": variables["params"], "batch_stats": variables["batch_stats"]}
    ).items():
        value = np.ascontiguousarray(value, dtype=value.dtype.newbyteorder("<"))
        digest.update(f"{name}|{value.dtype.str}|{value.shape}\n".encode())
        digest.update(value.tobytes())
    return digest.hexdigest()


@dataclasses.dataclass(frozen=True)
class LoadedDecoder:
    """A decoder read from disk: its variables, bit length, wavelet and the file's metadata."""

    variables: Variables
    bits: int
    wavelet: str
    metadata: dict[str, Any]
    path: Path

    @property
    def fingerprint(self) -> str:
        return str(self.metadata["fingerprint"])


def save_decoder(
    path: str | Path,
    variables: Mapping[str, Any],
    metadata: Mapping[str, Any] | None = None,
    wavelet: str = "bior4.4",
) -> dict[str, Any]:
    """Write ``variables`` and metadata to ``path`` (``.npz``, no pickle) atomically; return the metadata."""
    bits, channels, depth = architecture(variables)
    flat = _flatten({"params": variables["params"], "batch_stats": variables["batch_stats"]})
    flat = {k: np.asarray(v, np.float32) for k, v in flat.items()}
    meta = dict(metadata or {})
    margin = pool_margin(variables)
    meta.update(
        format=FORMAT,
        version=FORMAT_VERSION,
        bits=bits,
        channels=channels,
        depth=depth,
        wavelet=wavelet,
        pool_margin=margin,
        fingerprint=fingerprint(with_pool_margin(_unflatten(flat), margin)),
    )
    write_npz_atomic(path, flat, meta)
    return meta


def write_npz_atomic(path: str | Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> None:
    """Write ``arrays`` and ``meta`` (JSON, under ``__metadata__``) to a compressed ``.npz`` at ``path``,
    atomically (a temporary file, then a rename), so a killed write never leaves a truncated file."""
    payload = np.frombuffer(json.dumps(dict(meta), sort_keys=True).encode(), np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{_META_KEY: payload}, **arrays)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buffer.getvalue())
    os.replace(tmp, path)


def _expected_shapes(bits: int, channels: int, depth: int) -> dict[str, tuple[int, ...]]:
    module = HiddenDecoder(bits=bits, channels=channels, depth=depth)
    shapes = jax.eval_shape(lambda: module.init(jax.random.PRNGKey(0), jnp.zeros((1, 8, 8, 3))))
    leaves = jax.tree_util.tree_flatten_with_path(dict(shapes))[0]
    return {"/".join(str(k.key) for k in path): tuple(leaf.shape) for path, leaf in leaves}


def read_variables_npz(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The raw arrays and metadata of a decoder file; MnerfError for a missing or unreadable file."""
    path = Path(path)
    if not path.is_file():
        raise MnerfError(f"decoder file {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.array(data[name]) for name in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, zipfile.LargeZipFile) as err:
        raise MnerfError(
            f"decoder file {path} is corrupt or truncated ({type(err).__name__}: {err})"
        ) from None
    if _META_KEY not in arrays:
        raise MnerfError(f"decoder file {path} has no metadata entry (not an mnerf decoder file)")
    try:
        meta = json.loads(arrays.pop(_META_KEY).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MnerfError(f"decoder file {path} has unreadable metadata ({err})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise MnerfError(f"decoder file {path} is not an mnerf decoder file (format {meta.get('format')!r})")
    return arrays, meta


def load_decoder(path: str | Path, expect_bits: int | None = None) -> LoadedDecoder:
    """Read a decoder file written by :func:`save_decoder` (no pickle) and check it.

    Raises MnerfError with a one-line message for a missing, corrupt or truncated file, a bit length other
    than ``expect_bits``, arrays of the wrong shapes, or weights that do not match the recorded fingerprint.
    """
    path = Path(path)
    arrays, meta = read_variables_npz(path)
    try:
        bits, channels, depth = int(meta["bits"]), int(meta["channels"]), int(meta["depth"])
        wavelet = str(meta["wavelet"])
        margin = int(meta.get("pool_margin", 0))  # files written before the setting existed pool everywhere
    except (KeyError, TypeError, ValueError) as err:
        raise MnerfError(f"decoder file {path} has incomplete metadata ({err})") from None
    if expect_bits is not None and bits != expect_bits:
        raise MnerfError(
            f"decoder file {path} decodes {bits}-bit messages, but {expect_bits} bits are expected"
        )
    if wavelet not in dwt.DEC_LO:
        raise MnerfError(f"decoder file {path} names an unknown wavelet {wavelet!r}")
    expected = _expected_shapes(bits, channels, depth)
    if set(arrays) != set(expected):
        missing = sorted(set(expected) - set(arrays)) or sorted(set(arrays) - set(expected))
        raise MnerfError(
            f"decoder file {path} does not hold a {bits}-bit HiDDeN decoder (mismatch at {missing[0]})"
        )
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise MnerfError(f"decoder file {path}: {name} has shape {arrays[name].shape}, expected {shape}")
    if margin < 0:
        raise MnerfError(f"decoder file {path} has a negative pooling margin ({margin})")
    variables = with_pool_margin(_unflatten({k: v.astype(np.float32) for k, v in arrays.items()}), margin)
    if fingerprint(variables) != meta.get("fingerprint"):
        raise MnerfError(f"decoder file {path} is corrupt: its weights do not match the recorded fingerprint")
    variables = jax.tree.map(jnp.asarray, variables)
    return LoadedDecoder(variables=variables, bits=bits, wavelet=wavelet, metadata=meta, path=path)


FRESH = "fresh"  # ``--decoder fresh``: see :func:`fresh_decoder`


def fresh_decoder(
    bits: int,
    images: np.ndarray,
    seed: int = 0,
    wavelet: str = "bior4.4",
    max_images: int = 64,
) -> LoadedDecoder:
    """A random-init decoder whitened on ``images [N, H, W, 3]`` in [0, 1] (up to ``max_images`` of them).

    For embedding when no trained decoder is at hand: MultiNeRF's phase 2 trains the decoder with the field,
    so the pair can agree on a code for this one scene. Whitening on the scene's own images centres the
    logits of its unwatermarked renders (random bits, near 50 % accuracy). Such a decoder has never seen an
    attack: its robustness is what phase 2's augmentations give it, no more.
    """
    images = np.asarray(images, np.float32)
    if images.ndim != 4 or images.shape[-1] != 3 or len(images) == 0:
        raise MnerfError(f"a fresh decoder is whitened on RGB images [N, H, W, 3], got shape {images.shape}")
    if len(images) < max_images:
        # A scene with few views: its flipped images count too (whitening needs more samples than bits).
        images = np.concatenate([images, images[:, ::-1], images[:, :, ::-1], images[:, ::-1, ::-1]])
    images = images[:max_images]
    if len(images) <= bits:
        raise MnerfError(f"a fresh {bits}-bit decoder needs more than {bits // 4} training images")
    variables = init_decoder(jax.random.PRNGKey(seed), bits)
    variables = calibrate_batch_norm(variables, dwt.ll2(jnp.asarray(images), wavelet))
    batches = [dwt.ll2(jnp.asarray(images[i : i + 16]), wavelet) for i in range(0, len(images), 16)]
    variables = fit_whitening(variables, batches)
    variables = jax.tree.map(lambda x: np.asarray(x, np.float32), variables)
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "bits": bits,
        "wavelet": wavelet,
        "fresh": {"seed": seed, "whitening_images": len(images)},
        "fingerprint": fingerprint(variables),
    }
    return LoadedDecoder(variables, bits, wavelet, meta, Path(FRESH))


def shipped_decoder_path(bits: int) -> Path:
    """Path of the decoder shipped inside the package for ``bits`` (:data:`SHIPPED_BITS`)."""
    if bits not in SHIPPED_BITS:
        raise MnerfError(
            f"no shipped decoder for {bits} bits (shipped: {', '.join(map(str, SHIPPED_BITS))}); "
            f"train one with `mnerf train-decoder --bits {bits} --out DIR`"
        )
    return ASSET_DIR / f"hidden_l{bits}.npz"


def shipped_encoder_path(bits: int) -> Path | None:
    """The HiDDeN encoder shipped with the ``bits`` decoder (trained against it, which stays frozen), or None
    when the package has none for it."""
    path = shipped_decoder_path(bits).with_name(f"hidden_l{bits}_encoder.npz")
    return path if path.is_file() else None


def shipped_check_path(bits: int) -> Path:
    """Path of the small fixed batch of encoded images (uint8) shipped with the ``bits`` decoder."""
    return shipped_decoder_path(bits).with_name(f"hidden_l{bits}_check.npz")


def load_shipped_decoder(bits: int = 16) -> LoadedDecoder:
    return load_decoder(shipped_decoder_path(bits), expect_bits=bits)
