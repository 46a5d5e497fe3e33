"""Several watermarked runs' evaluations side by side, grouped by the settings they differ in.

A setting's figures move from seed to seed by several points, so one run
per setting decides little. :func:`compare_runs` reads each run's ``eval-<split>.json`` (``mnerf evaluate``)
and the ``[watermark]`` section of its ``config.json``, finds the fields whose values differ between the runs
(less the ones that only pick a seed or a schedule's bookkeeping, :data:`IGNORED_BY_DEFAULT`), and groups the
runs by those values: each group is one setting over its seeds, summarised by the mean, the lowest and the
highest of every figure. ``mnerf compare`` prints the tables and can plot PSNR against bit accuracy.

Figures (fractions in [0, 1] except the dB and LPIPS ones):

- ``bits``, ``bits_png``, ``bits_worst_id``: mean bit accuracy over IDs on float renders, on 8-bit PNGs, and
  the lowest ID's.
- ``best_match``: the rendered ID is the best-matching key. ``named_binomial``, ``named_sign_flip``: it is
  also named (corrected p-value below the run's threshold) by that test; ``named_worst_id``: the lowest ID's
  named rate, by the test the run decides by. ``wrong_binomial``,
  ``wrong_sign_flip``: another ID is named. ``clean_claimed_binomial``, ``clean_claimed_sign_flip``: clean
  renders named as some ID.
- ``psnr`` (dB against the ground truth), ``psnr_drop`` (dB, the watermarked renders' PSNR less the clean
  model's: negative is a loss), ``lpips``.

With ``attacks`` (``mnerf compare --attacks SUITE`` / ``--model-attacks SUITE``) each run's scores under an
attack suite (``mnerf attack``'s JSON) are read too, and :func:`attack_table` gives one row per setting and
attack: ``bits``, ``bits_worst_id``, ``best_match``, ``named`` (by the run's decision) and
``false_claims`` (the clean model's renders under the same attack named as a key), each over the seeds.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from mnerf_jax.core.config import flat_items
from mnerf_jax.core.errors import ConfigError, MnerfError
from mnerf_jax.core.watermark_config import translate_flat

# Watermark fields that say which seed ran or how the run was kept, not what was trained: runs that differ
# only in them are seeds of one setting.
IGNORED_BY_DEFAULT: tuple[str, ...] = (
    "seed",
    "key_seed",
    "time_budget.minutes",
    "phase3.reserve_min",
    "checkpoint_every",
    "keep_checkpoints",
)

# (figure, format, header) in table order.
FIGURES: tuple[tuple[str, str, str], ...] = (
    ("bits", "pct", "bits"),
    ("bits_png", "pct", "PNG"),
    ("bits_worst_id", "pct", "worst ID"),
    ("best_match", "pct", "best match"),
    ("named_binomial", "pct", "named (bin.)"),
    ("named_sign_flip", "pct", "named (s-f)"),
    ("named_worst_id", "pct", "worst ID named"),
    ("wrong_binomial", "pct", "wrong ID (bin.)"),
    ("clean_claimed_binomial", "pct", "clean claimed (bin.)"),
    ("psnr", "db", "PSNR"),
    ("psnr_drop", "db", "ΔPSNR"),
    ("lpips", "lpips", "LPIPS"),
)


# The attack rows' figures in table order: (figure, its key in ``mnerf attack``'s JSON, header).
_ATTACK_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("bits", "bit_accuracy_mean", "bits"),
    ("bits_worst_id", "bit_accuracy_min", "worst ID"),
    ("best_match", "identification_accuracy", "best match"),
    ("named", "verified_identification_accuracy", "named"),
    ("false_claims", "false_claim_rate", "false claims"),
)
ATTACK_KEYS: Mapping[str, str] = {figure: key for figure, key, _ in _ATTACK_COLUMNS}
ATTACK_FIGURES: tuple[tuple[str, str, str], ...] = tuple(
    (figure, "pct", header) for figure, _, header in _ATTACK_COLUMNS
)


@dataclasses.dataclass(frozen=True)
class AttackSuite:
    """Which of ``mnerf attack``'s score files to read: a suite of attacks on the renders, or (``model``) on
    the watermarked field (evaluation.attacks.attacks_path, evaluation.model_attacks)."""

    suite: str
    model: bool = False

    def file_name(self, split: str) -> str:
        kind = "model-attacks" if self.model else "attacks"
        return f"eval-{split}-{kind}-{self.suite}.json"

    def command(self, run: Path, split: str) -> str:
        option = "--model-suite" if self.model else "--suite"
        return f"mnerf attack --run {run} --split {split} {option} {self.suite}"


class CompareError(MnerfError):
    """A run that cannot be compared: not a watermarked run, or not evaluated on the split."""


@dataclasses.dataclass(frozen=True)
class RunFigures:
    """One evaluated watermarked run: its directory, its ``[watermark]`` settings and its figures."""

    path: Path
    settings: Mapping[str, Any]
    figures: Mapping[str, float | None]
    views: int
    num_ids: int
    bits: int
    # Per attack (in the suite's order), the ATTACK_FIGURES; empty unless a suite was asked for.
    attacks: Mapping[str, Mapping[str, float | None]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Group:
    """Runs sharing the values of every compared setting (seeds of one setting)."""

    label: str  # "losses.lambda_key=0.1, fidelity.psnr=27.0"; "all runs" when nothing differs
    runs: tuple[RunFigures, ...]

    def stats(self, figure: str) -> tuple[float, float, float] | None:
        """(mean, lowest, highest) of ``figure`` over the runs that report it; None when none does."""
        return _stats([r.figures.get(figure) for r in self.runs])

    def attack_names(self) -> list[str]:
        """The attacks any run was scored under, in the first run's order, then any others'."""
        names: dict[str, None] = {}
        for r in self.runs:
            names |= dict.fromkeys(r.attacks)
        return list(names)

    def attack_stats(self, attack: str, figure: str) -> tuple[float, float, float] | None:
        """(mean, lowest, highest) of an attack row's ``figure`` over the runs scored under it."""
        return _stats([(r.attacks.get(attack) or {}).get(figure) for r in self.runs])


