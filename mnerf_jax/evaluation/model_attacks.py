"""Robustness of a watermarked run to attacks on the model (``mnerf attack --model-suite``): the attacker
holds the watermarked field and changes its parameters (:mod:`mnerf_jax.watermark.model_attacks`: noise,
quantisation, pruning, fine-tuning), then renders.

After each attack every ID renders the same evenly spread views of the split; the renders are rounded to
8 bits (what a verifier receives, as the PNGs ``mnerf evaluate`` saves) and scored exactly as the image
attacks score them (:func:`evaluation.attacks.score`: mean and worst-ID bit accuracy, best match right, the
right ID named). False claims are measured on the clean model's renders of the same views: the attacker's
changes are to the watermarked field, the clean model is not attacked, so its renders (the PNGs
``mnerf evaluate`` saved in ``eval-<split>/clean/``, else rendered once from the source run) are one set of
negatives, and every row reports the same false-claim figures.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import view_indices
from mnerf_jax.data.images import to_uint8
from mnerf_jax.evaluation import attacks as image_attacks
from mnerf_jax.evaluation import watermarked as wm_eval
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import decision
from mnerf_jax.watermark import model_attacks as M
from mnerf_jax.watermark import run as wm_run

NO_ATTACK = "none"


def model_attacks_path(run_dir: str | Path, split: str, suite: str) -> Path:
    """Where the scores go: ``WMRUN/eval-<split>-model-attacks-<suite>.json``."""
    return Path(run_dir) / f"eval-{split}-model-attacks-{suite}.json"


def _decode(decoder: Any, wm: Any, images: np.ndarray) -> np.ndarray:
    """Logits ``[B, L]`` of uint8 images ``[B, H, W, 3]`` as the run's decoder reads them."""
    return wm_eval.decode_renders(decoder, wm, images.astype(np.float32) / np.float32(255.0), batch=32)


def clean_negatives(
    run: runs.LoadedRun, split: str, names: Sequence[str], cameras: Any, indices: Sequence[int]
) -> tuple[np.ndarray | None, str | None]:
    """``(uint8 [V, H, W, 3], "saved" | "rendered")``: the clean model's renders of the views ``names``
    (``cameras[indices]``), the saved PNGs when every one is there, else rendered from the source run;
    ``(None, None)`` when the source run is gone too."""
    saved = image_attacks.saved_clean(run.run_dir, split, names)
    if saved is not None:
        return saved, "saved"
    source = wm_eval.clean_model(run)
    if source is None:
        return None, None
    return np.stack([to_uint8(x) for x in runs.render_views(source, cameras, indices)]), "rendered"


