"""Shared fixtures: the ``ci`` sample is simulated once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from simulator.presets import preset_config

CI_CONFIG = Path(__file__).resolve().parents[1] / "deploy" / "configs" / "ci.yaml"
from simulator.run import simulate


@pytest.fixture(scope="session", autouse=True)
def _traceback_logs_in_a_temporary_folder(tmp_path_factory):
    """The command line's traceback logs (flows.cli) go under the session's temporary folder."""
    import os

    os.environ["WELDRECON_LOG_DIR"] = str(tmp_path_factory.mktemp("logs"))


@pytest.fixture(scope="session")
def ci_sample(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ci") / "sample"
    simulate(preset_config("ci"), out)
    return out


@pytest.fixture(scope="session")
def ci_config():
    return preset_config("ci")


def _reconstructed(sample: Path, out: Path):
    """``sample`` reconstructed into ``out`` (real Prefect engine, ci settings): (run folder, report)."""
    import os

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.reconstruct import reconstruct_sample

    return out, reconstruct_sample(str(sample), str(out), str(CI_CONFIG), started_by="pytest")


@pytest.fixture(scope="session")
def ci_run(ci_sample, tmp_path_factory):
    """The ``ci`` sample reconstructed once: (run folder, report)."""
    return _reconstructed(ci_sample, tmp_path_factory.mktemp("recon") / "run")


# a subset of the ci sample that reconstructs on its own (both setups, 3 passes each, the two
# rolled ones of each setup seeing the side walls' 11 stickers from both; its mesh is open where
# the subset leaves the part unscanned): for tests of the plumbing around a run, at ~half the cost
# of the whole ci sample
SIX = ["top-L02", "top-L04", "top-L05", "bottom-L02", "bottom-L04", "bottom-L05"]


@pytest.fixture(scope="session")
def six_sample(ci_sample, tmp_path_factory) -> Path:
    from tests.flows.samples import copy_sample

    return copy_sample(ci_sample, tmp_path_factory.mktemp("six") / "sample", SIX)


@pytest.fixture(scope="session")
def six_run(six_sample, tmp_path_factory):
    """The six-pass subset reconstructed once: (run folder, report)."""
    return _reconstructed(six_sample, tmp_path_factory.mktemp("recon-six") / "run")


@pytest.fixture(scope="session", autouse=True)
def _one_prefect_api_that_dies_with_pytest():
    """One temporary Prefect API server for the whole session, started before any flow runs, as
    the command line starts its own (flows.reconstruct.prefect_api_for_workers): the kernel stops it
    when pytest dies, however it dies (Prefect's own in-process server outlived a kill -9), and
    every flow of the session, its Dask workers and the command lines it starts (which inherit
    PREFECT_API_URL) report to it instead of each starting a server of its own. Stopped while
    pytest's output is still open. A PREFECT_API_URL set by the caller is used as it is."""
    import os

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.reconstruct import prefect_api_for_workers

    with prefect_api_for_workers() as url:
        yield url
