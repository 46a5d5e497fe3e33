"""Evaluation of a watermarked run: bit accuracy per ID, image quality, identification of the ID.

Every ID renders every evaluated view; the renders are decoded as floats and again from 8-bit PNGs, and
named by ``identification.py`` (best-matching key, binomial and sign-flip p-values, the decision). The clean
model's renders of the same views show what an unwatermarked image decodes to.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
from tqdm import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.data import PATH_SPLIT
from mnerf_jax.data.images import round_to_8bit, to_uint8
from mnerf_jax.imaging import metrics
from mnerf_jax.reader import extract, geometry_search, read_window
from mnerf_jax.reader.identification import (
    bit_accuracy,
    false_detection_summary,
    identification_summary,
    identify,
    identify_logits,
    logits_to_bits,
)
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import decision
from mnerf_jax.watermark import run as wm_run

# The clean model's renders of the evaluated views, beside each ID's: WMRUN/eval-<split>/clean/<view>.png.
CLEAN_FOLDER = "clean"
# The render path's views evaluated when none are asked for (issue 52's spiral protocol): a spiral for
# forward-facing scenes, else an orbit; they have no ground truth, so quality is against the clean model only.
PATH_VIEWS = 30

# ------------------------------------------------------------------------------------------- evaluation


def decode_renders(decoder: Any, wm: Any, images: np.ndarray, batch: int = 16) -> np.ndarray:
    """Logits ``[B, L]`` of ``images`` as the run's decoder reads them (``wm``: its watermark config, for the
    read window)."""

    images = np.asarray(images, np.float32)
    return np.asarray(
        extract.decode(decoder.variables, images, decoder.wavelet, batch, read_window.of_config(wm.reading))
    )


def with_read_jitter(wm: Any, read_jitter: int | None) -> Any:
    """The watermark config ``wm`` read with ``read_jitter`` (None: as it is); MnerfError below 0."""
    if read_jitter is None:
        return wm
    reading = dataclasses.replace(wm.reading, jitter=read_window.check_jitter(read_jitter))
    return dataclasses.replace(wm, reading=reading)


def _save_png(path: Path, image: np.ndarray) -> None:
    """Write float ``image [H, W, 3]`` in [0, 1] as an 8-bit PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, to_uint8(image))


def _save_and_reload_png(path: Path, image: np.ndarray) -> np.ndarray:
    """Write an 8-bit PNG and read it back as float32 ``[H, W, 3]`` (what a viewer of the render gets)."""

    _save_png(path, image)
    return extract.load_image(path)


def _quality(preds: np.ndarray, targets: np.ndarray | None, lpips_net: str) -> dict[str, float | None]:
    if targets is None:  # no ground truth (the render path)
        return dict.fromkeys(("psnr", "ssim", "lpips"))

    out = metrics.image_metrics(preds, targets, lpips_net=lpips_net)
    return {k: out[k] for k in ("psnr", "ssim", "lpips")}


