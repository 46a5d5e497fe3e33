"""Robustness of a watermarked run: bit accuracy, identification and false claims of its evaluated renders
under attack (``mnerf attack``).

``mnerf evaluate`` saves every ID's render of every evaluated view as an 8-bit PNG
(``WMRUN/eval-<split>/id<K>/<view>.png``) and the clean model's render of each (``eval-<split>/clean/``).
This module reads those files back, applies each attack of :mod:`mnerf_jax.imaging.attack_suites` (a suite,
or attacks named one by one; each attack's output is 8-bit, what a verifier receives), decodes the results
with the run's decoder (and its read window, which finds the object in an image of any size) and scores them
as evaluation scores the renders: mean and worst-ID bit accuracy, best-matching key right, and named (the
run's test and threshold). The clean renders meet the same attack (the same seed: the same parameters per
view) and are scored for false claims: the share of them the decision names as some key. ``"none"`` is the
PNGs as saved, the row ``eval-<split>.json`` reports as ``bit_accuracy_png_mean``. With a geometry search
(``reader.geometry_search``: ``--search``, or the run's ``watermark.reading.search``) every row is also read
with the search, its p-values corrected over candidates × keys, the clean renders' false claims included.

Reading saved files rather than rendering again keeps this cheap (no field is loaded) and scores exactly the
images the evaluation scored.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import view_indices
from mnerf_jax.data.images import to_uint8
from mnerf_jax.evaluation import watermarked as wm_eval
from mnerf_jax.imaging import attack_suites, augment
from mnerf_jax.imaging.attack_suites import Attack
from mnerf_jax.reader import extract, geometry_search, read_window
from mnerf_jax.reader.identification import (
    Identification,
    bit_accuracy,
    false_detection_summary,
    identify_logits,
    logits_to_bits,
)
from mnerf_jax.watermark import decision
from mnerf_jax.watermark import run as wm_run

NO_ATTACK = "none"
CLEAN_FOLDER = wm_eval.CLEAN_FOLDER
MEANS = (
    "bit_accuracy_mean",
    "bit_accuracy_min",
    "identification_accuracy",
    "verified_identification_accuracy",
    "false_claim_rate",
)


def attacks_path(run_dir: str | Path, split: str, suite: str | None = None) -> Path:
    """Where the scores go: ``eval-<split>-attacks-<suite>.json``, or ``eval-<split>-attacks.json`` for
    attacks named one by one (and the 14 augmentations at one strength, the default)."""
    return Path(run_dir) / (f"eval-{split}-attacks-{suite}.json" if suite else f"eval-{split}-attacks.json")


def _load_pngs(files: Sequence[Path]) -> np.ndarray:
    """uint8 ``[V, H, W, 3]`` of 8-bit PNG files (exact: ``to_uint8`` undoes ``load_image``'s /255)."""
    return np.stack([to_uint8(extract.load_image(f)) for f in files])


def saved_renders(
    run_dir: Path, split: str, views: int | None = None
) -> tuple[dict[str, Any], list[str], np.ndarray]:
    """``(eval-<split>.json, view names, renders uint8 [N, V, H, W, 3])``: every ID's saved PNGs of the
    evaluated views, ``views`` of them evenly spread (None or 0: all). A clear error where the evaluation,
    or one of its files, is missing."""

    path = run_dir / f"eval-{split}.json"
    if not path.is_file():
        raise MnerfError(
            f"{run_dir} has no {path.name}: run `mnerf evaluate --run {run_dir} --split "
            f"{split}` first (it saves the renders this reads)"
        )
    try:
        result = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise MnerfError(f"{path} is not valid JSON ({err}); evaluate again") from None
    names = list(result.get("view_names") or [])
    if not names:
        raise MnerfError(f"{path} lists no view names (written by an older mnerf evaluate); evaluate again")
    chosen = [names[i] for i in view_indices(len(names), views)]
    folder = run_dir / f"eval-{split}"
    renders = []
    for n in range(int(result["num_ids"])):
        files = [folder / f"id{n}" / f"{name}.png" for name in chosen]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise MnerfError(
                f"{len(missing)} saved render(s) of ID {n} are missing (first: {missing[0]}); "
                f"run `mnerf evaluate --run {run_dir} --split {split}` again"
            )
        renders.append(_load_pngs(files))
    return result, chosen, np.stack(renders)


def saved_clean(run_dir: Path, split: str, names: Sequence[str]) -> np.ndarray | None:
    """The clean model's saved renders uint8 ``[V, H, W, 3]`` of the views ``names``, or None when any is
    missing (an evaluation written before they were saved, or a run whose source run is gone)."""
    files = [run_dir / f"eval-{split}" / CLEAN_FOLDER / f"{name}.png" for name in names]
    return _load_pngs(files) if all(f.is_file() for f in files) else None


def score(
    logits: np.ndarray,
    messages: np.ndarray,
    threshold: float,
    test: str,
    ident: Identification | None = None,
) -> dict[str, Any]:
    """Scores of attacked renders' ``logits [N, V, L]`` (ID n's renders in row n) against the keys
    ``messages [N, L]``: mean and worst-ID bit accuracy, best match right, named right. ``ident``: their
    identification when made otherwise (a search's, corrected for its reads; default: of these logits)."""

    n, v, bits = logits.shape
    per_id = bit_accuracy(logits_to_bits(logits), messages[:, None]).mean(axis=1)
    if ident is None:
        ident = identify_logits(logits.reshape(n * v, bits), messages, threshold, test)
    truth = np.repeat(np.arange(n), v)
    return {
        "bit_accuracy_mean": float(per_id.mean()),
        "bit_accuracy_min": float(per_id.min()),
        "bit_accuracy_per_id": per_id.tolist(),
        "identification_accuracy": float((ident.best_id == truth).mean()),
        "verified_identification_accuracy": float((ident.decision == truth).mean()),
    }


def false_claims(
    logits: np.ndarray,
    messages: np.ndarray,
    threshold: float,
    test: str,
    ident: Identification | None = None,
) -> dict[str, Any]:
    """How the decision names the clean model's attacked renders ``logits [V, L]``: ``false_claim_rate``
    (named as any key under ``test``; ``..._by_test``) and ``claimed_per_id [N]``. ``ident``: as
    :func:`score`."""
    if ident is None:
        ident = identify_logits(logits, messages, threshold, test)
    summary = false_detection_summary(ident, len(messages))
    return {
        "false_claim_rate": summary["false_detection_rate"],
        "false_claim_rate_by_test": summary["false_detection_rate_by_test"],
        "claimed_per_id": summary["claimed_per_id"],
    }


def choose_attacks(
    suite: str | None = None,
    names: Sequence[str] | None = None,
    strength: str | None = None,
    regen: str | None = None,
    codec_models: Sequence[str] = (),
) -> tuple[list[Attack], str | None]:
    """``(attacks, suite label)`` to run, checked before any work: a ``suite``; or ``names``
    (:func:`attack_suites.resolve`: registry names, or augmentation names at ``strength``); or, with
    neither, the 14 augmentations at ``strength`` (default low; the command's old default). ``regen``
    (``module:function``) adds that hook's row and ``codec_models`` (``ARCHITECTURE=PATH``: CompressAI's
    codecs from the user's weights, :func:`attack_suites.codec_model_attack`) one row each, to the ``regen``
    suite's stand-ins when nothing else is chosen. The label names the output file (None:
    ``eval-<split>-attacks.json``)."""
    if suite and names:
        raise MnerfError("--suite and --attacks choose the attacks two ways: give one")
    if suite and strength:
        raise MnerfError(
            "--strength sets the 14 augmentations' strength without --suite (paper has all three)"
        )
    if strength and strength not in augment.STRENGTHS:
        raise MnerfError(f"unknown attack strength {strength!r} (known: {', '.join(augment.STRENGTHS)})")
    hook = [attack_suites.hook_attack(regen)] if regen else []
    hook += [attack_suites.codec_model_attack(spec) for spec in codec_models]
    if suite:
        chosen, label = attack_suites.suite(suite), suite
    elif names:
        chosen, label = attack_suites.resolve(names, strength or "low"), None
    elif hook:
        chosen, label = attack_suites.suite("regen"), "regen"
    else:
        return attack_suites.resolve(augment.AUGMENTATION_NAMES, strength or "low"), None
    repeated = sorted({a.name for a in hook if [b.name for b in chosen + hook].count(a.name) > 1})
    if repeated:
        raise MnerfError(f"attack rows named twice: {', '.join(repeated)} (give each weights file once)")
    return chosen + hook, label


def _read(decoder: Any, wm: Any, images: np.ndarray, search: geometry_search.GeometrySearch) -> np.ndarray:
    """Logits ``[B, C, L]`` of uint8 images ``[B, H, W, 3]`` as the run's decoder reads them: the search's C
    candidate reads, the plain read first (C = 1 without a search)."""
    x = images.astype(np.float32) / np.float32(255.0)
    if not search.active:
        return wm_eval.decode_renders(decoder, wm, x, batch=32)[:, None]
    reading = read_window.of_config(wm.reading)
    return geometry_search.search_logits(decoder.variables, x, search, decoder.wavelet, 32, reading)


def _scored(
    reads: np.ndarray,
    clean: np.ndarray | None,
    messages: np.ndarray,
    threshold: float,
    test: str,
    search: geometry_search.GeometrySearch,
) -> dict[str, Any]:
    """One row: the plain read's scores of ``reads [N, V, C, L]`` (and false claims of the clean renders'
    ``clean [V, C, L]``), and with a search its scores as ``row["search"]``, with how often each candidate
    was kept (``candidates_kept``, by label)."""
    n, v = reads.shape[:2]
    row = score(reads[:, :, 0], messages, threshold, test)
    if clean is not None:
        row.update(false_claims(clean[:, 0], messages, threshold, test))
    if search.active:
        kept = geometry_search.identify(
            reads.reshape(n * v, *reads.shape[2:]), messages, search.candidates(), threshold, test
        )
        searched = score(kept.logits.reshape(n, v, -1), messages, threshold, test, kept.identification)
        labels = [c.label for c in kept.chosen_candidates()]
        searched["candidates_kept"] = {label: labels.count(label) for label in dict.fromkeys(labels)}
        if clean is not None:
            kept_clean = geometry_search.identify(clean, messages, search.candidates(), threshold, test)
            searched.update(
                false_claims(kept_clean.logits, messages, threshold, test, kept_clean.identification)
            )
        row["search"] = searched
    return row


def _means(rows: Sequence[dict[str, Any]]) -> dict[str, float] | None:
    """Each of :data:`MEANS`'s scores averaged over ``rows`` (None without rows)."""
    if not rows:
        return None
    return {k: float(np.mean([s[k] for s in rows])) for k in MEANS if k in rows[0]}


def evaluate_attacks(
    run_dir: str | Path,
    split: str = "test",
    strength: str | None = None,
    names: Sequence[str] | None = None,
    views: int | None = None,
    seed: int = 0,
    progress: bool = False,
    *,
    suite: str | None = None,
    regen: str | None = None,
    codec_models: Sequence[str] = (),
    search: str | None = None,
    search_scales: tuple[float, ...] | None = None,
    search_degrees: tuple[float, ...] | None = None,
) -> dict[str, Any]:
    """Score a watermarked run's saved evaluation PNGs under each attack (:func:`choose_attacks`); writes
    and returns :func:`attacks_path`'s JSON. ``"none"`` is always scored first; a hook's row runs next, so
    a hook that fails fails before the rest; nothing is written unless every row is scored.

    ``views``: evenly spread views of the evaluation's (None or 0: all). Every attack draws from ``seed``
    (:mod:`imaging.attack_suites`), the same for every ID and for the clean renders.
    Keys: ``split``, ``suite``, ``strength`` (the augmentations' strength without a suite), ``named``
    (attacks named one by one), ``views``, ``view_names``,
    ``num_ids``, ``bits``, ``seed``, ``test``, ``threshold`` (the run's calibrated one where it has one,
    ``threshold_source``: ``watermark.decision``), ``step``, ``order`` (the rows in order),
    ``attacks`` ``{name: score(...) + family, description, and with the clean renders false_claims(...)}``,
    ``skipped`` ``{name: why}`` (attacks that cannot run here, such as WebP without libwebp),
    ``false_claims_measured`` and ``mean_over_attacks`` (each score's mean over the attacks, "none" left out).
    ``search`` (default: the run's ``watermark.reading.search``) with its grids: every row is read plainly and
    with that geometry search (:func:`_scored`; ``search`` then describes it, and ``mean_over_attacks_search``
    averages the searched rows).
    """
    run_dir = Path(run_dir)
    attacks, label = choose_attacks(suite, names, strength, regen, codec_models)
    keys, decoder = wm_run.load_keys_and_decoder(run_dir)
    saved = rundir.read_run_config(run_dir).watermark
    rule = decision.decision_rule(run_dir, saved.reading, decoder.fingerprint)
    threshold, test = rule.threshold, rule.test
    searched = geometry_search.of_config(saved.reading, search, search_scales, search_degrees)
    evaluation, chosen, renders = saved_renders(run_dir, split, views)
    clean = saved_clean(run_dir, split, chosen)
    messages = np.asarray(keys.messages, np.float32)
    if renders.shape[0] != messages.shape[0]:
        raise MnerfError(
            f"{run_dir}'s evaluation has {renders.shape[0]} IDs but its keys.json {messages.shape[0]}"
        )
    n, v = renders.shape[:2]
    skipped = {a.name: a.unavailable for a in attacks if a.unavailable}
    runnable = [a for a in attacks if not a.unavailable]
    # A user's hook first: a failing model fails before the rest is spent.
    todo = sorted(runnable, key=lambda a: a.family != "hook")
    bar = None
    if progress:
        bar = tqdm(
            total=len(todo) + 1, unit="attack", desc=f"attacks ({label or 'named'})", dynamic_ncols=True
        )
    rows: dict[str, Any] = {}
    try:
        for attack in [None, *todo]:
            name = NO_ATTACK if attack is None else attack.name
            # One ID at a time (the augmentations' median filter stacks k² copies of its batch); the same
            # seed for each, so every ID meets the same parameters per view.
            hit = [renders[k] if attack is None else attack(renders[k], seed) for k in range(n)]
            reads = _read(decoder, saved, np.concatenate(hit), searched)
            clean_reads = None
            if clean is not None:
                clean_reads = _read(
                    decoder, saved, clean if attack is None else attack(clean, seed), searched
                )
            row = _scored(
                reads.reshape(n, v, *reads.shape[1:]), clean_reads, messages, threshold, test, searched
            )
            if attack is not None:
                row.update(family=attack.family, description=attack.description)
            rows[name] = row
            if bar is not None:
                bar.update(1)
                bar.set_postfix(attack=name, bits=f"{row['bit_accuracy_mean']:.3f}")
    finally:
        if bar is not None:
            bar.close()
    order = [NO_ATTACK, *(a.name for a in runnable)]
    rows = {name: rows[name] for name in order}  # the hook back in its place
    attacked = [rows[name] for name in order[1:]]
    result = {
        "split": split,
        "suite": label,
        "strength": None if label else (strength or "low"),
        "named": bool(names) and not label,
        "views": v,
        "view_names": chosen,
        "num_ids": n,
        "bits": int(messages.shape[1]),
        "seed": seed,
        "test": test,
        "threshold": threshold,
        "threshold_source": rule.source,
        "step": evaluation.get("step"),
        "order": order,
        "attacks": rows,
        "skipped": skipped,
        "false_claims_measured": clean is not None,
        "mean_over_attacks": _means(attacked),
        "search": searched.describe() if searched.active else None,
        "mean_over_attacks_search": _means([s["search"] for s in attacked]) if searched.active else None,
    }
    rundir.write_json_atomic(attacks_path(run_dir, split, label), result)
    return result
