"""Fixtures shared across test modules."""

from __future__ import annotations

from pathlib import Path

import pytest

from parksim.cli import main


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``parksim synth tiny`` (4 fisheyes, 160x120, 12 frames at 10 Hz), made once for the whole session.

    Shared by many modules: read it, never write into it or beside it (copy it to change it).
    """
    out = tmp_path_factory.mktemp("tiny-shared") / "tiny"
    assert main(["synth", "tiny", "-o", str(out), "--quiet"]) == 0
    return out
