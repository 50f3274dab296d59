"""The verdict while the part is still clamped, on the ``demo`` preset (32 passes, 6.3 M points) at
ten times the robot's pace: ``weldrecon reconstruct --follow`` publishes the provisional weld
verdict, mesh, FE model with its stress, and QA page before the whole-sample stages that replace
them, and ends with the same files as a run on the finished sample.

The passes land as bench/replay_scan.py lands them (copied under a hidden name, renamed when the
robot would have finished the pass): the replay costs no CPU, as beside a real cell. Nothing is
timed; the order is read from the audit trail. What the lags are at the robot's own pace on the
paper preset is in bench/README.md."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from bench.replay_scan import replay
from data_catalog.audit import read_trail
from tests.flows.cli import REPO, cli_env

DEMO_CONFIG = REPO / "deploy" / "configs" / "demo.yaml"
WHOLE_SAMPLE = ("registration", "refine", "merge", "segment", "weld", "mesh", "export", "volume", "stress", "report",
                "qa_report")


def _reconstruct(sample: Path, out: Path, log: Path, *follow: str) -> subprocess.Popen:
    """``weldrecon reconstruct`` in a process of its own, with the demo's settings and no stage
    cache: every stage made by this run."""
    env = cli_env()
    env.pop("WELDRECON_STAGE_CACHE", None)
    with open(log, "w") as err:
        return subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(sample), "--out", str(out),
                                 "--config", str(DEMO_CONFIG), *follow], cwd=REPO, env=env,
                                stdout=subprocess.DEVNULL, stderr=err)


def _whole_sample_stages(trail: list[dict]) -> dict[str, dict]:
    return {e["stage"]: e for e in trail if e.get("kind") == "stage" and e.get("item") is None}


def _outputs(entry: dict) -> dict[str, str]:
    """A stage entry's outputs' sha256 (not its record: when and by which flow run it was made)."""
    return {path: digest for path, digest in entry["artefacts"].items() if not path.endswith("/record.json")}


@pytest.mark.slow
def test_the_demo_at_ten_times_the_robots_pace(demo_sample, tmp_path):
    live, run, done = tmp_path / "live", tmp_path / "run", tmp_path / "done"
    landing = threading.Thread(target=replay, args=(demo_sample, live, 10.0))
    landing.start()
    try:
        follow = _reconstruct(live, run, tmp_path / "follow.err", "--follow", "--follow-timeout", "600")
    finally:
        landing.join()
    # the run on the finished sample, beside the follow's last steps (the finished sample is the
    # same folder the replay copied from)
    whole = _reconstruct(demo_sample, done, tmp_path / "done.err")
    try:
        assert follow.wait(timeout=1800) == 0, (tmp_path / "follow.err").read_text()[-3000:]
        assert whole.wait(timeout=1800) == 0, (tmp_path / "done.err").read_text()[-3000:]
    finally:
        for process in (follow, whole):
            if process.poll() is None:
                process.kill()
    _check(demo_sample, run, done)


def _check(demo_sample: Path, run: Path, done: Path) -> None:
    passes = sum(1 for _ in (demo_sample / "passes").iterdir())
    trail = read_trail(run)
    seq = {e["seq"]: i for i, e in enumerate(trail)}
    stages = _whole_sample_stages(trail)
    assert set(stages) == set(WHOLE_SAMPLE), sorted(stages)
    # the verdict on every pass, then the mesh, then the FE model, the stress and the QA page, each
    # published before the whole-sample stage that replaces it (and so before the last pass's
    # whole-sample stages finished)
    verdict = [e for e in trail if e["kind"] == "provisional-published" and e["passes"] == passes]
    meshes = [e for e in trail if e["kind"] == "provisional-mesh-published" and e["passes"] == passes]
    models = [e for e in trail if e["kind"] == "provisional-model-published" and e["passes"] == passes]
    assert len(verdict) == 1 and len(meshes) == 1 and len(models) == 1, (verdict, meshes, models)
    assert seq[verdict[0]["seq"]] < seq[meshes[0]["seq"]] < seq[models[0]["seq"]] < seq[stages["registration"]["seq"]]
    # the FE model: a remesh gmsh stalls on is given up after flows.provisional.MODEL_TIMEOUT_S of CPU
    # time and the provisional surface's own triangles kept (seen: gmsh's patch classification stalled
    # 9 minutes on one provisional mesh; on another run's the model was remeshed in ~70 s). CPU time,
    # not the wall clock's: in CI, beside the other tests, under a limit of 120 s of wall time no model
    # was made (why, the test did not say then; beside one busy process here the remesh took 91 s).
    record = json.loads((run / "provisional" / "model.json").read_text())
    assert models[0]["fe_model"], record["fe_model"]
    # the stress: made, or why not said on the page's record (seen in one of two runs: CalculiX refused
    # a provisional section's mesh, "nonpositive jacobian", where the final sections solved; such a
    # section is now left out and named, tasks.section_model.each_solved)
    assert models[0]["stress"] or record["stress"]["why"], record["stress"]
    # what the provisional verdict said is what the final one says
    provisional = json.loads((run / "provisional" / "weld_verdict.json").read_text())["weld"]
    final = json.loads((run / "results" / "report.json").read_text())["weld"]
    assert provisional["summary"]["verdict"] == final["verdict"] == verdict[0]["verdict"], (provisional["summary"],
                                                                                             final["verdict"])
    # measured (bench/README.md, 2026-11-28): height 1.960 / 1.968 mm, groove depth 0.407 / 0.407 mm,
    # flank angle 22.18 / 22.37 deg
    for name, bound in (("reinforcement_height_mm", 0.05), ("groove_depth_mm", 0.05), ("flank_angle_deg", 1.0)):
        assert abs(provisional["statistics"][name]["median"] - final["statistics"][name]["median"]) < bound, name
    # the final files: the same bytes as the run on the finished sample's, stage by stage and
    # published (the page differs: its audit section is each folder's own trail)
    finished = read_trail(done)
    for name, entry in _whole_sample_stages(finished).items():
        assert _outputs(stages[name]) == _outputs(entry), name
    published = [e for e in trail if e["kind"] == "run-finished"][-1]["artefacts"]
    published_done = [e for e in finished if e["kind"] == "run-finished"][-1]["artefacts"]
    assert set(published) == set(published_done)
    assert {k: v for k, v in published.items() if not k.endswith(".html")} == \
           {k: v for k, v in published_done.items() if not k.endswith(".html")}
    assert not any("provisional" in p.name or b"PROVISIONAL" in p.read_bytes() for p in (run / "results").iterdir()
                   if p.suffix in (".html", ".json"))
