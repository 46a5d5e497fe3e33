"""Running a study: fit each scene once, then embed, evaluate and attack each cell, skipping what is done.

The study folder::

    DIR/study.json                  the spec the study was run with (name, path, tables)
    DIR/fits/<scene>-<hash>/        each scene's fit (a run directory), shared by its cells
    DIR/cells/<cell-id>/wm/         the cell's watermarked run (eval-<split>.json, its PNGs, attacks)
    DIR/cells/<cell-id>/stages/     one record per finished stage: embed, evaluate, attack-<suite>
    DIR/cells/<cell-id>/result.json written last, atomically: the cell is done
    DIR/cells/<cell-id>/error.json  a failed cell's error (the study goes on; a later run retries it)
    DIR/results.{json,csv,md}       the table (results.py), rewritten after every cell
    DIR/report.md, DIR/figures/     the report (report.py), written by ``mnerf study`` when the run ends

A killed study loses at most the stage it was in: a fit and an embedding resume from their last checkpoint
(``mnerf fit --resume``, ``mnerf embed --resume``), an evaluation or attack suite is redone, and a stage
whose record exists is not run again. A fit in progress is held under a file lock (``fcntl.flock``), so
shards sharing a folder on one machine (or a file system that honours POSIX locks) fit a scene once.

Peak memory is ``resource.getrusage(RUSAGE_SELF).ru_maxrss``: the process's peak resident set so far,
recorded before and after each cell. It is the cell's own peak when it exceeds the figure before it;
otherwise an earlier cell (or fit) of the same process peaked higher and the cell's peak is unknown but no
larger. One process per cell (``--only CELL``) measures each cell alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import resource
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from mnerf_jax.core import machine, rundir
from mnerf_jax.core.config import Config
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.evaluation import attacks as wm_attacks
from mnerf_jax.evaluation import watermarked as wm_eval
from mnerf_jax.reader import decoder_io
from mnerf_jax.study import cost, grid, results
from mnerf_jax.study.spec import StudySpec
from mnerf_jax.watermark import embed as wm_embed
from mnerf_jax.watermark import run as wm_run

STUDY_FILE = "study.json"
STUDY_KIND = "study"
FIT_DONE = "metrics.json"  # written by fit_run at its end

# (config, scene folder or None, run folder, resume, quiet) -> None: the command line's ``fit_run``, handed
# down so that this layer needs nothing from the one above it.
FitScene = Callable[[Config, Path | None, Path, bool, bool], Any]


class StudyError(MnerfError):
    """A study folder that cannot take this study, or a selection of no cells."""


@dataclasses.dataclass(frozen=True)
class StudySummary:
    """What :func:`run_study` did: cells selected, run now, found done, failed (``(id, error)``)."""

    out: Path
    selected: int
    ran: int
    skipped: int
    failed: tuple[tuple[str, str], ...]
    rows: tuple[dict[str, Any], ...]


def peak_rss_mb() -> float:
    """The process's peak resident set so far in MiB (Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2.0**20 if sys.platform == "darwin" else 1024.0), 1)


def param_counts(params: Mapping[str, Any]) -> dict[str, int]:
    """Parameter counts and bytes of a watermarked run's params: the whole, and the watermark's part
    (``params["wm"]`` and the colour MLP's extra rows); the TensoRF's is the rest."""

    def count(tree: Any) -> tuple[int, int]:
        leaves = jax.tree.leaves(tree)
        return sum(int(np.size(x)) for x in leaves), sum(int(np.size(x)) * x.dtype.itemsize for x in leaves)

    whole, whole_bytes = count(params)
    mlp = params.get("mlp", {})
    extra = {k: mlp[k] for k in ("out_extra", "in_extra") if k in mlp}
    wm, wm_bytes = count({"wm": params.get("wm", {}), "extra": extra})
    return {"count": whole, "bytes": whole_bytes, "watermark_count": wm, "watermark_bytes": wm_bytes}


def _plain(value: Any) -> Any:
    """``value`` as it reads back from JSON (tuples become lists), so that saved settings compare equal."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def check_decoder(spec: StudySpec, bits: int) -> None:
    """MnerfError, in one line, when the cell's decoder is missing: no file, or none shipped for ``bits``."""
    path = spec.decoder_path(bits)
    if path is None:
        decoder_io.shipped_decoder_path(bits)  # raises for a bit length without a shipped decoder
    elif str(path) != decoder_io.FRESH and not path.is_file():
        raise MnerfError(f"no decoder file {path} for {bits} bits (the spec's [decoders] table)")


def stage(folder: Path, name: str, settings: Mapping[str, Any], work: Callable[[], dict[str, Any]]) -> dict:
    """Run ``work`` unless ``folder/stages/<name>.json`` records it done under ``settings``; returns the
    record (``work``'s dict, ``settings`` and its ``seconds``), written atomically once it ends."""
    path = folder / "stages" / f"{name}.json"
    settings = _plain(dict(settings))
    record = results.read_json(path)
    if record is not None and record.get("settings") == settings:
        return record
    t0 = time.perf_counter()
    record = {**work(), "settings": settings, "seconds": round(time.perf_counter() - t0, 2)}
    rundir.write_json_atomic(path, record)
    return record


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file closes
        yield


