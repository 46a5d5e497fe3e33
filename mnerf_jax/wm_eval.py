"""Evaluation of a watermarked run: bit accuracy per ID, image quality, identification of the ID.

Identification. A decoded message (``L`` logits ``ℓ``, bits ``b = ℓ > 0``) is compared with every key
``m_n``. The best match is the key with the largest soft correlation ``Σ_i ℓ_i (2 m_n,i − 1)``
(:func:`identify_logits`, what evaluation and ``mnerf extract`` use): soft-decision decoding, the
maximum-likelihood key when the logits are equally scaled noisy readings of ``±1`` (the decoder's whitening
layer scales them alike), so a confident bit outweighs a doubtful one; counting agreeing bits alone
(:func:`identify`, hard decisions) throws that away and leaves ties. With ``k`` the agreeing bits of the
chosen key, under the null hypothesis (no watermark: decoded bits are fair coin flips independent of the
keys) the agreement with one fixed key is ``X ~ Bin(L, ½)``, so

    p = P[X ≥ k] = Σ_{j≥k} C(L, j) / 2^L

and, as one of ``N`` keys was picked, the Bonferroni-corrected ``p_N = min(1, N·p)`` bounds the chance
that *any* key agrees this well by luck (the chosen key agrees at most as well as the best-agreeing one, so
picking it by soft correlation keeps the bound). The decision rule: report the best-matching ID when
``p_N < threshold`` (default :data:`DEFAULT_THRESHOLD` = 1e-3, i.e. at most one false claim per thousand
unwatermarked images), otherwise "no watermark" (ID −1). A tie between two keys at the best score is
undecided (−1) too.

The smallest attainable ``p_N`` is ``N / 2^L`` (all bits agree): with short messages and many IDs the
threshold may be out of reach whatever the accuracy (4 IDs × 8 bits: 0.0156). Results therefore report both
the *best-match* identification accuracy (the argmax is the rendered ID) and the *verified* one (argmax
correct and ``p_N < threshold``), plus ``min_attainable_p`` so a reader can tell the two apart.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_THRESHOLD = 1e-3
NO_WATERMARK = -1
# IDs rendered together in evaluation: one geometry pass per view serves them all (wm_run.render_with_ids).
IDS_PER_RENDER = 16


# ---------------------------------------------------------------------------------------------- bits


def logits_to_bits(logits: np.ndarray) -> np.ndarray:
    """Decoded bits ``[..., L]`` uint8: 1 where the logit is > 0."""
    return (np.asarray(logits) > 0).astype(np.uint8)


def bit_accuracy(bits: np.ndarray, message: np.ndarray) -> np.ndarray:
    """Fraction of matching bits ``[...]`` between decoded ``bits [..., L]`` and ``message [..., L]``."""
    return np.mean(np.asarray(bits, np.uint8) == np.asarray(message, np.uint8), axis=-1)


def binomial_tail(k: int, n: int) -> float:
    """``P[X ≥ k]`` for ``X ~ Bin(n, ½)``, exact (integer arithmetic)."""
    k = max(int(k), 0)
    if k > n:
        return 0.0
    return sum(math.comb(n, j) for j in range(k, n + 1)) / float(1 << n)


# ----------------------------------------------------------------------------------------- identification


@dataclasses.dataclass(frozen=True)
class Identification:
    """Identification of a batch of ``B`` decoded messages against ``N`` keys.

    best_id [B]       the best-matching key (−1 on a tie)
    agreement [B]     agreeing bits with that key
    bit_accuracy [B]  agreement / L
    p_value [B]       P[Bin(L, ½) ≥ agreement]
    p_corrected [B]   min(1, N·p_value)
    decision [B]      best_id where p_corrected < threshold, else −1 ("no watermark")
    """

    best_id: np.ndarray
    agreement: np.ndarray
    bit_accuracy: np.ndarray
    p_value: np.ndarray
    p_corrected: np.ndarray
    decision: np.ndarray
    threshold: float
    bits: int
    num_ids: int

    @property
    def min_attainable_p(self) -> float:
        return min(1.0, self.num_ids / float(1 << self.bits))


def identify(
    decoded: np.ndarray, messages: np.ndarray, threshold: float = DEFAULT_THRESHOLD
) -> Identification:
    """Best-matching key by agreeing bits (hard decisions), its binomial p-value and the decision.

    Args:
      decoded: ``[B, L]`` decoded bits (or ``[L]``).
      messages: ``[N, L]`` keys.
      threshold: decision threshold on the Bonferroni-corrected p-value.
    """
    messages = np.asarray(messages, np.uint8)
    agree = _agreement(np.atleast_2d(np.asarray(decoded, np.uint8)), messages)
    return _identification(agree, agree, messages, threshold)


def identify_logits(
    logits: np.ndarray, messages: np.ndarray, threshold: float = DEFAULT_THRESHOLD
) -> Identification:
    """Best-matching key by soft correlation ``Σ ℓ_i (2 m_i − 1)`` (module docstring), its binomial p-value
    (on its agreeing bits ``ℓ > 0``) and the decision.

    Args:
      logits: ``[B, L]`` decoder logits (or ``[L]``).
      messages: ``[N, L]`` keys.
      threshold: decision threshold on the Bonferroni-corrected p-value.
    """
    logits = np.atleast_2d(np.asarray(logits, np.float64))
    messages = np.asarray(messages, np.uint8)
    agree = _agreement(logits_to_bits(logits), messages)
    signs = 2.0 * messages.astype(np.float64) - 1.0
    return _identification(logits @ signs.T, agree, messages, threshold)


def _agreement(bits: np.ndarray, messages: np.ndarray) -> np.ndarray:
    """Agreeing bits ``[B, N]`` of decoded ``bits [B, L]`` with each key of ``messages [N, L]``."""
    if bits.shape[-1] != messages.shape[-1]:
        raise ValueError(f"decoded messages have {bits.shape[-1]} bits, the keys {messages.shape[-1]}")
    return (bits[:, None, :] == messages[None, :, :]).sum(-1)


def _identification(
    scores: np.ndarray, agree: np.ndarray, messages: np.ndarray, threshold: float
) -> Identification:
    """The key of highest ``scores [B, N]`` (−1 on a tie), judged by its agreeing bits ``agree [B, N]``."""
    n_ids, bits = messages.shape
    top = scores.max(axis=1)
    best_id = scores.argmax(axis=1)
    tie = (scores == top[:, None]).sum(axis=1) > 1
    best = np.take_along_axis(agree, best_id[:, None], axis=1)[:, 0]
    best_id = np.where(tie, NO_WATERMARK, best_id)
    p = np.array([binomial_tail(int(k), bits) for k in best], np.float64)
    p_corr = np.minimum(1.0, n_ids * p)
    decision = np.where((p_corr < threshold) & ~tie, best_id, NO_WATERMARK)
    return Identification(
        best_id=best_id.astype(np.int64),
        agreement=best.astype(np.int64),
        bit_accuracy=best / bits,
        p_value=p,
        p_corrected=p_corr,
        decision=decision.astype(np.int64),
        threshold=float(threshold),
        bits=int(bits),
        num_ids=int(n_ids),
    )


def confusion_matrix(true_ids: Sequence[int], predicted: Sequence[int], num_ids: int) -> np.ndarray:
    """``[N, N + 1]`` counts: row = rendered ID, column = predicted ID, last column = none / undecided."""
    out = np.zeros((num_ids, num_ids + 1), np.int64)
    for t, p in zip(true_ids, predicted, strict=True):
        out[int(t), int(p) if 0 <= int(p) < num_ids else num_ids] += 1
    return out


def identification_summary(
    true_ids: Sequence[int], ident: Identification
) -> dict[str, Any]:
    """Identification accuracies and the confusion matrices (best match and decision) as plain data."""
    true = np.asarray(true_ids, np.int64)
    best_ok = ident.best_id == true
    verified_ok = ident.decision == true
    return {
        "identification_accuracy": float(best_ok.mean()) if true.size else math.nan,
        "verified_identification_accuracy": float(verified_ok.mean()) if true.size else math.nan,
        "detection_rate": float((ident.decision >= 0).mean()) if true.size else math.nan,
        "threshold": ident.threshold,
        "min_attainable_p": ident.min_attainable_p,
        "median_p_corrected": float(np.median(ident.p_corrected)) if true.size else math.nan,
        "confusion_best_match": confusion_matrix(true, ident.best_id, ident.num_ids).tolist(),
        "confusion_decision": confusion_matrix(true, ident.decision, ident.num_ids).tolist(),
    }


def false_detection_summary(ident: Identification, num_ids: int = 0) -> dict[str, Any]:
    """How often unwatermarked images are claimed (decision ≠ −1): should be ≤ the threshold; and how many
    were claimed as each of the ``num_ids`` keys (a decoder biased towards some keys claims those)."""
    claimed = ident.decision[ident.decision >= 0]
    return {
        "false_detection_rate": float((ident.decision >= 0).mean()) if ident.decision.size else math.nan,
        "mean_best_agreement": float(ident.bit_accuracy.mean()) if ident.decision.size else math.nan,
        "claimed_per_id": np.bincount(claimed, minlength=num_ids).tolist(),
    }


# ------------------------------------------------------------------------------------------- evaluation


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _decode(decoder: Any, images: np.ndarray, batch: int = 16) -> np.ndarray:
    from mnerf_jax import extract

    images = np.asarray(images, np.float32)
    return np.asarray(extract.decode(decoder.variables, images, decoder.wavelet, batch))


def _save_and_reload_png(path: Path, image: np.ndarray) -> np.ndarray:
    """Write an 8-bit PNG and read it back as float32 ``[H, W, 3]`` (what a viewer of the render gets)."""
    import imageio.v3 as iio

    from mnerf_jax import extract

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, _to_uint8(image))
    return extract.load_image(path)


def _quality(preds: np.ndarray, targets: np.ndarray, lpips_net: str) -> dict[str, float]:
    from mnerf_jax import metrics

    out = metrics.image_metrics(preds, targets, lpips_net=lpips_net)
    return {k: out[k] for k in ("psnr", "ssim", "lpips")}


def evaluate_watermarked_run(
    run_dir: str | Path,
    split: str = "test",
    data_path: str | Path | None = None,
    *,
    max_views: int | None = None,
    threshold: float | None = None,
    lpips_net: str = "alex",
    save_pngs: bool = True,
    progress: bool = False,
    keep_renders: bool = False,
) -> dict[str, Any]:
    """Evaluate a watermarked run on ``split``; writes ``run_dir/eval-<split>.json`` and returns its dict.

    For every evaluated view and every ID (up to :data:`IDS_PER_RENDER` IDs from one geometry pass): render
    (float, unclamped by nothing but the renderer's [0, 1]),
    decode, and again after a round trip through an 8-bit PNG (``run_dir/eval-<split>/id<K>/<view>.png``).
    The clean (pre-watermark) model of ``--from`` renders the same views: quality is reported against the
    ground truth and against those clean renders, and the clean renders' bit accuracy against every key
    (chance: 50 %) and false-detection rate show what an unwatermarked image decodes to.

    Top-level keys: ``bit_accuracy_mean``, ``bit_accuracy_min`` (worst ID), ``bit_accuracy_png_mean``,
    ``psnr``, ``ssim``, ``lpips`` (vs ground truth), ``psnr_clean_model`` / ``ssim_clean_model`` /
    ``lpips_clean_model`` (vs the clean model's renders), ``clean_psnr`` (clean model vs ground truth),
    ``identification_accuracy`` (best-matching key by soft correlation is the rendered ID;
    ``identification_accuracy_hard``: by agreeing bits), ``verified_identification_accuracy`` (and its p-value
    passes ``threshold``), ``clean_bit_accuracy``, ``clean_false_detection_rate`` (and per ID, which keys
    the false detections claimed: ``clean_false_detection_ids [N]``),
    ``num_ids``, ``bits``, ``split``, ``views``, ``per_id`` and ``identification`` (confusion matrices).
    With ``keep_renders`` the returned dict (not the file) also holds ``_renders`` ``{ID: [V, H, W, 3]}``,
    ``_clean`` and ``_gt``.
    """
    from mnerf_jax import run as runs
    from mnerf_jax import watermark, wm_run

    run_dir = Path(run_dir)
    run = wm_run.load_watermarked_run(run_dir)
    keys = run.extras["keys"]
    decoder = run.extras["decoder"]
    thr = float(run.config.watermark.id_threshold if threshold is None else threshold)
    scene_split = run.load_scene(data_path, splits=(split,)).split(split)
    indices = runs.view_indices(len(scene_split), max_views)
    names = [scene_split.names[i] for i in indices]
    gt = np.asarray(scene_split.images[indices], np.float32)
    n_ids, n_views = keys.num_ids, len(indices)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_views * (n_ids + 1), unit="render", desc=f"evaluate {split}", dynamic_ncols=True)
    # A view's renders count one per ID (a render of K IDs at once is 3K channels wide).
    tick = (lambda i, rgb: bar.update(rgb.shape[-1] // 3)) if bar is not None else None
    try:
        source = _clean_model(run)
        clean = None
        if source is not None:
            clean = np.stack(runs.render_views(source, scene_split.cameras, indices, on_view=tick))
        renders: dict[int, np.ndarray] = {}
        group = IDS_PER_RENDER if watermark.uses_ids(run.config.watermark) else 1
        for first in range(0, n_ids, group):
            ids = range(first, min(first + group, n_ids))
            out = wm_run.render_with_ids(run, ids, scene_split.cameras, indices, on_view=tick)
            renders.update({n: np.stack(images) for n, images in out.items()})
    finally:
        if bar is not None:
            bar.close()

    png_dir = run_dir / f"eval-{split}"
    per_id, true_ids, decoded, decoded_png, all_renders = [], [], [], [], []
    for n in range(n_ids):
        logits = _decode(decoder, renders[n])
        if save_pngs:
            reloaded = np.stack([_save_and_reload_png(png_dir / f"id{n}" / f"{name}.png", img)
                                 for name, img in zip(names, renders[n], strict=True)])  # fmt: skip
        else:
            reloaded = np.stack([_to_uint8(img).astype(np.float32) / 255.0 for img in renders[n]])
        logits_png = _decode(decoder, reloaded)
        bits, bits_png = logits_to_bits(logits), logits_to_bits(logits_png)
        ident_n = identify_logits(logits, keys.messages, thr)
        per_id.append({
            "id": n,
            "message": "".join(str(int(b)) for b in keys.messages[n]),
            "bit_accuracy": float(bit_accuracy(bits, keys.messages[n]).mean()),
            "bit_accuracy_png": float(bit_accuracy(bits_png, keys.messages[n]).mean()),
            "bit_accuracy_per_view": bit_accuracy(bits, keys.messages[n]).tolist(),
            "identification_accuracy": float((ident_n.best_id == n).mean()),
            "psnr": _quality(renders[n], gt, lpips_net)["psnr"],
        })  # fmt: skip
        true_ids += [n] * n_views
        decoded.append(logits)
        decoded_png.append(logits_png)
        all_renders.append(renders[n])
    decoded_all = np.concatenate(decoded)
    ident = identify_logits(decoded_all, keys.messages, thr)
    ident_png = identify_logits(np.concatenate(decoded_png), keys.messages, thr)
    ident_hard = identify(logits_to_bits(decoded_all), keys.messages, thr)
    stacked = np.concatenate(all_renders)
    quality = _quality(stacked, np.tile(gt, (n_ids, 1, 1, 1)), lpips_net)
    accs = [row["bit_accuracy"] for row in per_id]
    result: dict[str, Any] = {
        "split": split,
        "views": n_views,
        "view_names": names,
        "num_ids": n_ids,
        "bits": keys.bits,
        "min_hamming": keys.min_hamming,
        "variant": run.config.watermark.variant,
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
    result["identification"] = {k: result.pop(k) for k in ("threshold", "min_attainable_p",
                                                             "median_p_corrected", "confusion_best_match",
                                                             "confusion_decision")}  # fmt: skip
    result["identification"]["ids"] = list(range(n_ids))
    if clean is not None:
        vs_clean = _quality(stacked, np.tile(clean, (n_ids, 1, 1, 1)), lpips_net)
        clean_q = _quality(clean, gt, lpips_net)
        clean_logits = _decode(decoder, clean)
        clean_bits = logits_to_bits(clean_logits)
        clean_ident = identify_logits(clean_logits, keys.messages, thr)
        false_claims = false_detection_summary(clean_ident, n_ids)
        result.update({
            "psnr_clean_model": vs_clean["psnr"],
            "ssim_clean_model": vs_clean["ssim"],
            "lpips_clean_model": vs_clean["lpips"],
            "clean_psnr": clean_q["psnr"],
            "clean_ssim": clean_q["ssim"],
            "clean_lpips": clean_q["lpips"],
            "clean_bit_accuracy": float(np.mean([bit_accuracy(clean_bits, m).mean() for m in keys.messages])),
            "clean_false_detection_rate": false_claims["false_detection_rate"],
            "clean_false_detection_ids": false_claims["claimed_per_id"],
        })  # fmt: skip
    else:
        result.update(dict.fromkeys((
            "psnr_clean_model", "ssim_clean_model", "lpips_clean_model", "clean_psnr", "clean_ssim",
            "clean_lpips", "clean_bit_accuracy", "clean_false_detection_rate", "clean_false_detection_ids",
        )))  # fmt: skip
    runs.write_json_atomic(run_dir / f"eval-{split}.json", result)
    if keep_renders:
        result = {**result, "_renders": renders, "_clean": clean, "_gt": gt}
    return result


def _clean_model(run: Any) -> Any:
    """The run the watermark was embedded into, or None when it is gone (clean figures are then left out)."""
    from mnerf_jax import run as runs

    source = run.extras.get("source_run")
    if not source or runs.read_marker(source) is None:
        return None
    return runs.load_run(source)


# ------------------------------------------------------------------------------------ images from files


def identify_images(
    run_dir: str | Path, paths: Sequence[str | Path], threshold: float | None = None, batch_size: int = 32
) -> list[dict[str, Any]]:
    """Decode image files with a watermarked run's decoder and identify the ID of each (``mnerf extract
    --run WMRUN IMAGE...``): one record per image with the bits, the best-matching ID, its bit accuracy,
    the p-value, the corrected p-value and the decision ``id`` (−1: no watermark, i.e. the corrected
    p-value is not below ``threshold``, default the run's ``watermark.id_threshold``).

    Only the run's keys, decoder and config are read (not its field checkpoint).
    """
    from mnerf_jax import extract, wm_run
    from mnerf_jax import run as runs

    keys, decoder = wm_run.load_keys_and_decoder(run_dir)
    if threshold is None:
        threshold = runs.read_run_config(run_dir).watermark.id_threshold
    thr = float(threshold)
    logits = extract.decode_paths(decoder.variables, paths, decoder.wavelet, batch_size)
    ident = identify_logits(logits, keys.messages, thr)
    return [
        {
            "image": str(p),
            "bits": "".join(str(int(b)) for b in logits_to_bits(row)),
            "best_id": int(ident.best_id[i]),
            "bit_accuracy": float(ident.bit_accuracy[i]),
            "p_value": float(ident.p_value[i]),
            "p_corrected": float(ident.p_corrected[i]),
            "id": int(ident.decision[i]),
            "threshold": thr,
        }
        for i, (p, row) in enumerate(zip(paths, logits, strict=True))
    ]
