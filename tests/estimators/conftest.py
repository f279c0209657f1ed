"""Shared fixtures of the estimator tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimators import deterioration_ekf as de
from estimators.flea import flea_dir

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def flea_path() -> Path:
    """The FLEA data folder; skips the test when it is absent."""
    path = flea_dir()
    if not (path / "index.csv").is_file():
        pytest.skip(
            f"FLEA data not found at {path} (set FLEETHEALTH_FLEA_DIR to the folder with index.csv)"
        )
    return path


def upgraded_dekf_state(version: int) -> de.DekfState:
    """The deterioration EKF state dumped by its version-``version`` code (a file in ``data``),
    loaded, and so upgraded to the current version."""
    blob = (DATA / f"deterioration_ekf_state_v{version}.bin").read_bytes()
    assert f'"version":{version}'.encode() in blob
    state = de.load_state(blob)
    assert state.version == de.STATE_VERSION
    return state
