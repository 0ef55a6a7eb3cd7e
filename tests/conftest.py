"""Shared fixtures: the real CT data beside the project, and thread limits for a 2-core machine."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Before torch loads OpenMP: idle threads sleep instead of spinning (tests run beside Snakemake/Slurm jobs).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("CTSPLAT_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real head and abdomen CT); skips the test when it is absent."""
    if not (SHARED_DATA / "ct0051_head").is_dir():
        pytest.skip(f"real CT data not found at {SHARED_DATA} (expected ../shared/data beside the repository)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def ct0051_head(shared_data: Path) -> Path:
    return shared_data / "ct0051_head"


@pytest.fixture(scope="session")
def totalseg_j2k(shared_data: Path) -> Path:
    path = shared_data / "totalseg_abdomen_j2k"
    if not path.is_dir():
        pytest.skip(f"{path} not found")
    return path


@pytest.fixture(autouse=True, scope="session")
def _limit_threads() -> None:
    import torch

    torch.set_num_threads(min(2, os.cpu_count() or 1))
