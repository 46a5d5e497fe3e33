"""False claims on clean images, measured in bulk, and the decision threshold calibrated on them
(``scripts/false_claims.py``).

A watermarked run's decoder reads many images that carry no watermark, and the decision statistic (the best
key's corrected p-value, :mod:`reader.calibration`) is recorded for each under both tests. Three sources:

- ``clean``: the clean model's renders of the evaluated views (the PNGs ``mnerf evaluate`` saved in
  ``eval-<split>/clean/``, else rendered from the source run) under every attack of an ``mnerf attack`` suite,
  the unattacked renders included, evenly spread over the (attack, view) pairs when there are more than
  its share;
- ``photos``: crops of scikit-image's bundled photographs (offline) at random positions and scales, resized
  to the renders' size, some mirrored;
- ``procedural``: procedural textures (smooth noise, gradients, checkerboards, shapes on flat ground:
  ``reader.train.cover_images``) and views of the built-in procedural scene (``data.procedural``) at random
  cameras on white, black or grey, at the renders' size.

``images`` are shared evenly among the sources asked for; ``clean`` gives what it has and the others share
the rest. The result (``WMRUN/false-claims.json``) holds the counts named per source and per group (attack,
photograph, kind) at the run's configured threshold, the statistic's distribution, the threshold table (the
largest threshold naming at most ``k`` images, with its Clopper–Pearson bound) and the calibrated threshold
of each test for the stated rate, which ``WMRUN/calibration.json`` then records for the reading
(:mod:`watermark.decision`).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from tqdm import tqdm

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import load_scene, procedural, view_indices
from mnerf_jax.data.images import to_uint8
from mnerf_jax.evaluation import attacks as image_attacks
from mnerf_jax.evaluation import watermarked as wm_eval
from mnerf_jax.imaging import attack_suites
from mnerf_jax.reader import calibration, significance
from mnerf_jax.reader.identification import identify_logits, min_attainable_p
from mnerf_jax.reader.train import cover_images
from mnerf_jax.tensorf import run as runs
from mnerf_jax.watermark import decision
from mnerf_jax.watermark import run as wm_run

SOURCES = ("clean", "photos", "procedural")
FALSE_CLAIMS_FILE = "false-claims.json"
DEFAULT_IMAGES = 10_000
TABLE_ROWS = 50  # the threshold table lists the thresholds naming at most this many images
SCENE_SIDE = 128  # procedural scene views are ray-traced at most this many pixels wide, then resized
Batches = Iterator[tuple[str, np.ndarray]]  # (group, uint8 images [B, H, W, 3])


def false_claims_path(run_dir: str | Path) -> Path:
    return Path(run_dir) / FALSE_CLAIMS_FILE


def check_sources(names: Sequence[str]) -> list[str]:
    """The sources asked for, each once, in :data:`SOURCES` order; MnerfError naming an unknown one."""
    unknown = sorted(set(names) - set(SOURCES))
    if unknown or not names:
        raise MnerfError(
            f"unknown image source(s) {', '.join(unknown) or '(none)'} (known: {', '.join(SOURCES)})"
        )
    return [s for s in SOURCES if s in names]


def quotas(total: int, sources: Sequence[str], clean_available: int) -> dict[str, int]:
    """Images per source: ``total`` shared evenly, ``clean`` capped at ``clean_available`` and its
    shortfall shared by the others (the first ones take a remainder)."""
    shares = {s: total // len(sources) + (i < total % len(sources)) for i, s in enumerate(sources)}
    if "clean" in shares and shares["clean"] > clean_available:
        spare, shares["clean"] = shares["clean"] - clean_available, clean_available
        others = [s for s in sources if s != "clean"]
        for i, s in enumerate(others):
            shares[s] += spare // len(others) + (i < spare % len(others))
    return shares


# ------------------------------------------------------------------------------------------ the sources


def clean_renders(
    run_dir: Path, split: str, views: int | None, data_path: str | Path | None
) -> tuple[np.ndarray | None, str]:
    """``(uint8 [V, H, W, 3] or None, where from)``: the clean model's saved renders of the evaluated views,
    else its renders of ``views`` evenly spread views of ``split`` (source run), else None."""
    evaluation = run_dir / f"eval-{split}.json"
    if evaluation.is_file():
        try:
            names = list(json.loads(evaluation.read_text()).get("view_names") or [])
        except json.JSONDecodeError:
            names = []
        names = [names[i] for i in view_indices(len(names), views)] if names else []
        saved = image_attacks.saved_clean(run_dir, split, names) if names else None
        if saved is not None:
            return saved, f"saved by mnerf evaluate in eval-{split}/clean"
    source = rundir.read_marker(run_dir).get("source_run")
    if not source or rundir.read_marker(source) is None:
        return None, "no saved clean renders, and the source run is gone"
    model = wm_run.load_run(source)
    part = model.load_scene(data_path, splits=(split,)).split(split)
    indices = view_indices(len(part), views)
    images = runs.render_views(model, part.cameras, indices)
    return np.stack([to_uint8(x) for x in images]), f"rendered from {source}"


def clean_batches(clean: np.ndarray, attacks: Sequence[Any], count: int, seed: int) -> Batches:
    """``count`` of the (attack, view) pairs (``None``: no attack, first), evenly spread in attack-major
    order; each attack's views as one batch, named by the attack."""
    rows = [None, *attacks]
    v = len(clean)
    chosen = np.unique(np.round(np.linspace(0, len(rows) * v - 1, count)).astype(int)) if count else []
    for a, attack in enumerate(rows):
        views = [int(i) - a * v for i in chosen if a * v <= i < (a + 1) * v]
        if views:
            images = clean[views]
            yield (
                (image_attacks.NO_ATTACK if attack is None else attack.name),
                (images if attack is None else attack(images, seed)),
            )