def _stats(values: Iterable[float | None]) -> tuple[float, float, float] | None:
    kept = [v for v in values if v is not None]
    if not kept:
        return None
    return sum(kept) / len(kept), min(kept), max(kept)


# Plain JSON reads, not rundir.read_marker / read_run_config: those import the checkpoint stack (JAX, Orbax),
# and the config parser checks every field against today's Config, where a comparison needs only the
# recorded [watermark] values (by their dotted names; a run written before the sections is translated).
WATERMARK_KIND = "multinerf"  # rundir.WATERMARK_KIND


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CompareError(f"{path}: missing ({what})") from None
    except (OSError, json.JSONDecodeError) as err:
        raise CompareError(f"{path}: unreadable ({err})") from None
    if not isinstance(data, dict):
        raise CompareError(f"{path}: not a JSON object")
    return data


def _by_test(result: Mapping[str, Any], key: str, test: str) -> float | None:
    """A rate of one identification test; the run's own figure when it predates the per-test ones."""
    by_test = result.get(f"{key}_by_test")
    if isinstance(by_test, Mapping) and test in by_test:
        return float(by_test[test])
    own_test = (result.get("identification") or {}).get("test", "binomial")
    return float(result[key]) if key in result and own_test == test else None


def _named_worst_id(result: Mapping[str, Any]) -> float | None:
    """The lowest per-ID named rate, from the decision confusion matrix ``[N, N + 1]`` (the run's test)."""
    confusion = (result.get("identification") or {}).get("confusion_decision")
    if not confusion:
        return None
    counts = [(row[i], sum(row)) for i, row in enumerate(confusion) if sum(row)]
    return min(right / total for right, total in counts) if counts else None


def figures_of(result: Mapping[str, Any]) -> dict[str, float | None]:
    """The compared figures of one ``eval-<split>.json`` (module docstring); None for any it lacks."""

    def get(key: str) -> float | None:
        value = result.get(key)
        return None if value is None else float(value)

    psnr, clean = get("psnr"), get("clean_psnr")
    return {
        "bits": get("bit_accuracy_mean"),
        "bits_png": get("bit_accuracy_png_mean"),
        "bits_worst_id": get("bit_accuracy_min"),
        "best_match": get("identification_accuracy"),
        "named_binomial": _by_test(result, "verified_identification_accuracy", "binomial"),
        "named_sign_flip": _by_test(result, "verified_identification_accuracy", "sign_flip"),
        "named_worst_id": _named_worst_id(result),
        "wrong_binomial": _by_test(result, "misidentification_rate", "binomial"),
        "wrong_sign_flip": _by_test(result, "misidentification_rate", "sign_flip"),
        "clean_claimed_binomial": _by_test(result, "clean_false_detection_rate", "binomial"),
        "clean_claimed_sign_flip": _by_test(result, "clean_false_detection_rate", "sign_flip"),
        "psnr": psnr,
        "psnr_drop": None if psnr is None or clean is None else psnr - clean,
        "lpips": get("lpips"),
    }


