"""Shared fixtures: the ``ci`` sample is simulated once per test session.

The suite runs on every core (pytest-xdist, ``-n auto`` in pyproject.toml). What is costly and
the same for every worker is made once for the whole session, by the first worker that needs it,
under a file lock (``_made_once``): the simulated samples and the shared stage cache, so that a
run one worker made is copied, verified, by the others instead of being computed again."""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import gc
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest

from simulator.presets import preset_config

CI_CONFIG = Path(__file__).resolve().parents[1] / "deploy" / "configs" / "ci.yaml"
from simulator.run import simulate


def _session_root(tmp_path_factory) -> Path:
    """The folder every worker of this session shares (a worker's own base folder's parent)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


class _SessionLock:
    """An exclusive lock on ``name`` among the workers of this session (fcntl, released on exit
    or when the worker dies)."""

    def __init__(self, tmp_path_factory, name: str):
        self.path = _session_root(tmp_path_factory) / f".{name}.lock"

    def __enter__(self):
        self._file = open(self.path, "w")
        fcntl.flock(self._file, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc):
        fcntl.flock(self._file, fcntl.LOCK_UN)
        self._file.close()


def _made_once(tmp_path_factory, name: str, make: Callable[[Path], object]) -> Path:
    """``<session root>/name``, made by ``make(path)`` by the first worker that asks for it (the
    others wait for it, then reuse it); a half-made one (its maker failed) is made again."""
    target = _session_root(tmp_path_factory) / name
    done = target.parent / f".{name}.done"
    with _SessionLock(tmp_path_factory, name):
        if not done.exists():
            shutil.rmtree(target, ignore_errors=True)
            target.parent.mkdir(parents=True, exist_ok=True)
            make(target)
            done.touch()
    return target


@pytest.fixture(scope="session", autouse=True)
def _traceback_logs_in_a_temporary_folder(tmp_path_factory):
    """The command line's traceback logs (flows.cli) go under the session's temporary folder."""
    os.environ["WELDRECON_LOG_DIR"] = str(tmp_path_factory.mktemp("logs"))


@pytest.fixture(scope="session", autouse=True)
def _one_stage_cache_for_the_session(tmp_path_factory):
    """Every run folder of the session (the flows, the command lines they start, the stage
    tests) shares one stage cache (``$WELDRECON_STAGE_CACHE``, data_catalog.stages.StageStore):
    a stage made once for the same data, settings and code is copied, verified, into the next
    folder that needs it. Tests of recomputation itself turn it off (``no_stage_cache``)."""
    os.environ["WELDRECON_STAGE_CACHE"] = str(_made_once(tmp_path_factory, "stage-cache", Path.mkdir))


@pytest.fixture
def no_stage_cache(monkeypatch):
    """This test's runs make every stage in their own folder (no shared stage cache)."""
    monkeypatch.delenv("WELDRECON_STAGE_CACHE", raising=False)


@pytest.fixture
def collected_after():
    """The garbage collected as the test ends: for the tests that start Dask clusters, whose
    nannies change the logging when they are collected (tests/flows/cli.py ``_logging_state``)."""
    yield
    gc.collect()


@pytest.fixture(scope="session")
def ci_sample(tmp_path_factory) -> Path:
    return _made_once(tmp_path_factory, "ci-sample", lambda out: simulate(preset_config("ci"), out))


@pytest.fixture(scope="session")
def demo_sample(tmp_path_factory) -> Path:
    """The ``demo`` preset's sample (32 passes, 6.3 M points), without previews."""
    return _made_once(tmp_path_factory, "demo-sample", lambda out: simulate(preset_config("demo"), out, previews=False))


@pytest.fixture(scope="session")
def ci_config():
    return preset_config("ci")


@pytest.fixture(scope="session")
def no_pose_log_sample(ci_sample, tmp_path_factory) -> Path:
    """The ``ci`` sample from a cell that logs no flange pose per profile (``log_profile_poses:
    false``): its passes are placed by their nominal sweeps alone. The profiles are the ci
    sample's (the simulator draws nothing for the log): made from it, not simulated again."""
    from tests.flows.samples import without_pose_logs

    return _made_once(tmp_path_factory, "no-pose-log-sample", lambda out: without_pose_logs(ci_sample, out))