@dataclasses.dataclass
class _Context:
    spec: StudySpec
    out: Path
    fit_scene: FitScene
    progress: bool
    fit_errors: dict[str, str] = dataclasses.field(default_factory=dict)


def ensure_fit(ctx: _Context, cell: grid.Cell) -> tuple[Path, dict[str, Any]]:
    """The fitted run of the cell's scene (fitted now, or resumed, when not done): ``(folder, record)``."""
    scene = cell.scene
    given = scene.fit_path()
    if given is not None:
        return given, {"fit_id": None, "seconds": None}
    key = grid.fit_id(scene)
    if key in ctx.fit_errors:
        raise MnerfError(f"the fit of scene {scene.name} failed: {ctx.fit_errors[key]}")
    folder = ctx.out / results.FITS_DIR / key
    with _locked(ctx.out / results.FITS_DIR / f".{key}.lock"):
        if not (folder / FIT_DONE).is_file():
            if folder.is_dir() and any(folder.iterdir()) and rundir.read_marker(folder) is None:
                shutil.rmtree(folder)  # killed before its run files were written: start it cleanly
            resume = folder.is_dir() and rundir.read_marker(folder) is not None
            try:
                ctx.fit_scene(grid.fit_config(scene), scene.data_path(), folder, resume, not ctx.progress)
            except Exception as err:
                ctx.fit_errors[key] = _one_line(err)
                raise MnerfError(f"the fit of scene {scene.name} failed: {ctx.fit_errors[key]}") from err
    metrics = results.read_json(folder / FIT_DONE) or {}
    return folder, {"fit_id": key, "seconds": metrics.get("train_seconds")}


def _embed(ctx: _Context, cell: grid.Cell, source: Path, wm_dir: Path) -> dict[str, Any]:
    if wm_dir.is_dir() and any(wm_dir.iterdir()) and rundir.read_marker(wm_dir) is None:
        shutil.rmtree(wm_dir)  # killed before its run files were written: start it cleanly
    result = wm_embed.embed(
        source,
        wm_dir,
        cell.num_ids,
        cell.bits,
        preset=cell.method.preset_ref(),
        overrides=cell.embed_overrides(),
        decoder_path=ctx.spec.decoder_path(cell.bits),
        resume=rundir.read_marker(wm_dir) is not None if wm_dir.is_dir() else False,
        progress=ctx.progress,
    )
    params = result.state.params if result.state is not None else wm_run.load_watermarked_run(wm_dir).params
    return {
        "steps": result.steps,
        "stopped_by_budget": result.stopped_by_budget,
        "run_seconds": round(result.run_seconds, 2),  # the embedding over all its processes
        "params": param_counts(params),
        "config": rundir.read_run_config(wm_dir).to_dict(),  # the config the embedding ran with
    }


def _evaluate(ctx: _Context, wm_dir: Path) -> dict[str, Any]:
    m = ctx.spec.measure
    result = wm_eval.evaluate_watermarked_run(
        wm_dir, m.split, max_views=m.views or None, lpips_net=m.lpips, progress=ctx.progress
    )
    return {"result": {k: v for k, v in result.items() if k not in ("per_id", "view_names")}}


def _attack(ctx: _Context, wm_dir: Path, suite: str) -> dict[str, Any]:
    m = ctx.spec.measure
    result = wm_attacks.evaluate_attacks(
        wm_dir,
        m.split,
        suite,
        list(m.attack_names) or None,
        m.attack_views or None,
        m.attack_seed,
        progress=ctx.progress,
    )
    scores = {
        name: {k: v for k, v in s.items() if k != "bit_accuracy_per_id"}
        for name, s in result["attacks"].items()
    }
    return {"mean_over_attacks": result["mean_over_attacks"], "attacks": scores}


def run_cell(ctx: _Context, cell: grid.Cell) -> dict[str, Any]:
    """Fit (shared), embed, evaluate and attack one cell; writes and returns its ``result.json``."""
    rss_before = peak_rss_mb()
    folder = results.cell_dir(ctx.out, cell)
    # A cell that cannot run fails here, in one line, before any fit: its decoder, its config.
    check_decoder(ctx.spec, cell.bits)
    grid.embed_config(cell)
    source, fit = ensure_fit(ctx, cell)
    wm_dir = folder / "wm"
    m = ctx.spec.measure
    embed = stage(folder, "embed", {}, lambda: _embed(ctx, cell, source, wm_dir))
    evaluate = stage(
        folder,
        "evaluate",
        {"split": m.split, "views": m.views, "lpips": m.lpips, "embed_steps": embed["steps"]},
        lambda: _evaluate(ctx, wm_dir),
    )
    attack_settings = {
        "embed_steps": embed["steps"],
        "split": m.split,
        "names": m.attack_names,
        "views": m.attack_views,
        "seed": m.attack_seed,
    }
    attacks = {
        suite: stage(
            folder,
            f"attack-{suite}",
            {**attack_settings, "strength": suite},
            lambda s=suite: _attack(ctx, wm_dir, s),
        )
        for suite in m.attacks
    }
    result = {
        "cell_id": cell.id,
        "cell": cell.settings(),
        "measure": m.to_dict(),
        "fit": fit,
        "embed": embed,
        "evaluate": evaluate,
        "attacks": attacks,
        "peak_rss_mb": peak_rss_mb(),
        "peak_rss_before_mb": rss_before,
        "machine": machine.describe(),
    }
    rundir.write_json_atomic(folder / results.RESULT_FILE, result)
    (folder / results.ERROR_FILE).unlink(missing_ok=True)
    return result


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text if isinstance(err, MnerfError) else f"{type(err).__name__}: {text}"