def attack_figures_of(result: Mapping[str, Any], where: Path) -> dict[str, dict[str, float | None]]:
    """The ATTACK_FIGURES of every attack of one ``mnerf attack`` score file, in its order."""
    rows = result.get("attacks")
    if not isinstance(rows, Mapping):
        raise CompareError(f"{where}: not a file of mnerf attack's scores")
    order = [a for a in result.get("order") or [] if a in rows] or list(rows)
    return {
        attack: {
            figure: None if rows[attack].get(key) is None else float(rows[attack][key])
            for figure, key in ATTACK_KEYS.items()
        }
        for attack in order
    }


def load_run_figures(
    run_dir: str | Path, split: str = "test", attacks: AttackSuite | None = None
) -> RunFigures:
    """A watermarked run's settings and its figures on ``split`` (and under ``attacks``); CompareError when
    it has none."""
    path = Path(run_dir)
    if not path.is_dir():
        raise CompareError(f"{path}: no such run directory")
    marker = _read_json(path / "run.json", "not a mnerf run directory")
    if marker.get("kind") != WATERMARK_KIND:
        raise CompareError(
            f"{path}: a {marker.get('kind', 'unknown')!r} run, not a watermarked one (mnerf embed)"
        )
    config = _read_json(path / "config.json", "the run's config")
    settings = config.get("watermark")
    if not isinstance(settings, dict):
        raise CompareError(f"{path}/config.json: no [watermark] section")
    result = _read_json(
        path / f"eval-{split}.json", f"evaluate it first: mnerf evaluate --run {path} --split {split}"
    )
    if "bit_accuracy_mean" not in result:
        raise CompareError(f"{path}/eval-{split}.json: not a watermarked run's evaluation")
    try:
        settings = flat_items(translate_flat(settings))
    except ConfigError as err:
        raise CompareError(f"{path}/config.json: {err}") from None
    settings["source_run"] = marker.get("source_run")
    scores: dict[str, dict[str, float | None]] = {}
    if attacks is not None:
        where = path / attacks.file_name(split)
        scores = attack_figures_of(
            _read_json(where, f"score it first: {attacks.command(path, split)}"), where
        )
    return RunFigures(
        path=path,
        settings=settings,
        figures=figures_of(result),
        views=int(result.get("views", 0)),
        num_ids=int(result.get("num_ids", 0)),
        bits=int(result.get("bits", 0)),
        attacks=scores,
    )


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True)


def varying_settings(runs: Sequence[RunFigures], ignore: Iterable[str] = IGNORED_BY_DEFAULT) -> list[str]:
    """The setting names whose values differ between ``runs`` (sorted), less ``ignore``."""
    ignored = set(ignore)
    names = sorted({k for r in runs for k in r.settings} - ignored)
    return [n for n in names if len({_canonical(r.settings.get(n)) for r in runs}) > 1]


def _label(settings: Mapping[str, Any], names: Sequence[str]) -> str:
    def show(value: Any) -> str:
        return value if isinstance(value, str) else _canonical(value)

    return ", ".join(f"{n}={show(settings.get(n))}" for n in names) or "all runs"


def group_runs(runs: Sequence[RunFigures], ignore: Iterable[str] = IGNORED_BY_DEFAULT) -> list[Group]:
    """Runs grouped by the values of their :func:`varying_settings`, in the order each group first appears."""
    names = varying_settings(runs, ignore)
    groups: dict[str, list[RunFigures]] = {}
    for r in runs:
        groups.setdefault(_label(r.settings, names), []).append(r)
    return [Group(label, tuple(members)) for label, members in groups.items()]


def compare_runs(
    run_dirs: Sequence[str | Path],
    split: str = "test",
    ignore: Iterable[str] = IGNORED_BY_DEFAULT,
    attacks: AttackSuite | None = None,
) -> list[Group]:
    """Load every run (all errors before any output) and group them (module docstring)."""
    if not run_dirs:
        raise CompareError("no runs given")
    return group_runs([load_run_figures(d, split, attacks) for d in run_dirs], ignore)