def _reconstructed(sample: Path, out: Path, *, lock=None, stop_after: str | None = None, config=CI_CONFIG):
    """``sample`` reconstructed into ``out`` (real Prefect engine, the settings ``config``, ci.yaml unless named): (run folder, report),
    the report as published (tests.flows.samples.as_published; a run stopped after the stage
    ``stop_after`` publishes none: its stages' refs and metrics only). ``lock``: a _SessionLock held
    while it runs, so that a second worker reconstructing the same sample waits and then copies
    the stages from the stage cache instead of making them too."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.reconstruct import reconstruct_sample

    from tests.flows.samples import as_published

    with lock or contextlib.nullcontext():
        return out, as_published(reconstruct_sample(str(sample), str(out), str(config), started_by="pytest",
                                                    stop_after=stop_after))


# the T-joint's top setup: what the tjoint-single preset scans
TJOINT_TOP = ["top-Y01", "top-Y02", "top-Y03", "top-Y04", "top-Y05", "top-Y06", "top-Y07", "top-Y08", "top-X01",
              "top-X02"]


@pytest.fixture(scope="session")
def tjoint_sample(tmp_path_factory) -> Path:
    return _made_once(tmp_path_factory, "tjoint-sample",
                      lambda out: simulate(preset_config("tjoint"), out, previews=False))


@pytest.fixture(scope="session")
def tjoint_run(tjoint_sample, tmp_path_factory):
    """The T-joint, both setups, reconstructed once with the ci settings up to the surface mesh (not
    the weld stage, which a run stopped after mesh does not need: ``tjoint_weld`` makes it):
    (run folder, report as tests.flows.samples.as_published gives it)."""
    return _reconstructed(tjoint_sample, tmp_path_factory.mktemp("recon-tjoint") / "run", stop_after="mesh",
                          lock=_SessionLock(tmp_path_factory, "tjoint-run"))


@pytest.fixture(scope="session")
def tjoint_single_sample(tjoint_sample, tmp_path_factory) -> Path:
    """The T-joint's top setup alone (the tjoint-single preset's passes), truth included."""
    import shutil

    from tests.flows.samples import copy_sample

    sample = copy_sample(tjoint_sample, tmp_path_factory.mktemp("tjoint-single") / "sample", TJOINT_TOP)
    shutil.copytree(tjoint_sample / "truth", sample / "truth")
    return sample


@pytest.fixture(scope="session")
def tjoint_single_run(tjoint_single_sample, tmp_path_factory):
    """The T-joint's top setup reconstructed up to the surface mesh, as ``tjoint_run``."""
    return _reconstructed(tjoint_single_sample, tmp_path_factory.mktemp("recon-tjoint-single") / "run",
                          stop_after="mesh",
                          lock=_SessionLock(tmp_path_factory, "tjoint-single-run"))


@pytest.fixture(scope="session")
def cruciform_sample(tmp_path_factory) -> Path:
    return _made_once(tmp_path_factory, "cruciform-sample",
                      lambda out: simulate(preset_config("cruciform"), out, previews=False))


@pytest.fixture(scope="session")
def cruciform_run(cruciform_sample, tmp_path_factory):
    """The cruciform, both setups, reconstructed once up to the weld stage (its four fillet welds
    measured, every 2 mm: tests.flows.samples.FILLET_CONFIG; no mesh): (run folder, report as
    ``tjoint_run``'s)."""
    from tests.flows.samples import FILLET_CONFIG

    return _reconstructed(cruciform_sample, tmp_path_factory.mktemp("recon-cruciform") / "run", stop_after="weld",
                          lock=_SessionLock(tmp_path_factory, "cruciform-run"), config=FILLET_CONFIG)


@pytest.fixture(scope="session")
def ci_run(ci_sample, tmp_path_factory):
    """The ``ci`` sample reconstructed once: (run folder, report)."""
    return _reconstructed(ci_sample, tmp_path_factory.mktemp("recon") / "run",
                          lock=_SessionLock(tmp_path_factory, "ci-run"))


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
    """The six-pass subset reconstructed once with the quick settings (tests.flows.samples.QUICK_CONFIG,
    as every test that runs this subset whole): (run folder, report)."""
    from tests.flows.samples import QUICK_CONFIG

    return _reconstructed(six_sample, tmp_path_factory.mktemp("recon-six") / "run", config=QUICK_CONFIG,
                          lock=_SessionLock(tmp_path_factory, "six-run"))


_OWN_HOME: Path | None = None
_SERVICES_NO_TEST_READS = ("task_run_recorder", "event_persister", "triggers", "block_registration")
_API_SERVER = None  # flows.api_server.TemporaryAPIServer, when this process started the session's


def pytest_configure(config):
    """Prefect's home (its database, its local result storage) and weldrecon's cache of code
    versions are this test process's own temporary folder, set before anything imports Prefect,
    not the user's ``~/.prefect`` and ``~/.cache/weldrecon``: the tests leave nothing there (the
    Prefect database had grown to 400 MB). Each test process starts one temporary Prefect API
    server here, while pytest collects (flows.api_server): every flow of the process, its Dask
    workers and the command lines it starts (which inherit PREFECT_API_URL) report to it instead
    of each starting a server of its own; the kernel stops it when the process dies, however it
    dies. One server per test worker, not one for all: a suite run with one for both workers had a
    core idle for about a minute at a time while both ran flows (not seen with one each; the cause
    not pinned down). What the caller set (PREFECT_HOME, PREFECT_API_URL, WELDRECON_CACHE_DIR) is
    kept. The folder is removed at exit, after the server has stopped."""
    global _OWN_HOME, _API_SERVER
    if not hasattr(config, "workerinput") and config.getoption("numprocesses", None):
        return  # the controller of the test workers runs no test
    from flows.api_server import TemporaryAPIServer

    _OWN_HOME = Path(tempfile.mkdtemp(prefix="weldrecon-tests-"))
    atexit.register(shutil.rmtree, _OWN_HOME, ignore_errors=True)
    if not (os.environ.get("PREFECT_HOME") or os.environ.get("PREFECT_API_URL")):
        os.environ["PREFECT_HOME"] = str(_OWN_HOME / "prefect")
    os.environ.setdefault("WELDRECON_CACHE_DIR", str(_OWN_HOME / "cache"))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    if not os.environ.get("PREFECT_API_URL"):
        # without the services that record each task run's states and every event in the database
        # (no test reads them back; the flow runs, their states and logs are recorded as ever) and
        # without registering Prefect's block types (none is used): measured on a six-pass run,
        # the server's CPU 20.5 -> 16.2 s to start and 4.0 -> 2.8 s to serve the run
        _API_SERVER = TemporaryAPIServer.launch(log=_OWN_HOME / "prefect-api-server.log",
                                                without=_SERVICES_NO_TEST_READS)
        os.environ["PREFECT_API_URL"] = _API_SERVER.url  # before anything imports Prefect
        # stopped at exit, after Prefect's own exit handlers (registered later, run first) have
        # sent what they still hold
        atexit.register(_API_SERVER.stop)


