"""The scores of ``mnerf attack`` (:mod:`mnerf_jax.evaluation.attacks`) as a text table and a bar plot."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mnerf_jax.evaluation.plots import plt
from mnerf_jax.imaging import augment

NO_ATTACK = "none"
# Beyond this many attacks the bars run down the page (one row each) instead of across it.
HORIZONTAL_FROM = 40
LABEL_CHARS = 36  # longer names are cut in the plot (the table and JSON keep them whole)


def _label(name: str) -> str:
    return name if len(name) <= LABEL_CHARS else "…" + name[-(LABEL_CHARS - 1) :]


def attack_order(result: Mapping[str, Any]) -> list[str]:
    """The attacks of ``result`` in the order they ran (its ``order``; the JSON file keeps its keys
    sorted). A file written before ``order`` was recorded: the augmentations' order, ``"none"`` first."""
    if result.get("order"):
        return [name for name in result["order"] if name in result["attacks"]]
    rank = {name: i for i, name in enumerate((NO_ATTACK, *augment.AUGMENTATION_NAMES))}
    return sorted(result["attacks"], key=lambda name: rank.get(name, len(rank)))


def title(result: Mapping[str, Any]) -> str:
    """What was run: ``model suite S`` (attacks on the field), ``suite S``, ``S attacks`` (the 14
    augmentations at strength S) or ``named attacks``."""
    if result.get("model"):
        return f"model suite {result['suite']}"
    if result.get("suite"):
        return f"suite {result['suite']}"
    if result.get("named"):
        return "named attacks"
    return f"{result['strength']} attacks"


def format_table(result: Mapping[str, Any]) -> str:
    """The attacks as a text table: bits mean / worst ID, best match, named, and (with the clean renders)
    false claims; with a geometry search the same read with it (``S:`` columns); then the mean over the
    attacks and the attacks skipped, with why."""
    claims = bool(result.get("false_claims_measured"))
    search = result.get("search")
    rows = [(name, result["attacks"][name]) for name in attack_order(result)]
    if result.get("mean_over_attacks"):
        mean = dict(result["mean_over_attacks"])
        if search and result.get("mean_over_attacks_search"):
            mean["search"] = result["mean_over_attacks_search"]
        rows.append(("mean of attacks", mean))
    width = max(18, *(len(name) + 1 for name, _ in rows))
    head = f"{'attack (' + title(result) + ')':<{width}} {'bits':>8} {'worst ID':>9} {'best match':>11}"
    head += f" {'named':>8}" + (f" {'false claims':>13}" if claims else "")
    if search:
        head += f" {'S: bits':>8} {'S: best':>8} {'S: named':>9}" + (f" {'S: claims':>10}" if claims else "")
    lines = [head]
    nan = float("nan")
    for name, s in rows:
        line = (
            f"{name:<{width}} {s['bit_accuracy_mean']:>8.2%} {s['bit_accuracy_min']:>9.2%} "
            f"{s['identification_accuracy']:>11.2%} {s['verified_identification_accuracy']:>8.2%}"
        )
        if claims:
            line += f" {s.get('false_claim_rate', nan):>13.2%}"
        if search:
            t = s.get("search") or {}
            line += (
                f" {t.get('bit_accuracy_mean', nan):>8.2%} {t.get('identification_accuracy', nan):>8.2%}"
                f" {t.get('verified_identification_accuracy', nan):>9.2%}"
            )
            if claims:
                line += f" {t.get('false_claim_rate', nan):>10.2%}"
        lines.append(line)
    if search:
        lines.append(
            f"S: read with the {search['mode']} search ({search['candidates']} candidates; p-values "
            "corrected over candidates × keys)"
        )
    for name, why in (result.get("skipped") or {}).items():
        lines.append(f"{name:<{width}} skipped: {why}")
    return "\n".join(lines)


def attacks_plot(path: Path, results: Mapping[str, Mapping[str, Any]]) -> Path:
    """Bar plot of bit accuracy per attack, with the 50 % chance line: for one run (``{label: result}``) the
    mean over IDs and the worst ID, for several each run's mean over IDs side by side (the attacks of the
    first run, in :func:`attack_order`). Past :data:`HORIZONTAL_FROM` attacks the bars are horizontal."""

    first = next(iter(results.values()))
    names = attack_order(first)
    if len(results) == 1:
        bars = {
            "mean over IDs": [first["attacks"][k]["bit_accuracy_mean"] for k in names],
            "worst ID": [first["attacks"][k]["bit_accuracy_min"] for k in names],
        }
        if first.get("search"):
            bars[f"mean over IDs, {first['search']['mode']} search"] = [
                first["attacks"][k].get("search", {}).get("bit_accuracy_mean", np.nan) for k in names
            ]
    else:
        bars = {
            label: [r["attacks"].get(k, {}).get("bit_accuracy_mean", np.nan) for k in names]
            for label, r in results.items()
        }
    x = np.arange(len(names))
    width = 0.8 / len(bars)
    horizontal = len(names) > HORIZONTAL_FROM
    size = (7.5, 0.16 * len(names) + 1.5) if horizontal else (0.55 * len(names) + 5.0, 3.6)
    fig, ax = plt.subplots(figsize=size)
    for j, (label, values) in enumerate(bars.items()):
        place, heights = x - 0.4 + width * (j + 0.5), np.asarray(values, float) * 100
        if horizontal:
            ax.barh(place, heights, height=width, label=label)
        else:
            ax.bar(place, heights, width=width, label=label)
    if horizontal:
        ax.axvline(50.0, color="grey", linestyle="--", linewidth=1, label="chance")
        ax.set_yticks(x, [_label(n) for n in names], fontsize=6)
        ax.set_ylim(len(names) - 0.5, -0.5)  # the first attack on top, no empty margins
        ax.set_xlabel("bit accuracy (%)")
        ax.set_xlim(0, 100)
    else:
        ax.axhline(50.0, color="grey", linestyle="--", linewidth=1, label="chance")
        ax.set_xticks(x, [_label(n) for n in names], rotation=45, ha="right", fontsize=8)
        ax.set_ylabel("bit accuracy (%)")
        ax.set_ylim(0, 100)
    ax.set_title(f"{first['num_ids']} IDs x {first['views']} views, {title(first)}", fontsize=9)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