def _resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """uint8 ``[h, w, 3]`` resized to ``[height, width, 3]`` (bilinear, antialiased)."""
    if image.shape[:2] == (height, width):
        return image
    return np.asarray(
        Image.fromarray(image).resize((width, height), Image.Resampling.BILINEAR, reducing_gap=2.0)
    )


def photo_crop(rng: np.random.Generator, photo: np.ndarray, height: int, width: int) -> np.ndarray:
    """A crop of ``photo`` (float ``[h, w, 3]``) with the renders' aspect, 25–100 % of the largest that fits,
    at a random place, resized to ``[height, width, 3]`` uint8 and mirrored half the time."""
    h, w = photo.shape[:2]
    fit_h = min(h, w * height / width)
    ch = max(int(round(fit_h * rng.uniform(0.25, 1.0))), 1)
    cw = max(min(int(round(ch * width / height)), w), 1)
    y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    crop = _resize(to_uint8(photo[y : y + ch, x : x + cw]), height, width)
    return crop[:, ::-1].copy() if rng.random() < 0.5 else crop


def photo_batches(count: int, height: int, width: int, seed: int, batch: int) -> Batches:
    """``count`` crops of the bundled photographs (:func:`photo_crop`), grouped by photograph."""
    named = [
        (name, image)
        for name in (*cover_images.TRAIN_PHOTOS, *cover_images.HELDOUT_PHOTOS)
        for image in cover_images.load_photos([name])  # a stereo pair gives two
    ]
    names, photos = [n for n, _ in named], [p for _, p in named]
    rng = np.random.default_rng([seed, 0xF07])
    for start in range(0, count, batch):
        n = min(batch, count - start)
        picks = rng.integers(0, len(photos), n)
        for p in np.unique(picks):
            yield (
                names[int(p)],
                np.stack([photo_crop(rng, photos[p], height, width) for _ in range(int((picks == p).sum()))]),
            )


