"""How a watermarked run names an ID: the decision's threshold and test, given on the command line,
calibrated on clean images (``WMRUN/calibration.json``, written by ``scripts/false_claims.py``) or the run's
config (``watermark.reading.id_threshold`` / ``id_test``), in that order.

A calibration holds, per test, the threshold found for a stated false-claim rate (:mod:`reader.calibration`)
with the decoder's fingerprint and the read it was measured with (window, background, jitter, wavelet). It
applies only to that decoder read that way: another read changes the statistic, so the rule falls back to the
config's threshold and says why.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from mnerf_jax.core import rundir
from mnerf_jax.core.errors import MnerfError
from mnerf_jax.reader import calibration, significance

CALIBRATION_FILE = "calibration.json"
CALIBRATE_HINT = "scripts/false_claims.py --run WMRUN calibrates it"


def read_settings(reading: Any) -> dict[str, Any]:
    """What a calibration depends on in a ``watermark.reading`` config: the window, its background, the
    jitter, the side it is read at and the wavelet."""
    return {
        "window": float(reading.window),
        "background": float(reading.background),
        "jitter": int(reading.jitter),
        "max_side": int(reading.max_side),
        "wavelet": str(reading.wavelet),
    }


@dataclasses.dataclass(frozen=True)
class DecisionRule:
    """The threshold on the corrected p-value of ``test`` below which an ID is named; ``source``: ``given``,
    ``calibrated`` or ``config``; ``calibration``: the calibration entry used (None unless calibrated);
    ``note``: why a run's calibration was not used (empty when there is none, or it was)."""

    threshold: float
    test: str
    source: str
    calibration: dict[str, Any] | None = None
    note: str = ""

    def describe(self) -> str:
        """``threshold T (binomial test; calibrated on M clean images: k named, rate ≤ R at 95 %)``, or
        why it is uncalibrated."""
        head = f"threshold {self.threshold:.3g} ({self.test.replace('_', '-')} test; "
        if self.calibration is not None:
            return head + calibration.describe(self.calibration) + ")"
        why = "set by --threshold" if self.source == "given" else "the run's watermark.reading.id_threshold"
        return head + f"{why}, uncalibrated: {self.note or CALIBRATE_HINT})"

    def as_record(self) -> dict[str, Any]:
        """The rule as JSON fields: ``threshold``, ``test``, ``threshold_source``, ``calibration``."""
        return {
            "threshold": self.threshold,
            "test": self.test,
            "threshold_source": self.source,
            "calibration": self.calibration,
        }


def load_calibration(run_dir: str | Path) -> dict[str, Any] | None:
    """``WMRUN/calibration.json`` or None; MnerfError for a file that is not a calibration."""
    path = Path(run_dir) / CALIBRATION_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise MnerfError(f"{path} is not valid JSON ({err}); calibrate again or remove it") from None
    if not isinstance(data, dict) or not isinstance(data.get("tests"), dict):
        raise MnerfError(f"{path} is not a calibration (no 'tests'); calibrate again or remove it")
    return data


def write_calibration(run_dir: str | Path, data: dict[str, Any]) -> Path:
    """Write ``data`` as ``WMRUN/calibration.json`` (atomically) and return the path."""
    path = Path(run_dir) / CALIBRATION_FILE
    rundir.write_json_atomic(path, data)
    return path


def decision_rule(
    run_dir: str | Path,
    reading: Any,
    decoder_fingerprint: str,
    threshold: float | None = None,
    test: str | None = None,
) -> DecisionRule:
    """The rule a run decides by: ``test`` (default the config's ``id_test``) at ``threshold`` when given,
    else at the calibrated threshold of that test when ``calibration.json`` matches the decoder and the read
    (``reading``, a ``watermark.reading`` config), else at the config's ``id_threshold``."""
    test = significance.check_test(reading.id_test if test is None else test)
    if threshold is not None:
        return DecisionRule(float(threshold), test, "given")
    saved = load_calibration(run_dir)
    note = ""
    if saved is not None:
        entry = saved["tests"].get(test)
        if saved.get("decoder_fingerprint") != decoder_fingerprint:
            note = f"{CALIBRATION_FILE} was measured with another decoder; calibrate again"
        elif saved.get("read") != read_settings(reading):
            then, now = saved.get("read") or {}, read_settings(reading)
            diff = ", ".join(f"{k} {then.get(k)} (now {v})" for k, v in now.items() if then.get(k) != v)
            note = f"{CALIBRATION_FILE} was measured reading with {diff}"
        elif entry is None:
            note = f"{CALIBRATION_FILE} has no {test} entry"
        else:
            return DecisionRule(float(entry["threshold"]), test, "calibrated", dict(entry))
    return DecisionRule(float(reading.id_threshold), test, "config", None, note)
