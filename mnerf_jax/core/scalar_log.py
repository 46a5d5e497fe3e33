"""Training curves of ``mnerf embed`` as TensorBoard scalars (``WMRUN/tb``, as ``mnerf fit`` writes
``RUN/tb``), and a reader of such event files for scripts and tests that need no TensorBoard install.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

# Each scalar is the mean of a metric over this many steps.
LOG_EVERY = 10
LOGGED_METRICS = (
    "loss",
    "bce",
    "key_ce",
    "perceptual",
    "bit_acc",
    "psnr",
    "psnr_clean",
    "psnr_budget",
    "fidelity",
    "loss_patch",
)


class ScalarLog:
    """Scalars ``train/<metric>`` in ``out/tb``: each metric of :data:`LOGGED_METRICS` the step reports, as
    its mean over :data:`LOG_EVERY` steps, at the step that ends them (a resumed run appends)."""

    def __init__(self, out: Path):
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(str(Path(out) / "tb"))
        self.window: list[dict[str, float]] = []
        self.step = 0

    def add(self, step: int, metrics: dict[str, float], last: bool = False) -> None:
        """Step ``step``'s (0-based) metrics; ``last``: the run ends here, so write what is pending."""
        self.window.append(metrics)
        self.step = step + 1
        if self.step % LOG_EVERY == 0 or last:
            self._write()

    def _write(self) -> None:
        for name in LOGGED_METRICS:
            values = [m[name] for m in self.window if name in m]
            if values:
                self.writer.add_scalar(f"train/{name}", float(np.mean(values)), self.step)
        self.window = []

    def close(self) -> None:
        """Write what is pending (a run the time budget or an error ended between two log points)."""
        if self.window:
            self._write()
        self.writer.flush()
        self.writer.close()


def read_scalars(folder: str | Path) -> dict[str, list[tuple[int, float]]]:
    """``{tag: [(step, value), ...]}`` of the scalar events in ``folder``'s event files, in file order.

    An event file is TFRecord-framed: u64 length, u32 CRC, an ``Event`` protobuf, u32 CRC per record (the CRCs
    are not checked; a truncated last record, as a killed run leaves, is skipped).
    """
    from tensorboardX.proto import event_pb2

    scalars: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(Path(folder).glob("events.out.tfevents.*")):
        data, at = path.read_bytes(), 0
        while at + 12 <= len(data):
            (length,) = struct.unpack("<Q", data[at : at + 8])
            if at + 16 + length > len(data):
                break
            event = event_pb2.Event.FromString(data[at + 12 : at + 12 + length])
            at += 16 + length
            for value in event.summary.value:
                scalars.setdefault(value.tag, []).append((int(event.step), float(value.simple_value)))
    return scalars