def scene_view(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A view of a random procedural scene (seed 0–7) from a random camera on white, black or grey, uint8
    ``[height, width, 3]`` (ray-traced at most :data:`SCENE_SIDE` pixels wide, then resized)."""
    objects = procedural.build_scene(int(rng.integers(0, 8)))
    poses, _ = procedural.camera_poses(int(rng.integers(0, 1 << 30)), 1, 1)
    rgba = (
        procedural.render_view(objects, poses[0], min(max(height, width), SCENE_SIDE)).astype(np.float32)
        / 255
    )
    ground = float(rng.choice([1.0, 0.0, rng.uniform(0.2, 0.8)]))
    rgb = rgba[..., :3] * rgba[..., 3:] + ground * (1.0 - rgba[..., 3:])
    side = rgb.shape[0]
    return _resize(to_uint8(rgb), height, width) if (height, width) != (side, side) else to_uint8(rgb)


def procedural_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A procedural texture at ``[height, width, 3]`` uint8 (made square at the longer side, cropped)."""
    side = max(height, width)
    image = to_uint8(cover_images.procedural_image(rng, side))
    y, x = (side - height) // 2, (side - width) // 2
    return image[y : y + height, x : x + width]


def procedural_batches(count: int, height: int, width: int, seed: int, batch: int) -> Batches:
    """``count`` procedural images: three textures (group ``texture``) for each scene view (``scene``)."""
    rng = np.random.default_rng([seed, 0x9C0])
    for start in range(0, count, batch):
        n = min(batch, count - start)
        kinds = [(start + i) % 4 == 3 for i in range(n)]
        scenes = [scene_view(rng, height, width) for k in kinds if k]
        textures = [procedural_image(rng, height, width) for k in kinds if not k]
        if textures:
            yield "texture", np.stack(textures)
        if scenes:
            yield "scene", np.stack(scenes)


# ------------------------------------------------------------------------------------------ measuring


def _tally(stats: dict[str, np.ndarray], threshold: float) -> dict[str, int]:
    return {test: int((s < threshold).sum()) for test, s in stats.items()}


def measure_false_claims(
    run_dir: str | Path,
    images: int = DEFAULT_IMAGES,
    sources: Sequence[str] = SOURCES,
    *,
    split: str = "test",
    suite: str = "all",
    views: int | None = None,
    seed: int = 0,
    batch: int = 64,
    rate: float | None = None,
    calibrate: bool = True,
    data_path: str | Path | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Decode about ``images`` clean images from ``sources`` with a watermarked run's decoder; write
    ``WMRUN/false-claims.json`` (module docstring) and, with ``calibrate``, ``WMRUN/calibration.json`` at
    the stated ``rate`` (default the run's ``watermark.reading.id_threshold``); return the result.

    ``suite``: the ``mnerf attack`` suite the clean renders go through; ``views``: views of ``split`` to
    render when none are saved (None: all); ``batch``: images per decoder call.
    """
    run_dir = Path(run_dir)
    sources = check_sources(sources)
    if images < 1 or batch < 1:
        raise MnerfError(f"--images and --batch must be ≥ 1, got {images} and {batch}")
    keys, decoder = wm_run.load_keys_and_decoder(run_dir)
    wm = rundir.read_run_config(run_dir).watermark
    nominal = float(wm.reading.id_threshold)
    rate = nominal if rate is None else float(rate)
    if not 0.0 < rate < 1.0:
        raise MnerfError(f"--rate must be in (0, 1), got {rate}")
    attacks = [a for a in attack_suites.suite(suite) if not a.unavailable] if "clean" in sources else []
    clean, clean_note = (None, "not asked for")
    if "clean" in sources:
        clean, clean_note = clean_renders(run_dir, split, views, data_path)
    available = 0 if clean is None else len(clean) * (len(attacks) + 1)
    if clean is None and sources == ["clean"]:
        raise MnerfError(f"{run_dir}: no clean images to read ({clean_note})")
    share = quotas(images, sources, available)
    height, width = clean.shape[1:3] if clean is not None else _render_size(run_dir, split, data_path)
    make = {
        "clean": lambda n: clean_batches(clean, attacks, n, seed) if clean is not None else iter(()),
        "photos": lambda n: photo_batches(n, height, width, seed, batch),
        "procedural": lambda n: procedural_batches(n, height, width, seed, batch),
    }
    messages = np.asarray(keys.messages, np.float32)
    bar = (
        tqdm(total=sum(share.values()), unit="image", desc="false claims", dynamic_ncols=True)
        if progress
        else None
    )
    stats: dict[str, dict[str, list[np.ndarray]]] = {
        s: {t: [] for t in significance.ID_TESTS} for s in sources
    }
    groups: dict[str, dict[str, Any]] = {s: {} for s in sources}
    try:
        for source in sources:
            for group, hit in make[source](share[source]):
                logits = wm_eval.decode_renders(
                    decoder, wm, hit.astype(np.float32) / np.float32(255.0), batch
                )
                ident = identify_logits(logits, messages, nominal)
                got = {
                    "binomial": calibration.decision_statistic(ident.best_id, ident.p_corrected),
                    "sign_flip": calibration.decision_statistic(ident.best_id, ident.p_corrected_sign_flip),
                }
                for test, s in got.items():
                    stats[source][test].append(s)
                row = groups[source].setdefault(group, {"images": 0, "named": dict.fromkeys(got, 0)})
                row["images"] += len(hit)
                for test, k in _tally(got, nominal).items():
                    row["named"][test] += k
                if bar is not None:
                    bar.update(len(hit))
    finally:
        if bar is not None:
            bar.close()
    result = summarise(run_dir, stats, groups, nominal, rate, wm, decoder.fingerprint)
    result.update(
        requested=int(images),
        split=split,
        suite=suite if "clean" in sources else None,
        seed=int(seed),
        size=[int(height), int(width)],
        num_ids=int(keys.num_ids),
        bits=int(keys.bits),
        test=str(wm.reading.id_test),
    )
    if "clean" in sources:
        result["sources"]["clean"]["note"] = clean_note
    if result["images"] < 1:
        raise MnerfError(f"{run_dir}: no image was read")
    rundir.write_json_atomic(false_claims_path(run_dir), result)
    if calibrate:
        write_run_calibration(run_dir, result)
    return result


def _render_size(run_dir: Path, split: str, data_path: str | Path | None) -> tuple[int, int]:
    """``(height, width)`` of the run's renders of ``split`` (its scene's cameras)."""
    config = rundir.read_run_config(run_dir)
    marker = rundir.read_marker(run_dir)
    path = data_path if data_path is not None else marker.get("data")
    if path is None and config.data.dataset != "procedural":
        raise MnerfError(f"{run_dir} does not record where its data is; pass --data")
    cameras = load_scene(path, config.data, config.render, (split,)).split(split).cameras
    return int(cameras.height), int(cameras.width)


def summarise(
    run_dir: Path,
    stats: dict[str, dict[str, list[np.ndarray]]],
    groups: dict[str, dict[str, Any]],
    nominal: float,
    rate: float,
    wm: Any,
    fingerprint: str,
) -> dict[str, Any]:
    """The JSON of a measurement: per source its images, named (at ``nominal``) and their Clopper–Pearson
    bounds, its groups; over all, the statistic's ``distribution``, the ``thresholds`` table and the
    ``calibration`` for ``rate`` of each test."""
    joined = {
        t: np.concatenate([a for s in stats.values() for a in s[t]] or [np.zeros(0)])
        for t in significance.ID_TESTS
    }
    m = int(joined["binomial"].size)
    per_source = {}
    for source, by_test in stats.items():
        values = {t: np.concatenate(a or [np.zeros(0)]) for t, a in by_test.items()}
        n = int(values["binomial"].size)
        named = _tally(values, nominal)
        per_source[source] = {
            "images": n,
            "named": named,
            "rate_upper": {
                t: calibration.clopper_pearson_upper(k, n) if n else None for t, k in named.items()
            },
            "groups": groups[source],
        }
    dists = {t: calibration.distribution(v) for t, v in joined.items()} if m else {}
    named = _tally(joined, nominal)
    return {
        "run": str(run_dir),
        "decoder_fingerprint": fingerprint,
        "read": decision.read_settings(wm.reading),
        "images": m,
        "threshold": nominal,
        "named": named,
        "rate_upper": {t: calibration.clopper_pearson_upper(k, m) if m else None for t, k in named.items()},
        "sources": per_source,
        "distribution": dists,
        "thresholds": {t: calibration.threshold_table(d, TABLE_ROWS) for t, d in dists.items()},
        "target_rate": rate,
        "confidence": calibration.CONFIDENCE,
        "calibration": {
            t: calibration.threshold_for_rate(
                d, rate, calibration.CONFIDENCE, nominal, min_attainable_p(wm.num_ids, wm.bits)
            )
            for t, d in dists.items()
        },
    }


def write_run_calibration(run_dir: str | Path, result: dict[str, Any]) -> Path:
    """``WMRUN/calibration.json`` from a measurement's ``calibration`` entries (:mod:`watermark.decision`)."""
    return decision.write_calibration(
        run_dir,
        {
            "source": FALSE_CLAIMS_FILE,
            "decoder_fingerprint": result["decoder_fingerprint"],
            "read": result["read"],
            "images": result["images"],
            "target_rate": result["target_rate"],
            "confidence": result["confidence"],
            "tests": result["calibration"],
        },
    )


def recalibrate(run_dir: str | Path, rate: float | None = None) -> dict[str, Any]:
    """Calibrate again at ``rate`` (default the run's ``id_threshold``) from the distributions in
    ``WMRUN/false-claims.json``, without reading an image: rewrites its ``calibration`` and
    ``calibration.json``. MnerfError when there is no measurement, or it was made with another decoder."""
    run_dir = Path(run_dir)
    path = false_claims_path(run_dir)
    if not path.is_file():
        raise MnerfError(
            f"{run_dir} has no {FALSE_CLAIMS_FILE}: measure first (scripts/false_claims.py --run)"
        )
    try:
        result = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise MnerfError(f"{path} is not valid JSON ({err}); measure again") from None
    _, decoder = wm_run.load_keys_and_decoder(run_dir)
    if result.get("decoder_fingerprint") != decoder.fingerprint:
        raise MnerfError(f"{path} was measured with another decoder than {run_dir}'s: measure again")
    nominal = float(rundir.read_run_config(run_dir).watermark.reading.id_threshold)
    rate = nominal if rate is None else float(rate)
    if not 0.0 < rate < 1.0:
        raise MnerfError(f"--rate must be in (0, 1), got {rate}")
    result["target_rate"] = rate
    result["calibration"] = {
        t: calibration.threshold_for_rate(
            d, rate, calibration.CONFIDENCE, nominal, min_attainable_p(result["num_ids"], result["bits"])
        )
        for t, d in result["distribution"].items()
    }
    rundir.write_json_atomic(path, result)
    write_run_calibration(run_dir, result)
    return result
