"""Valid-looking input that is inconsistent (issue 10, item 5): every file decodes and every hash
matches, yet the poses are not rigid, the robot jumps, the clock runs back or a chunk of a pass is
out of place. The run refuses what cannot be right (naming pass and profile) and flags what may be
wrong (in report.json's checks and on the terminal)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import zarr

from data_catalog.hashing import sha256_tree
from tests.flows.cli import weldrecon
from tests.conftest import SIX
from tests.flows.samples import QUICK_CONFIG, copy_sample

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = REPO / "deploy" / "configs" / "ci.yaml"
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def _doctor(sample: Path, pass_id: str, edit) -> None:
    """Edit one pass's arrays in place, then refresh its manifest hash, as a careful forger would."""
    store = sample / "passes" / f"{pass_id}.zarr"
    edit(zarr.open_group(str(store), mode="r+"))
    manifest = json.loads((sample / "manifest.json").read_text())
    for setup in manifest["setups"]:
        for p in setup["passes"]:
            if p["pass_id"] == pass_id:
                p["content_sha256"] = sha256_tree(store)
    (sample / "manifest.json").write_text(json.dumps(manifest))


def _scale(g):
    T = g["T_world_flange"][...]
    T[:, :3, :3] *= 1.01  # a 1 % scale on every logged pose
    g["T_world_flange"][...] = T


def _shear(g):
    T = g["T_world_flange"][...]
    T[:, :3, :3] = T[:, :3, :3] @ np.array([[1.0, 0.01, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    g["T_world_flange"][...] = T


def _jump(g):
    T = g["T_world_flange"][...]
    T[400:, 1, 3] += 2.0  # from profile 400 on, the log is 2 mm off
    g["T_world_flange"][...] = T


def _time_order(g):
    t = g["timestamp_s"][...]
    t[300], t[301] = t[301], t[300]
    g["timestamp_s"][...] = t


@pytest.mark.parametrize("edit, message", [
    (_scale, r"pass top-L02: profile 0: T_world_flange is not rigid: its rotation part is off orthonormal by 0\.02"),
    (_shear, r"pass top-L02: profile 0: T_world_flange is not rigid"),
    (_jump, r"pass top-L02: profile 400: the logged flange pose jumps 2\.\d+ mm"),
    (_time_order, r"pass top-L02: profile 301: timestamp_s .* is not after the profile before"),
], ids=["scale", "shear", "jump", "time-order"])
def test_poses_and_times_that_cannot_be_right_are_refused_naming_pass_and_profile(ci_sample, tmp_path, edit, message):
    from flows.reconstruct import ReconstructionFailed, reconstruct_sample

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    _doctor(sample, "top-L02", edit)
    with pytest.raises(ReconstructionFailed, match=message):
        reconstruct_sample(str(sample), str(tmp_path / "out"), str(CI_CONFIG))
    assert not (tmp_path / "out" / "results").exists()


def test_the_refusal_is_one_line_on_the_terminal(ci_sample, tmp_path):
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    _doctor(sample, "top-L02", _scale)
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "out"), "--config", str(CI_CONFIG))
    assert done.returncode != 0
    error = done.stderr[done.stderr.index("weldrecon reconstruct: error:"):].splitlines()
    assert error[0] == "weldrecon reconstruct: error: stage denoise failed for 1 pass(es):"
    assert error[1].startswith("  pass top-L02: profile 0: T_world_flange is not rigid")
    assert error[2].startswith("  (the details and the traceback: ") and len(error) == 3
    assert "Traceback" not in done.stderr


def test_a_chunk_out_of_place_is_flagged_in_the_report_and_on_the_terminal(ci_sample, tmp_path):
    """A chunk of top-L02 swapped with another of the same pass (x, z and intensity; times and poses
    as they were), the hash refreshed, in the six-pass subset whose setups share the side walls'
    stickers (the first three passes of each setup share none: registration refuses them): exit 0
    as before, but the report flags the pass (the surface steps at the chunk boundaries) and the
    terminal says so; its target residuals are not what shows it (measured 0.013 mm, the other
    passes 0.015-0.028 mm);
    then a rerun with settings refine cannot use fails clearly and leaves the published results as
    they were."""
    sample = copy_sample(ci_sample, tmp_path / "s", SIX)

    def swap(g):
        c = g["z_mm"].chunks[0]
        for name in ("x_mm", "z_mm", "intensity"):
            a, b = g[name][2 * c:3 * c], g[name][4 * c:5 * c]
            g[name][2 * c:3 * c], g[name][4 * c:5 * c] = b, a

    _doctor(sample, "top-L02", swap)
    out = tmp_path / "out"
    # the ci settings with the weld and the stress read at fewer sections (what is checked here is
    # the chunk; its stages run once more than the session's, on this pass's data)
    done = weldrecon("reconstruct", str(sample), "--out", str(out), "--config", QUICK_CONFIG)
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "results" / "report.json").read_text())
    flagged = {(c["pass"], c["check"]) for c in report["checks"] if c["result"] != "ok"}
    # the chunk is what is flagged; of the rest only the FE model may be (the surface the swapped
    # chunk folds: its elements were outside the limits before gmsh's patches were bounded, within
    # them since). The subset's stress was flagged until the weld stage's face normal was fixed
    # (06d0a63: its sections were cut askew, the membrane stress 2 % off; now 0.3 %)
    assert ("top-L02", "surface continuity at chunk boundaries") in flagged
    assert flagged <= {("top-L02", "surface continuity at chunk boundaries"), ("all", "FE model")}
    # and the surfaces the setups share, the part as declared, the weld, the FE model, the stress
    assert len(report["checks"]) == 3 * 6 + 5
    jumps = next(c for c in report["checks"] if c["pass"] == "top-L02" and c["check"].startswith("surface"))
    assert {j["profile"] for j in jumps["measured"]} <= {256, 384, 512, 640} and jumps["measured"]
    assert f"checks: {23 - len(flagged)} of 23 ok" in done.stdout
    warnings = [line for line in done.stderr.splitlines() if "warning: pass top-L02" in line]
    assert len(warnings) == 1 and "a chunk may be out of place" in warnings[0]

    published = {p.name: p.read_bytes() for p in (out / "results").iterdir()}
    config = tmp_path / "tight.yaml"
    config.write_text(Path(QUICK_CONFIG).read_text() + "refine:\n  neighbour_mm: 0.2\n")
    done = weldrecon("reconstruct", str(sample), "--out", str(out), "--config", str(config))
    assert done.returncode != 0
    assert ("refine: no pass kept a surface point to match: none has 16 points (refine.normal_neighbours) "
            "within 0.2 mm (refine.neighbour_mm)") in done.stderr
    assert "Traceback" not in done.stderr
    assert {p.name: p.read_bytes() for p in (out / "results").iterdir()} == published
    # the settings published with the results are still those they were made with (the failed
    # run's are in its run-started entry), and nothing outside results/ claims otherwise
    settings = json.loads(published["config.json"])
    assert settings == json.loads(published["report.json"])["config"] and settings["refine"]["neighbour_mm"] != 0.2
    assert not (out / "config.json").exists()