def evaluate_model_attacks(
    run_dir: str | Path,
    split: str = "test",
    suite: str = "model",
    views: int | None = None,
    *,
    finetune_steps: Sequence[int] = M.FINETUNE_STEPS,
    held_id: int = 0,
    seed: int = 0,
    data_path: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Score a watermarked run under the model attacks of ``suite`` (:func:`model_attacks.model_suite`);
    writes and returns :func:`model_attacks_path`'s JSON (nothing is written unless every row is scored).

    ``views``: evenly spread views of the split (None or 0: all); ``finetune_steps``: the fine-tuning rows
    (one trajectory, snapshots at each count); ``held_id``: the ID the fine-tuning attacker renders; ``seed``:
    the noise and the fine-tuning's rays. Keys as :func:`evaluation.attacks.evaluate_attacks` writes them
    (``attacks`` rows with ``score`` + ``family``, ``description``, ``value`` and the false claims; a
    fine-tuning row also its last step's training PSNR, ``train_psnr``, in dB), plus
    ``model: true``, ``held_id``, ``finetune_steps``, ``clean_source`` (``saved``, ``rendered`` or None)
    and ``threshold_source``.
    """
    run_dir = Path(run_dir)
    chosen = M.model_suite(suite, finetune_steps)  # a bad suite or step count fails before any work
    run = wm_run.load_watermarked_run(run_dir)
    keys, decoder = run.extras["keys"], run.extras["decoder"]
    wm = run.config.watermark
    rule = decision.decision_rule(run_dir, wm.reading, decoder.fingerprint)
    tuned = [a for a in chosen if a.family == "finetune"]
    scene = run.load_scene(data_path, splits=(split, "train") if tuned else (split,))
    part = scene.split(split)
    indices = view_indices(len(part), views)
    names = [part.names[i] for i in indices]
    messages = np.asarray(keys.messages, np.float32)
    n, v = int(keys.num_ids), len(indices)
    if tuned and not 0 <= int(held_id) < n:
        raise MnerfError(f"--finetune-id {held_id} is outside [0, {n}): {run_dir} has {n} IDs")
    rule_args = (rule.threshold, rule.test)
    clean, clean_source = clean_negatives(run, split, names, part.cameras, indices)
    claims = {}
    if clean is not None:
        claims = image_attacks.false_claims(_decode(decoder, wm, clean), messages, *rule_args)

    bar = None
    if progress:
        bar = tqdm(total=len(chosen) + 1, unit="attack", desc=f"model attacks ({suite})", dynamic_ncols=True)
    rows: dict[str, Any] = {}

    placement = jax.tree.leaves(run.params)[0].sharding

    def score_params(name: str, params: Any, attack: M.ModelAttack | None) -> None:
        # Placed as the loaded params are: jit compiles again for arguments placed differently.
        params = jax.device_put(params, placement)
        renders = wm_run.render_every_id(dataclasses.replace(run, params=params), part.cameras, indices)
        images = np.concatenate([to_uint8(renders[k]) for k in range(n)])
        row = image_attacks.score(_decode(decoder, wm, images).reshape(n, v, -1), messages, *rule_args)
        if attack is not None:
            row.update(family=attack.family, value=attack.value, description=attack.description)
        row.update(claims)
        rows[name] = row
        if bar is not None:
            bar.update(1)
            bar.set_postfix(attack=name, bits=f"{row['bit_accuracy_mean']:.3f}")

    try:
        score_params(NO_ATTACK, run.params, None)
        for attack in chosen:
            if attack.family != "finetune":
                score_params(attack.name, attack.apply(run.params, seed), attack)
        if tuned:
            steps_bar = None
            if bar is not None:
                most = int(max(a.value for a in tuned))
                steps_bar = tqdm(total=most, unit="step", desc="fine-tune", leave=False, dynamic_ncols=True)
            psnr: dict[int, float] = {}

            def on_step(k: int, metrics: dict[str, float]) -> None:
                psnr[k] = float(metrics["psnr"])
                if steps_bar is not None:
                    steps_bar.update(1)

            try:
                snapshots = M.finetune_params(
                    run, scene, [int(a.value) for a in tuned], held_id, seed, on_step=on_step
                )
            finally:
                if steps_bar is not None:
                    steps_bar.close()
            for attack in tuned:
                score_params(attack.name, snapshots[int(attack.value)], attack)
                rows[attack.name]["train_psnr"] = psnr.get(int(attack.value))  # the last step's batch
    finally:
        if bar is not None:
            bar.close()
    order = [NO_ATTACK, *(a.name for a in chosen)]
    attacked = [rows[name] for name in order[1:]]
    result = {
        "split": split,
        "suite": suite,
        "model": True,
        "strength": None,
        "named": False,
        "views": v,
        "view_names": names,
        "num_ids": n,
        "bits": int(messages.shape[1]),
        "seed": seed,
        "test": rule.test,
        "threshold": rule.threshold,
        "threshold_source": rule.source,
        "step": run.step,
        "held_id": int(held_id),
        "finetune_steps": sorted(int(a.value) for a in tuned),
        "order": order,
        "attacks": {name: rows[name] for name in order},
        "skipped": {},
        "false_claims_measured": clean is not None,
        "clean_source": clean_source,
        "mean_over_attacks": {
            k: float(np.mean([s[k] for s in attacked])) for k in image_attacks.MEANS if k in rows[NO_ATTACK]
        }
        if attacked
        else None,
    }
    rundir.write_json_atomic(model_attacks_path(run_dir, split, suite), result)
    return result
