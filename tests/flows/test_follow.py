"""Streaming: ``weldrecon simulate --pace`` writes the plan first and each pass when the robot
would have finished it; ``weldrecon reconstruct --follow`` starts each pass's stages as soon as it
lands, so the robot and the reconstruction overlap, and ends with the same mesh as a run on the
finished sample.

The overlap is shown causally, not by a stopwatch: the test plays the robot and holds the last
pass back until the run has denoised an earlier one. A run that waited for the whole sample would
never get there (and fail on the test's deadline)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from data_catalog.audit import read_trail
from data_catalog.hashing import sha256_tree
from data_catalog.manifests import MANIFEST_NAME, load_manifest
from tests.flows.cli import REPO, cli_env, weldrecon
from tests.flows.samples import QUICK_CONFIG

CI_CONFIG = REPO / "deploy" / "configs" / "ci.yaml"


def _digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _land(source: Path, passes: Path) -> None:
    """A pass lands as a cell writes it: complete under a hidden name, then renamed into place."""
    hidden = passes / f".{source.name}.partial"
    shutil.copytree(source, hidden)
    os.rename(hidden, passes / source.name)


def _trail(out: Path) -> list[dict]:
    try:
        return read_trail(out)
    except FileNotFoundError:
        return []


def _denoised(out: Path) -> list[str]:
    return [e["item"] for e in _trail(out) if e.get("kind") == "stage" and e.get("stage") == "denoise"]


def _provisional(out: Path) -> list[dict]:
    return [e for e in _trail(out) if e.get("kind") == "provisional-published"]


@pytest.mark.slow
def test_follow_works_on_passes_while_the_last_is_still_being_scanned(six_sample, six_run, tmp_path):
    """... and publishes a provisional weld verdict while the last pass is still missing (the
    test holds it back until one is published), marked as such and never among the results."""
    _, finished = six_run
    sample, out = tmp_path / "live", tmp_path / "run"
    (sample / "passes").mkdir(parents=True)
    shutil.copy2(six_sample / MANIFEST_NAME, sample / MANIFEST_NAME)
    stores = sorted((six_sample / "passes").iterdir())
    with open(tmp_path / "follow.err", "w") as err:
        follow = subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(sample), "--out", str(out),
                                   "--follow", "--follow-timeout", "600", "--config", QUICK_CONFIG],
                                  cwd=REPO, env=cli_env(), stdout=subprocess.DEVNULL, stderr=err)
        try:
            for store in stores[:-1]:
                _land(store, sample / "passes")
            deadline = time.monotonic() + 600
            while not (_denoised(out) and _provisional(out)):  # the robot is still scanning the last pass
                assert follow.poll() is None, (tmp_path / "follow.err").read_text()[-3000:]
                assert time.monotonic() < deadline, ("no pass was denoised and no provisional verdict published while "
                                                     "the last one was missing")
                time.sleep(0.5)
            assert not (sample / "passes" / stores[-1].name).exists()
            early, early_verdicts = _denoised(out), _provisional(out)
            _land(stores[-1], sample / "passes")
            assert follow.wait(timeout=600) == 0, (tmp_path / "follow.err").read_text()[-3000:]
        finally:
            if follow.poll() is None:
                follow.kill()
    assert early and stores[-1].stem not in early
    assert len(_denoised(out)) == len(stores)
    # the provisional verdicts: made from the passes landed, said on the terminal, superseded in the
    # trail before the run's results are recorded, never in results/
    assert early_verdicts and all(2 <= e["passes"] < len(stores) and e["of_passes"] == len(stores) for e in early_verdicts)
    trail = _trail(out)
    kinds = [e["kind"] for e in trail]
    verdicts = [e for e in trail if e["kind"] == "provisional-published"]
    superseded = trail[kinds.index("provisional-superseded")]
    assert superseded["provisional"] == [e["seq"] for e in verdicts]
    assert kinds.index("provisional-superseded") < kinds.index("run-finished")
    document = json.loads((out / "provisional" / "weld_verdict.json").read_text())
    assert document["provisional"] is True and document["after_pass"] == verdicts[-1]["after_pass"]
    assert document["weld"]["measured"] and document["weld"]["summary"]["verdict"] == verdicts[-1]["verdict"]
    assert verdicts[-1]["artefacts"] == {"provisional/weld_verdict.json": _digest(out / "provisional" / "weld_verdict.json")}
    assert not any("provisional" in p.name for p in (out / "results").iterdir())
    err = (tmp_path / "follow.err").read_text()
    assert f"PROVISIONAL weld verdict after pass {early_verdicts[0]['after_pass']}" in err, err[-3000:]
    # after the last pass's verdict, the provisional mesh (two octree levels under stage mesh's):
    # closed, on the final mesh's surface, superseded with the verdicts
    meshes = [e for e in trail if e["kind"] == "provisional-mesh-published"]
    assert len(meshes) == 1 and meshes[0]["passes"] == len(stores) and meshes[0]["watertight"], meshes
    assert superseded["provisional_meshes"] == [meshes[0]["seq"]] and meshes[0]["seq"] > verdicts[-1]["seq"]
    record = json.loads((out / "provisional" / "mesh.json").read_text())
    assert record["provisional"] is True and record["passes"] == len(stores) and record["poisson_depth"] == 6
    assert meshes[0]["artefacts"] == {f"provisional/{name}": _digest(out / "provisional" / name)
                                      for name in ("mesh.ply", "mesh.json")}
    assert f"PROVISIONAL mesh after pass {meshes[0]['after_pass']} (6 of 6 passes)" in err, err[-3000:]
    import open3d as o3d

    final = o3d.t.geometry.RaycastingScene()
    final.add_triangles(o3d.t.io.read_triangle_mesh(str(next((out / "results").glob("*.stl")))))
    vertices = np.asarray(o3d.io.read_triangle_mesh(str(out / "provisional" / "mesh.ply")).vertices, np.float32)
    assert len(vertices) == record["vertices"]
    distance = final.compute_distance(o3d.core.Tensor(vertices)).numpy()
    # measured: median 0.43 mm, 90 % 1.09 mm from the final surface, 1,887 vertices (depth 6, an
    # octree cell of ~2.5 mm, on the part's 0.6 mm cells; the final mesh: depth 8 on 0.3 mm cells)
    assert np.median(distance) < 0.7 and np.percentile(distance, 90) < 1.6, (np.median(distance),
                                                                               np.percentile(distance, 90))
    # then the provisional FE model, stress and QA page: the whole run's stages on the grown poses,
    # the weld's cells and the provisional mesh, marked PROVISIONAL, superseded with the rest
    models = [e for e in trail if e["kind"] == "provisional-model-published"]
    assert len(models) == 1 and models[0]["seq"] > meshes[0]["seq"] and models[0]["passes"] == len(stores), models
    assert superseded["provisional_models"] == [models[0]["seq"]]
    assert models[0]["fe_model"] and models[0]["stress"], models[0]
    model = json.loads((out / "provisional" / "model.json").read_text())
    assert model["provisional"] is True and model["fe_model"]["made"] and model["stress"]["made"], model
    assert models[0]["artefacts"] == {f"provisional/{name}": _digest(out / "provisional" / name)
                                      for name in [*model["files"], "model.json"]}
    assert {f"{finished['sample_id']}{end}" for end in (".stl", ".inp", "_stress.vtu")} <= set(model["files"])
    page = (out / "provisional" / "report.html").read_text()
    assert page.count("PROVISIONAL") >= 2 and "<title>PROVISIONAL weldrecon QA report" in page
    assert "<!-- weldrecon: audit status -->" not in page and "Audit trail intact" in page, page[-2000:]
    assert "PROVISIONAL" not in (out / "results" / "report.html").read_text()
    assert f"PROVISIONAL QA page after pass {models[0]['after_pass']} (6 of 6 passes)" in err, err[-3000:]
    # each toe line's hot spot factor near the final one's (the final: refined poses, the depth-8
    # mesh, the segmented points); where along a toe it peaks may differ where two sections nearly
    # tie (the paper preset: 75 against 23 mm on one toe, factors 1.4-2.6 % apart, bench/README.md)
    provisional_report = json.loads((out / model["stages"]["report"] / "report.json").read_text())
    final_hot = {(h["line"], h["side"]): h["factor"]
                 for h in json.loads((out / "results" / "report.json").read_text())["stress"]["hot_spots"]}
    hot = {(h["line"], h["side"]): h["factor"] for h in provisional_report["stress"]["hot_spots"]}
    assert set(hot) == set(final_hot) and len(hot) >= 2, (hot, final_hot)
    assert all(abs(hot[toe] / final_hot[toe] - 1) < 0.1 for toe in hot), (hot, final_hot)
    # while it waits, what the plan reaches and what each next pass adds (tasks.pass_coverage,
    # checked against the simulated passes in tests/tasks/test_pass_coverage.py): top-L02 sees the
    # top line at 10-50 mm, top-L04 at 8-23 (new: 8-9)
    ids = [entry.pass_id for _, entry in load_manifest(sample).passes()]  # the order the passes are taken in
    assert "the plan reaches weld line top (60 mm) at 8-52 mm with 3 of 6 passes" in err, err[:3000]
    assert f"next: pass {ids[0]} (1 of 6) adds line top 10-50 mm (new: 10-50)" in err, err[:3000]
    # the next pass is the first of the plan not in yet: the passes' stages, cached here, may end out
    # of the plan's order on the two threads (then the first pass is still the next one, with less new)
    first_in = min((ids[0], ids[1]), key=lambda p: re.search(rf"denoise \d/6 {p} ", err).start())
    if first_in == ids[0]:
        assert f"next: pass {ids[1]} (2 of 6) adds line top 8-23 mm (new: 8-9)" in err, err[:3000]
    else:
        assert f"next: pass {ids[0]} (1 of 6) adds line top 10-50 mm (new: 24-50)" in err, err[:3000]
    assert "all 6 passes in: the whole-sample stages follow" in err, err[-3000:]
    # the same mesh as the run on the finished sample
    stl_live = out / "results" / f"{finished['sample_id']}.stl"
    stl_done = Path(finished["outputs"][f"{finished['sample_id']}.stl"]["path"])
    assert _digest(stl_live) == _digest(stl_done)


@pytest.mark.slow
def test_a_paced_scan_shows_the_plan_first_and_lands_the_same_passes_at_the_robots_pace(ci_sample, tmp_path):
    sample = tmp_path / "live"
    seen: dict[str, float] = {}
    scan = subprocess.Popen([sys.executable, "-m", "flows.cli", "simulate", "--preset", "ci", "--no-preview",
                             "--pace", "x40", str(sample)], cwd=REPO, env=cli_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        while scan.poll() is None:  # what a follower sees, in order
            if (sample / MANIFEST_NAME).exists():
                seen.setdefault(MANIFEST_NAME, time.monotonic())
            if (sample / "passes").is_dir():
                for store in (sample / "passes").iterdir():
                    if not store.name.startswith("."):
                        seen.setdefault(store.name, time.monotonic())
            time.sleep(0.05)
        _, scan_err = scan.communicate(timeout=60)
    finally:
        if scan.poll() is None:
            scan.kill()
    assert scan.returncode == 0, scan_err[-2000:]
    assert scan_err.count("passes land at 40 x") == 1
    plan = json.loads((sample / MANIFEST_NAME).read_text())
    entries = [e for setup in plan["setups"] for e in setup["passes"]]
    stores = [Path(e["file"]).name for e in entries]
    assert set(seen) == {MANIFEST_NAME, *stores}
    # the plan first, then each pass in the robot's order, the last no sooner than the robot allows
    order = sorted(seen, key=seen.get)
    assert order[0] == MANIFEST_NAME and order[1:] == stores
    assert seen[stores[-1]] - seen[MANIFEST_NAME] >= 0.9 * sum(e["duration_s"] for e in entries[1:]) / 40
    # the plan has no content hashes (not known until scanned); the passes are those of an unpaced scan
    finished = json.loads((ci_sample / MANIFEST_NAME).read_text())
    expected = {e["pass_id"]: e["content_sha256"] for setup in finished["setups"] for e in setup["passes"]}
    assert all(e["content_sha256"] is None for e in entries)
    assert {e["pass_id"]: sha256_tree(sample / e["file"]) for e in entries} == expected


def test_follow_names_the_pass_that_never_lands(ci_sample, tmp_path):
    sample = tmp_path / "partial"
    shutil.copytree(ci_sample, sample)
    missing = sorted((sample / "passes").iterdir())[-1]
    shutil.rmtree(missing)
    started = time.monotonic()
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--follow", "--follow-timeout", "3",
                   "--config", str(CI_CONFIG))
    assert done.returncode == 2
    assert f"{missing.name} did not appear (complete) within 3 s" in done.stderr, done.stderr[-2000:]
    assert time.monotonic() - started < 300
    # one line for the problem and one naming the log; Prefect's tracebacks go to that log
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    problems = [line for line in done.stderr.splitlines() if "error" in line.lower()]
    assert len(problems) == 1, done.stderr[-3000:]
    logs = list((tmp_path / "run" / "logs").glob("reconstruct-*.log"))
    assert len(logs) == 1 and f"the details and the traceback: {logs[0]}" in done.stderr
    assert "Traceback" in logs[0].read_text()