def evaluate_watermarked_run(
    run_dir: str | Path,
    split: str = "test",
    data_path: str | Path | None = None,
    *,
    max_views: int | None = None,
    threshold: float | None = None,
    test: str | None = None,
    lpips_net: str = "alex",
    save_pngs: bool = True,
    progress: bool = False,
    keep_renders: bool = False,
    read_jitter: int | None = None,
) -> dict[str, Any]:
    """Evaluate a watermarked run on ``split``; writes ``run_dir/eval-<split>.json`` and returns its dict.
    ``split`` :data:`PATH_SPLIT` evaluates novel views along the render path, which have no ground truth (the
    figures against it are None).

    For every evaluated view and every ID (up to ``wm_run.IDS_PER_RENDER`` IDs from one geometry pass): render
    (float, unclamped by nothing but the renderer's [0, 1]),
    decode, and again after a round trip through an 8-bit PNG (``run_dir/eval-<split>/id<K>/<view>.png``).
    The clean (pre-watermark) model of ``--from`` renders the same views (saved as 8-bit PNGs too, in
    ``eval-<split>/clean/``, for ``mnerf attack``'s false claims): quality is reported against the
    ground truth and against those clean renders, and the clean renders' bit accuracy against every key
    (chance: 50 %) and false-detection rate show what an unwatermarked image decodes to.

    Top-level keys: ``bit_accuracy_mean``, ``bit_accuracy_min`` (worst ID), ``bit_accuracy_png_mean``,
    ``psnr``, ``ssim``, ``lpips`` (vs ground truth), ``psnr_clean_model`` / ``ssim_clean_model`` /
    ``lpips_clean_model`` (vs the clean model's renders), ``clean_psnr`` (clean model vs ground truth),
    ``identification_accuracy`` (best-matching key by soft correlation is the rendered ID;
    ``identification_accuracy_hard``: by agreeing bits), ``verified_identification_accuracy`` (and its p-value
    under ``test``, default the run's ``watermark.reading.id_test``, passes ``threshold``, default the run's
    calibrated one or its ``watermark.reading.id_threshold`` (``watermark.decision``); under each test:
    ``verified_identification_accuracy_by_test``), ``misidentification_rate`` (named as another ID;
    ``..._by_test``), ``clean_bit_accuracy``, ``clean_false_detection_rate``
    (``..._by_test``; and per ID, which keys the false detections claimed: ``clean_false_detection_ids [N]``),
    ``num_ids``, ``bits``, ``split``, ``views``, ``per_id`` and ``identification`` (confusion matrices).
    With ``keep_renders`` the returned dict (not the file) also holds ``_renders`` ``{ID: [V, H, W, 3]}``,
    ``_clean`` and ``_gt``. ``read_jitter``: read with this jitter instead of the run's
    ``watermark.reading.jitter`` (recorded as ``read_jitter``).
    """

    run_dir = Path(run_dir)
    run = wm_run.load_watermarked_run(run_dir)
    keys = run.extras["keys"]
    decoder = run.extras["decoder"]
    wm = with_read_jitter(run.config.watermark, read_jitter)
    rule = decision.decision_rule(run_dir, wm.reading, decoder.fingerprint, threshold, test)
    thr, test = rule.threshold, rule.test
    path_views = PATH_VIEWS if split == PATH_SPLIT and not max_views else max_views
    cameras, indices, names, gt = run.split_views(split, data_path, path_views)
    n_ids, n_views = keys.num_ids, len(indices)

    bar = None
    if progress:
        bar = tqdm(total=n_views * (n_ids + 1), unit="render", desc=f"evaluate {split}", dynamic_ncols=True)
    # A view's renders count one per ID (a render of K IDs at once is 3K channels wide).
    tick = (lambda i, rgb: bar.update(rgb.shape[-1] // 3)) if bar is not None else None
    try:
        source = clean_model(run)
        clean = None
        if source is not None:
            clean = np.stack(runs.render_views(source, cameras, indices, on_view=tick))
        renders = wm_run.render_every_id(run, cameras, indices, on_view=tick)
    finally:
        if bar is not None:
            bar.close()

    png_dir = run_dir / f"eval-{split}"
    if save_pngs and clean is not None:
        # The clean model's renders too: `mnerf attack` measures false claims on them under each attack.
        for name, img in zip(names, clean, strict=True):
            _save_png(png_dir / CLEAN_FOLDER / f"{name}.png", img)
    per_id, true_ids, decoded, decoded_png, all_renders = [], [], [], [], []
    for n in range(n_ids):
        logits = decode_renders(decoder, wm, renders[n])
        if save_pngs:
            reloaded = np.stack(
                [
                    _save_and_reload_png(png_dir / f"id{n}" / f"{name}.png", img)
                    for name, img in zip(names, renders[n], strict=True)
                ]
            )
        else:
            reloaded = round_to_8bit(np.asarray(renders[n]))
        logits_png = decode_renders(decoder, wm, reloaded)
        bits, bits_png = logits_to_bits(logits), logits_to_bits(logits_png)
        ident_n = identify_logits(logits, keys.messages, thr)
        per_id.append(
            {
                "id": n,
                "message": "".join(str(int(b)) for b in keys.messages[n]),
                "bit_accuracy": float(bit_accuracy(bits, keys.messages[n]).mean()),
                "bit_accuracy_png": float(bit_accuracy(bits_png, keys.messages[n]).mean()),
                "bit_accuracy_per_view": bit_accuracy(bits, keys.messages[n]).tolist(),
                # Of the views, the fraction reading each bit right: a render is named (binomial, 16 bits and
                # 16 keys) only with every bit right, so one or two positions read wrong on most views keep an
                # ID from being named where scattered errors would not.
                "bit_accuracy_per_bit": (bits == np.asarray(keys.messages[n], np.uint8)[None])
                .mean(0)
                .tolist(),
                "identification_accuracy": float((ident_n.best_id == n).mean()),
                "verified_identification_accuracy": float((ident_n.decision_by(test) == n).mean()),
                "psnr": _quality(renders[n], gt, lpips_net)["psnr"],
            }
        )
        true_ids += [n] * n_views
        decoded.append(logits)
        decoded_png.append(logits_png)
        all_renders.append(renders[n])
    decoded_all = np.concatenate(decoded)
    ident = identify_logits(decoded_all, keys.messages, thr, test)
    ident_png = identify_logits(np.concatenate(decoded_png), keys.messages, thr, test)
    ident_hard = identify(logits_to_bits(decoded_all), keys.messages, thr)
    stacked = np.concatenate(all_renders)
    quality = _quality(stacked, None if gt is None else np.tile(gt, (n_ids, 1, 1, 1)), lpips_net)
    accs = [row["bit_accuracy"] for row in per_id]
    result: dict[str, Any] = {
        "split": split,
        "views": n_views,
        "view_names": names,
        "num_ids": n_ids,
        "bits": keys.bits,
        "min_hamming": keys.min_hamming,
        "variant": wm.variant,
        "read_jitter": wm.reading.jitter,
        "step": run.step,
        "decoder_fingerprint": decoder.fingerprint,
        "bit_accuracy_mean": float(np.mean(accs)),
        "bit_accuracy_min": float(np.min(accs)),
        "bit_accuracy_png_mean": float(np.mean([row["bit_accuracy_png"] for row in per_id])),
        "psnr": quality["psnr"],
        "ssim": quality["ssim"],
        "lpips": quality["lpips"],
        "lpips_net": lpips_net,
        **identification_summary(true_ids, ident),
        "identification_accuracy_png": float((ident_png.best_id == np.asarray(true_ids)).mean()),
        # The best match by agreeing bits alone (hard decisions, ties count as wrong): for comparison.
        "identification_accuracy_hard": float((ident_hard.best_id == np.asarray(true_ids)).mean()),
        "per_id": per_id,
        "source_run": None if source is None else str(source.run_dir),
    }
    result["identification"] = {
        k: result.pop(k)
        for k in (
            "threshold",
            "test",
            "min_attainable_p",
            "median_p_corrected",
            "confusion_best_match",
            "confusion_decision",
        )
    }
    result["identification"]["ids"] = list(range(n_ids))
    result["identification"]["threshold_source"] = rule.source  # given, calibrated or config
    if clean is not None:
        vs_clean = _quality(stacked, np.tile(clean, (n_ids, 1, 1, 1)), lpips_net)
        clean_q = _quality(clean, gt, lpips_net)
        clean_logits = decode_renders(decoder, wm, clean)
        clean_bits = logits_to_bits(clean_logits)
        clean_ident = identify_logits(clean_logits, keys.messages, thr, test)
        false_claims = false_detection_summary(clean_ident, n_ids)
        result.update(
            {
                "psnr_clean_model": vs_clean["psnr"],
                "ssim_clean_model": vs_clean["ssim"],
                "lpips_clean_model": vs_clean["lpips"],
                "clean_psnr": clean_q["psnr"],
                "clean_ssim": clean_q["ssim"],
                "clean_lpips": clean_q["lpips"],
                "clean_bit_accuracy": float(
                    np.mean([bit_accuracy(clean_bits, m).mean() for m in keys.messages])
                ),
                "clean_false_detection_rate": false_claims["false_detection_rate"],
                "clean_false_detection_rate_by_test": false_claims["false_detection_rate_by_test"],
                "clean_false_detection_ids": false_claims["claimed_per_id"],
            }
        )
    else:
        result.update(
            dict.fromkeys(
                (
                    "psnr_clean_model",
                    "ssim_clean_model",
                    "lpips_clean_model",
                    "clean_psnr",
                    "clean_ssim",
                    "clean_lpips",
                    "clean_bit_accuracy",
                    "clean_false_detection_rate",
                    "clean_false_detection_ids",
                    "clean_false_detection_rate_by_test",
                )
            )
        )
    rundir.write_json_atomic(run_dir / f"eval-{split}.json", result)
    if keep_renders:
        result = {**result, "_renders": renders, "_clean": clean, "_gt": gt}
    return result


def clean_model(run: Any) -> Any:
    """The run the watermark was embedded into, or None when it is gone (clean figures are then left out)."""

    source = run.extras.get("source_run")
    if not source or rundir.read_marker(source) is None:
        return None
    return wm_run.load_run(source)


# ------------------------------------------------------------------------------------ images from files


def identify_images(
    run_dir: str | Path,
    paths: Sequence[str | Path],
    threshold: float | None = None,
    batch_size: int = 32,
    test: str | None = None,
    read_jitter: int | None = None,
    search: str | None = None,
    search_scales: tuple[float, ...] | None = None,
    search_degrees: tuple[float, ...] | None = None,
) -> list[dict[str, Any]]:
    """Decode image files with a watermarked run's decoder and identify the ID of each (``mnerf extract
    --run WMRUN IMAGE...``): one record per image with the bits, the best-matching ID, its bit accuracy,
    the p-values (binomial and sign-flip, each also Bonferroni-corrected) and the decision ``id`` (−1: no
    watermark, i.e. the corrected p-value of ``test`` is not below ``threshold``; defaults: the run's
    ``watermark.reading.id_test``, and its calibrated threshold or ``watermark.reading.id_threshold``:
    ``watermark.decision``), the rule's fields (``threshold_source``, ``calibration``) and its description
    (``decision_rule``). ``read_jitter``: as in :func:`evaluate_watermarked_run`. ``search`` (``none``,
    ``scale``, ``rotation``, ``geometry``; default the run's ``watermark.reading.search``) with its grids:
    each image is read under every candidate transform undone and the best-supported read is kept
    (``reader.geometry_search``; its p-values corrected over candidates × keys; the record names the
    ``candidate`` and counts the ``reads``).

    Only the run's keys, decoder and config are read (not its field checkpoint).
    """

    keys, decoder = wm_run.load_keys_and_decoder(run_dir)
    saved = with_read_jitter(rundir.read_run_config(run_dir).watermark, read_jitter)
    rule = decision.decision_rule(run_dir, saved.reading, decoder.fingerprint, threshold, test)
    thr, test = rule.threshold, rule.test
    searched = geometry_search.of_config(saved.reading, search, search_scales, search_degrees)
    reading = read_window.of_config(saved.reading)
    chosen: list[geometry_search.Candidate] = []
    if searched.active:
        every = geometry_search.search_paths(
            decoder.variables, paths, searched, decoder.wavelet, batch_size, reading
        )
        kept = geometry_search.identify(every, keys.messages, searched.candidates(), thr, test)
        logits, ident, chosen = kept.logits, kept.identification, kept.chosen_candidates()
    else:
        logits = extract.decode_paths(decoder.variables, paths, decoder.wavelet, batch_size, reading)
        ident = identify_logits(logits, keys.messages, thr, test)
    records = []
    for i, (p, row) in enumerate(zip(paths, logits, strict=True)):
        record = {
            "image": str(p),
            "bits": "".join(str(int(b)) for b in logits_to_bits(row)),
            "best_id": int(ident.best_id[i]),
            "bit_accuracy": float(ident.bit_accuracy[i]),
            "p_value": float(ident.p_value[i]),
            "p_corrected": float(ident.p_corrected[i]),
            "p_value_sign_flip": float(ident.p_value_sign_flip[i]),
            "p_corrected_sign_flip": float(ident.p_corrected_sign_flip[i]),
            "id": int(ident.decision[i]),
            **rule.as_record(),
            "decision_rule": rule.describe(),
            "min_attainable_p": ident.min_attainable_p,
            "search": searched.mode,
        }
        if searched.active:
            record.update(candidate=chosen[i].to_dict(), reads=ident.reads)
        records.append(record)
    return records