def record_failure(out: Path, cell: grid.Cell, err: Exception) -> str:
    """Write the cell's ``error.json`` (its one-line error, and the traceback of an unexpected one)."""
    message = _one_line(err)
    rundir.write_json_atomic(
        results.cell_dir(out, cell) / results.ERROR_FILE,
        {
            "cell_id": cell.id,
            "error": message,
            "type": type(err).__name__,
            "traceback": None if isinstance(err, MnerfError) else traceback.format_exc(),
        },
    )
    return message


def prepare_study_dir(out: Path, spec: StudySpec, join: bool) -> None:
    """Check that ``out`` may hold this study (new, empty, or this study's own folder when ``join``) and
    record the spec in ``out/study.json``. StudyError, nothing written, otherwise."""
    if out.exists() and not out.is_dir():
        raise StudyError(f"--out {out} is a file, not a directory")
    marker = results.read_json(out / STUDY_FILE)
    if out.is_dir() and any(out.iterdir()):
        if marker is None or marker.get("kind") != STUDY_KIND:
            raise StudyError(f"--out {out} is not empty and holds no study; choose a new or empty directory")
        if marker.get("name") != spec.name:
            raise StudyError(f"--out {out} holds study {marker.get('name')!r}, not {spec.name!r}")
        if not join:
            raise StudyError(f"--out {out} already holds study {spec.name!r}; pass --resume to continue it")
    rundir.write_json_atomic(
        out / STUDY_FILE, {"kind": STUDY_KIND, "name": spec.name, "spec": str(spec.path)}
    )


def select_cells(spec: StudySpec, shard: tuple[int, int] | None, only: Sequence[str]) -> list[grid.Cell]:
    """The study's cells in ``shard`` (balanced by estimated cost over the whole grid) matching ``only``."""
    cells = grid.expand(spec)
    weights = cost.shard_weights(spec, cells) if shard is not None else None
    return grid.select(cells, shard, only, weights)


def run_study(
    spec: StudySpec,
    out: str | Path,
    fit_scene: FitScene,
    *,
    resume: bool = False,
    shard: tuple[int, int] | None = None,
    only: Sequence[str] = (),
    progress: bool = True,
    on_cell_done: Callable[[grid.Cell, str], None] | None = None,
) -> StudySummary:
    """Run the selected cells of ``spec`` into ``out`` (module docstring); returns what it did.

    ``shard`` ``(I, N)`` and ``only`` (globs on cell IDs) select the cells; a folder holding this study is
    continued with ``resume`` (or joined by a shard). A cell that fails is recorded with its error and the
    study goes on; an interrupt (KeyboardInterrupt) stops it, keeping what is done. ``on_cell_done(cell,
    status)`` is called after each cell ("done", "skipped", "failed").
    """
    out = Path(out)
    cells = select_cells(spec, shard, only)
    if not cells:
        raise StudyError(f"no cell of study {spec.name!r} is selected (--shard / --only)")
    prepare_study_dir(out, spec, join=resume or shard is not None)
    ctx = _Context(spec, out, fit_scene, progress)
    measure = spec.measure.to_dict()
    ran, skipped, failed = 0, 0, []
    bar = tqdm(
        total=len(cells), desc=f"study {spec.name}", unit="cell", disable=not progress, dynamic_ncols=True
    )
    try:
        for cell in cells:
            bar.set_postfix_str(cell.id)
            if results.finished_result(out, cell, measure) is not None:
                status = "skipped"
                skipped += 1
            else:
                try:
                    run_cell(ctx, cell)
                    status = "done"
                    ran += 1
                except Exception as err:  # a failing cell is recorded; KeyboardInterrupt stops the study
                    failed.append((cell.id, record_failure(out, cell, err)))
                    status = "failed"
                    tqdm.write(f"mnerf study: cell {cell.id} failed: {failed[-1][1]}", file=sys.stderr)
                results.write_tables(spec, out)
            bar.update(1)
            if on_cell_done is not None:
                on_cell_done(cell, status)
    finally:
        bar.close()
    rows = results.write_tables(spec, out)
    return StudySummary(out, len(cells), ran, skipped, tuple(failed), tuple(rows))
