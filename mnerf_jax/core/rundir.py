"""Run directories: what they hold, and refusing to overwrite another run.

A run directory holds::

    RUN/run.json        {"kind": "tensorf" | "multinerf", "version": 1, "fingerprint": ..., "data": PATH}
    RUN/config.json     the resolved config
    RUN/checkpoints/    orbax checkpoints (``checkpoint.CheckpointStore``)
    RUN/metrics.json    written by ``mnerf fit`` at the end
    RUN/tb/             TensorBoard scalars
    RUN/scene_transform.json  a normalised capture's transform from the file's frame to the scene's
                        (nerfstudio's ``transform`` [3, 4] and ``scale``; ``data.SceneTransform``)
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from mnerf_jax import __version__
from mnerf_jax.core.checkpoint import config_fingerprint, fingerprint_differences
from mnerf_jax.core.config import Config, ConfigError, from_dict
from mnerf_jax.core.errors import MnerfError

RUN_MARKER = "run.json"
CONFIG_FILE = "config.json"
SCENE_TRANSFORM_FILE = "scene_transform.json"
RUN_FORMAT_VERSION = 1
TENSORF_KIND = "tensorf"
WATERMARK_KIND = "multinerf"


class RunError(MnerfError):
    """A run directory that is missing, holds something else, or cannot be loaded."""


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename (never a half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON to ``path`` atomically (:func:`write_text_atomic`)."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True, allow_nan=True) + "\n")


def read_marker(run_dir: str | Path) -> dict[str, Any] | None:
    """``run.json`` of a directory, None when it has none; RunError when it is unreadable."""
    path = Path(run_dir) / RUN_MARKER
    if not path.is_file():
        return None
    try:
        marker = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise RunError(f"{path}: unreadable run marker ({err})") from None
    if not isinstance(marker, dict) or "kind" not in marker:
        raise RunError(f"{path}: not a mnerf run marker")
    return marker


def require_marker(run_dir: str | Path) -> dict[str, Any]:
    """``run.json`` of a run directory; RunError when the directory is missing or holds no run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"--run {run_dir}: no such directory")
    marker = read_marker(run_dir)
    if marker is None:
        raise RunError(f"{run_dir} is not a mnerf run (no {RUN_MARKER})")
    return marker


def with_full_size_reads(values: dict[str, Any]) -> dict[str, Any]:
    """A watermarked run's saved config, with ``watermark.reading.max_side`` 0 where it does not name it:
    runs embedded before the setting existed read every image at its own size."""
    wm = values.get("watermark")
    if not isinstance(wm, dict):
        return values
    reading = wm.get("reading")
    if isinstance(reading, dict):
        if "max_side" in reading:
            return values
        return {**values, "watermark": {**wm, "reading": {**reading, "max_side": 0}}}
    return {**values, "watermark": {**wm, "read_max_side": 0}}  # the flat layout before the sections


def read_run_config(run_dir: str | Path) -> Config:
    """The resolved config saved in ``RUN/config.json``."""
    path = Path(run_dir) / CONFIG_FILE
    try:
        values = json.loads(path.read_text())
        marker = read_marker(run_dir)
        if marker is not None and marker.get("kind") == WATERMARK_KIND:
            values = with_full_size_reads(values)
        return from_dict(values)
    except FileNotFoundError:
        raise RunError(f"{run_dir}: no {CONFIG_FILE}; is this a mnerf run directory?") from None
    except (json.JSONDecodeError, ConfigError) as err:
        raise RunError(f"{path}: unreadable config ({err})") from None


def prepare_output(out: str | Path, config: Config, *, resume: bool, kind: str = TENSORF_KIND) -> bool:
    """Check that ``out`` may receive this run; True when it continues a run already there.

    Refused (RunError, nothing written): ``out`` is a file; ``out`` holds files but no run; it holds
    a run of another kind or config; it holds this very run and ``resume`` is not set.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunError(f"--out {out} is a file, not a directory")
    if not out.exists() or not any(out.iterdir()):
        return False
    marker = read_marker(out)
    if marker is None:
        raise RunError(f"--out {out} is not empty and holds no mnerf run; choose a new or empty directory")
    if marker.get("kind") != kind:
        raise RunError(
            f"--out {out} holds a {marker.get('kind')!r} run, not a {kind!r} one; choose another directory"
        )
    if marker.get("fingerprint") != config_fingerprint(config):
        try:
            diffs = "; ".join(fingerprint_differences(read_run_config(out).to_dict(), config))
        except RunError:
            diffs = "its config.json is unreadable"
        # No differences under another digest: written before a field became bookkeeping.
        if diffs:
            raise RunError(f"--out {out} holds another run ({diffs}); choose another directory")
    if not resume:
        raise RunError(f"--out {out} already holds this run; pass --resume to continue it")
    return True


def write_run_files(
    out: str | Path,
    config: Config,
    *,
    data: str | Path | None,
    kind: str = TENSORF_KIND,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write ``config.json`` and the ``run.json`` marker (config first: a marker implies a config)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / CONFIG_FILE, config.to_dict())
    marker = {
        "kind": kind,
        "version": RUN_FORMAT_VERSION,
        "mnerf_version": __version__,
        "fingerprint": config_fingerprint(config),
        "config_name": config.name,
        "data": None if data is None else str(Path(data).expanduser().resolve()),
        **(extra or {}),
    }
    write_json_atomic(out / RUN_MARKER, marker)
