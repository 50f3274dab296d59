"""``flows.reconstruct._run_when_ready``, the whole-sample stages in Prefect's real thread pool: each
starts as soon as the stages it needs are done, so independent ones run side by side (the stress
beside the mesh); a failure submits nothing more and the first failed stage in registry order is
the one raised."""

from __future__ import annotations

import threading
from typing import NamedTuple

import pytest
from prefect import flow, task
from prefect.task_runners import ThreadPoolTaskRunner

from flows.reconstruct import _run_when_ready


class _Stage(NamedTuple):
    name: str
    needs: tuple[str, ...]


# the registry's shape after the weld: mesh and stress need only what is done, volume the mesh,
# the report all three
STAGES = [_Stage("mesh", ("segment",)), _Stage("stress", ("segment", "weld")), _Stage("volume", ("mesh", "weld")),
          _Stage("report", ("mesh", "volume", "stress"))]


@task
def _work(name: str, inputs: dict, started: dict, failing: set) -> str:
    started[name].set()
    if name == "mesh":  # ends only once the stress has started beside it: run one after the other, it fails
        if not started["stress"].wait(60):
            raise RuntimeError("the stress did not start while the mesh ran")
    if name in failing:
        raise ValueError(f"{name} failed")
    return f"{name}({','.join(f'{k}={v}' for k, v in sorted(inputs.items()))})"


def _events() -> dict[str, threading.Event]:
    return {s.name: threading.Event() for s in STAGES}


def _run(failing: set[str], started: dict[str, threading.Event]) -> dict:
    @flow(task_runner=ThreadPoolTaskRunner(max_workers=2))
    def whole_sample() -> dict:
        return _run_when_ready(STAGES, {"segment": "S", "weld": "W"},
                               lambda stage, inputs: _work.submit(stage.name, inputs, started, failing))

    return whole_sample()


def test_independent_stages_run_side_by_side_and_each_gets_its_inputs():
    refs = _run(set(), _events())
    assert refs["mesh"] == "mesh(segment=S)" and refs["stress"] == "stress(segment=S,weld=W)"
    assert refs["volume"] == "volume(mesh=mesh(segment=S),weld=W)"
    assert refs["report"] == "report(mesh=mesh(segment=S),stress=stress(segment=S,weld=W)," \
                             "volume=volume(mesh=mesh(segment=S),weld=W))"


def test_a_failure_stops_what_needs_it_and_the_first_in_registry_order_is_raised():
    with pytest.raises(ValueError, match="^mesh failed$"):  # the stress failed too, beside it
        _run({"mesh", "stress"}, _events())
    started = _events()
    with pytest.raises(ValueError, match="^stress failed$"):
        _run({"stress"}, started)
    assert started["mesh"].is_set() and not started["report"].is_set()  # the report was never submitted