# ----------------------------------------------------------------------------------------------- output


def _format(kind: str, value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return "—"
    if kind == "pct":
        return f"{100.0 * value:.1f} %"
    if kind == "db":
        return f"{value:.2f} dB"
    return f"{value:.3f}"


def _seed(r: RunFigures) -> str:
    return f"{r.settings.get('seed', '?')}/{r.settings.get('key_seed', '?')}"


def runs_table(groups: Sequence[Group]) -> str:
    """Markdown: one row per run (its setting, seed / key seed, every figure)."""
    head = ["setting", "run", "seed / keys", *(h for _, _, h in FIGURES)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g in groups:
        for r in g.runs:
            cells = [g.label, r.path.name, _seed(r), *(_format(k, r.figures.get(f)) for f, k, _ in FIGURES)]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _spread(kind: str, stats: tuple[float, float, float] | None, runs: int) -> str:
    """``mean (lowest – highest)``; the value alone for one run; — for none."""
    if stats is None:
        return "—"
    if runs == 1:
        return _format(kind, stats[0])
    return f"{_format(kind, stats[0])} ({_format(kind, stats[1])} – {_format(kind, stats[2])})"


def summary_table(groups: Sequence[Group]) -> str:
    """Markdown: one row per setting, each figure as mean (lowest – highest) over its runs."""
    head = ["setting", "runs", *(h for _, _, h in FIGURES)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g in groups:
        cells = [g.label, str(len(g.runs)), *(_spread(k, g.stats(f), len(g.runs)) for f, k, _ in FIGURES)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def attack_table(groups: Sequence[Group]) -> str:
    """Markdown: one row per setting and attack, each figure as mean (lowest – highest) over its runs."""
    head = ["setting", "runs", "attack", *(h for _, _, h in ATTACK_FIGURES)]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for g in groups:
        for attack in g.attack_names():
            scored = sum(attack in r.attacks for r in g.runs)
            cells = [g.label, str(scored), attack]
            cells += [_spread(k, g.attack_stats(attack, f), scored) for f, k, _ in ATTACK_FIGURES]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _stats_record(stats: tuple[float, float, float] | None) -> dict[str, float] | None:
    return None if stats is None else dict(zip(("mean", "min", "max"), stats, strict=True))


def to_json(groups: Sequence[Group]) -> dict[str, Any]:
    """Every group with its runs' figures and its (mean, lowest, highest) per figure."""
    return {
        "groups": [
            {
                "setting": g.label,
                "runs": [
                    {
                        "path": str(r.path),
                        "seed": r.settings.get("seed"),
                        "key_seed": r.settings.get("key_seed"),
                        "views": r.views,
                        "num_ids": r.num_ids,
                        "bits": r.bits,
                        "figures": dict(r.figures),
                        "attacks": {a: dict(row) for a, row in r.attacks.items()},
                    }
                    for r in g.runs
                ],
                "stats": {f: _stats_record(g.stats(f)) for f, _, _ in FIGURES},
                "attack_stats": {
                    a: {f: _stats_record(g.attack_stats(a, f)) for f, _, _ in ATTACK_FIGURES}
                    for a in g.attack_names()
                },
            }
            for g in groups
        ]
    }


def tradeoff_plot(path: str | Path, groups: Sequence[Group]) -> Path:
    """PNG: each run's PSNR drop against its bit accuracy, one colour per setting, the group means ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.6), dpi=120)
    for i, g in enumerate(groups):
        pts = [
            (r.figures["bits"], r.figures["psnr_drop"])
            for r in g.runs
            if r.figures.get("bits") is not None and r.figures.get("psnr_drop") is not None
        ]
        if not pts:
            continue
        colour = f"C{i % 10}"
        xs, ys = [100.0 * p[0] for p in pts], [p[1] for p in pts]
        ax.scatter(xs, ys, color=colour, label=f"{g.label} ({len(pts)})", zorder=3)
        ax.scatter(
            [sum(xs) / len(xs)], [sum(ys) / len(ys)], s=160, facecolors="none", edgecolors=colour, zorder=2
        )
    ax.set_xlabel("mean bit accuracy over IDs (%)")
    ax.set_ylabel("PSNR change against the clean model (dB)")
    ax.axhline(0.0, color="0.7", lw=0.8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
