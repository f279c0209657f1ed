"""Shared fixtures of the estimator tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from estimators.flea import flea_dir


@pytest.fixture(scope="session")
def flea_path() -> Path:
    """The FLEA data folder; skips the test when it is absent."""
    path = flea_dir()
    if not (path / "index.csv").is_file():
        pytest.skip(
            f"FLEA data not found at {path} (set FLEETHEALTH_FLEA_DIR to the folder with index.csv)"
        )
    return path
