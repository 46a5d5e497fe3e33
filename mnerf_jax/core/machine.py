"""The machine a run is measured on, in words, for the records that carry timings (study cells, decoder
training): the project's CPU kinds share model names but differ in speed and in float results, so the vector
instruction set is named too."""

from __future__ import annotations

import contextlib
import os
import platform
from pathlib import Path

import jax

CPUINFO = Path("/proc/cpuinfo")


def cpu_description(cpuinfo: str | None = None) -> str:
    """``"<model name> (AVX-512 | AVX2)"`` from ``/proc/cpuinfo`` (or the text given); the platform's
    processor name where there is no such file."""
    if cpuinfo is None:
        cpuinfo = ""
        with contextlib.suppress(OSError):
            cpuinfo = CPUINFO.read_text()
    lines = cpuinfo.splitlines()
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    cpu = names[0] if names else (platform.processor() or platform.machine())
    flags = next((line.split(":", 1)[1].split() for line in lines if line.startswith("flags")), [])
    isa = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else ""
    return f"{cpu} ({isa})" if isa else cpu


def describe() -> str:
    """CPU model and vector ISA, cores, Python, JAX and its first device, e.g. ``"AMD EPYC (AVX2), 2 cores,
    Python 3.11.7, jax 0.10.2 (cpu: cpu)"``."""
    device = jax.devices()[0]
    return (
        f"{cpu_description()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"jax {jax.__version__} ({device.platform}: {device.device_kind})"
    )
