"""Shared fixtures: the real scenes under ../shared/data, skipped with a reason where absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Tests run on CPU; keep XLA from grabbing an accelerator if one happens to be present.
os.environ.setdefault("JAX_PLATFORMS", "cpu")

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MNERF_SHARED_DATA", PROJECT_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    path = SHARED_DATA / "nerf_synthetic" / "lego"
    if not (path / "transforms_train.json").is_file():
        pytest.skip(f"real NeRF-Synthetic lego not found at {path} (set MNERF_SHARED_DATA)")
    return path


@pytest.fixture(scope="session")
def fern_dir() -> Path:
    path = SHARED_DATA / "nerf_llff_data" / "fern"
    if not (path / "poses_bounds.npy").is_file():
        pytest.skip(f"real LLFF fern not found at {path} (set MNERF_SHARED_DATA)")
    return path
