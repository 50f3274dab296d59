"""Shared fixtures: the ``ci`` sample is simulated once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from simulator.presets import preset_config
from simulator.run import simulate


@pytest.fixture(scope="session")
def ci_sample(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ci") / "sample"
    simulate(preset_config("ci"), out)
    return out


@pytest.fixture(scope="session")
def ci_config():
    return preset_config("ci")