@pytest.fixture(scope="session", autouse=True)
def _the_sessions_prefect_api():
    """This process's Prefect API answers before any test runs (it starts while pytest collects);
    the flows' last log lines are sent to it at the end."""
    from flows.api_server import wait_for_api

    yield _API_SERVER.wait_ready() if _API_SERVER is not None else wait_for_api(os.environ["PREFECT_API_URL"])
    if "prefect" in sys.modules:
        from prefect.logging.handlers import APILogHandler

        with contextlib.suppress(Exception):
            APILogHandler().flush()


# --- tiers: after the costliest files (``_COSTLIEST`` below), the suite runs fastest first ---
# 1: known answers on in-memory arrays and documents (tasks, schemas, the layout, the docs);
# 2: storage and the simulated cell (data_catalog, simulator, deploy);
# 3: stages through the runner and the flows end to end (flows).
_TIERS = (("tests/tasks/", "tests/schemas/", "tests/test_layering.py", "tests/test_docs.py"),
          ("tests/data_catalog/", "tests/simulator/", "tests/deploy/"),
          ("tests/flows/",))


def _tier(item) -> int:
    path = _relative(item)
    return next((k for k, prefixes in enumerate(_TIERS) if path.startswith(prefixes)), len(_TIERS))


# what the session makes once, by the first worker that needs it (the others wait for it)
_MADE_ONCE = {"ci_sample", "no_pose_log_sample", "six_sample", "tjoint_sample", "tjoint_single_sample", "ci_run", "six_run",
              "tjoint_run", "tjoint_single_run", "cruciform_sample", "cruciform_run"}


# The costliest files, in the order the workers take them (pyproject.toml: ``--dist loadfile
# --no-loadscope-reorder``: a worker takes a whole file, the next in this order when it is free;
# xdist's own order, by the number of tests in a file, ignores their cost). The longest first, so
# that the many short files even out the end; and each pair the two workers start side by side
# needs different made-once samples, so that neither waits for the other to make one: the
# six-pass run (resilience) beside the T-joint's; the ``ci`` run beside the cruciform's; then the
# files that reuse them. Seconds: one suite run's sum of the file's setup and calls (2026-11-28,
# 2 cores). A file not named here follows them, in its tier.
_COSTLIEST = ("tests/flows/test_resilience_audit.py",  # 103 s, makes the six-pass run (66 s)
              "tests/flows/test_reconstruct_tjoint.py",  # 110 s, the T-joint's runs
              "tests/flows/test_reconstruct_ci.py",  # 55 s, makes the ci run
              "tests/flows/test_reconstruct_cruciform.py",  # 73 s
              "tests/flows/test_stress_stage.py",  # 59 s, on the ci run
              "tests/flows/test_cli_errors.py",  # 103 s, a full disk on the six-pass run's stages
              "tests/deploy/test_service.py",  # 48 s, on the six-pass run's stages
              "tests/flows/test_consistency_checks.py",  # 38 s
              "tests/flows/test_measure_weld_cli.py",  # 34 s
              "tests/flows/test_batch.py",  # 29 s
              "tests/flows/test_per_pass_blocks.py",  # 28 s
              "tests/flows/test_plate_flow.py",  # 23 s
              "tests/flows/test_follow.py",  # 23 s
              "tests/flows/test_stage_keys.py",  # 22 s
              "tests/flows/test_declared_part_flow.py")  # 25 s, a six-pass run declared as another part


def _relative(item) -> str:
    return Path(str(item.fspath)).resolve().relative_to(Path(__file__).resolve().parents[1]).as_posix()


def _order(item) -> tuple[int, int, bool]:
    """The costliest files first (``_COSTLIEST``); then by tier, and within one, the tests that
    need none of the session's samples first."""
    path = _relative(item)
    first = _COSTLIEST.index(path) if path in _COSTLIEST else len(_COSTLIEST)
    return first, _tier(item), bool(_MADE_ONCE & set(item.fixturenames))


def pytest_collection_modifyitems(session, config, items):
    items.sort(key=_order)  # stable: otherwise the files' own order
