"""Shared fixtures: where ../shared/data lives (tests that need it skip when it is absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated `tiny` capture (seed 0), made once per test session. Treat it as read-only."""
    from lightstage.capture.simulate import simulate_capture

    return simulate_capture(tmp_path_factory.mktemp("sim") / "tiny", preset="tiny", seed=0, progress=False)
