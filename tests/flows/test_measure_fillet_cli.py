"""``weldrecon measure-weld --joint fillet``: a T-joint's corner drawn by the simulator
(simulator.tjoint: legs, a convex face, each toe rounded), swept along the weld, turned and moved
into a file's frame and written as a PLY; its root line found on the data (or given), its
figures against the drawn ones; a flat plate (no stem) refused in one line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation

from schemas.profile_weld import ScanWeld
from schemas.simulation import TJointConfig
from simulator.tjoint import constant_fillet, fillet_profile, fillet_truth
from tests.flows.cli import weldrecon

TJ = TJointConfig()
FILLET = constant_fillet(leg_base=7.0, leg_stem=6.0, convexity=0.8, toe_radius_base=1.0, toe_radius_stem=0.6)
TRUTH = fillet_truth(TJ, FILLET, 0.0, "x")
# the file's frame: the section's a (out along the base) -> x, the weld -> y, b (up the stem) -> z,
# turned 8 deg about x then 25 deg about z, the root moved to (100, 50, 10)
R_FILE = Rotation.from_euler("xz", [8, 25], degrees=True).as_matrix()
ROOT = np.array([100.0, 50.0, 10.0])
ALONG, OUT, UP = R_FILE @ [0.0, 1.0, 0.0], R_FILE @ [1.0, 0.0, 0.0], R_FILE @ [0.0, 0.0, 1.0]


def write_ply(path: Path, points: np.ndarray) -> Path:
    vertex = np.zeros(len(points), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    vertex["x"], vertex["y"], vertex["z"] = np.asarray(points, np.float64).T
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))
    return path


def tjoint_corner(*, stem: bool = True, noise_mm: float = 0.01, seed: int = 1, fillet=FILLET) -> np.ndarray:
    """The drawn fillet's section (0.05 mm apart, 30 mm of each plate from the root) every 0.5 mm
    along 40 mm of weld, 10 um of noise, in the file's frame; ``stem`` False: the base plate alone."""
    ab = fillet_profile(TJ, fillet, 0.0, 0.05)
    ab = ab[(ab[:, 0] <= 30.0) & (ab[:, 1] <= 30.0)]
    if not stem:
        ab = np.stack([np.arange(-30.0, 30.0, 0.05), np.zeros(1200)], 1)
    ys = np.arange(-20.0, 20.0 + 1e-9, 0.5)
    points = np.concatenate([np.stack([ab[:, 0], np.full(len(ab), y), ab[:, 1]], 1) for y in ys])
    points = points @ R_FILE.T + ROOT
    return points + np.random.default_rng(seed).normal(0.0, noise_mm, points.shape)


def _angle_deg(u, v) -> float:
    return math.degrees(math.acos(min(abs(float(np.dot(u, v))), 1.0)))


def _check_figures(doc: ScanWeld) -> None:
    g = doc.geometry
    # judged by the catalog's fillet rule: the drawn weld (legs 7 and 6 mm, convexity 0.8 mm, toes
    # at 45-60 deg) is within every limit
    assert g.joint == "fillet" and g.acceptance is not None and g.acceptance.joint == "fillet"
    assert g.summary.passed is True and g.summary.verdict == "pass" and not g.failing
    # 40 mm of weld, 2 mm end margins, a section at each whole mm along the line: 36 or 37 (the
    # noise moves the scan's ends by hundredths), every toe measured
    assert g.summary.sections in (36, 37) and all(t.measured for t in doc.toes)
    assert len(doc.toes) == 2 * g.summary.sections
    # the plates' sides found from where the points lie, within 0.1 deg of the drawn ones
    assert _angle_deg(doc.weld_line.across, OUT) < 0.1 and np.dot(doc.weld_line.across, OUT) > 0
    assert _angle_deg(doc.weld_line.face_normal, UP) < 0.1 and np.dot(doc.weld_line.face_normal, UP) > 0
    sections = g.sections
    assert all(abs(s.plates_angle_deg - 90.0) < 0.2 for s in sections)
    for s in sections:  # each section's root on the drawn root line, within 0.05 mm
        rel = np.subtract(s.centre_specimen_mm, ROOT)
        assert np.linalg.norm(rel - (rel @ ALONG) * ALONG) < 0.05

    def median(get):
        return float(np.median([get(s) for s in sections]))

    # bounds: tests/tasks/test_fillet_section.py's per-section errors at this noise (medians over 24
    # drawn fillets: radius 0.034, throat 0.038, convexity 0.027 mm, face angle 2.6 deg; a leg under
    # a 1 mm rounding within 0.1 mm); the median of 36 sections of one fillet is within them
    # (measured: legs 7.028 / 6.031, throat 4.577 (drawn 4.556), convexity 0.788, radii 1.032 /
    # 0.598 mm, angles 61.4 / 69.3 deg against the face's 60.2 / 70.1)
    assert abs(median(lambda s: s.leg_base_mm.value) - TRUTH.leg_base_mm) < 0.1
    assert abs(median(lambda s: s.leg_stem_mm.value) - TRUTH.leg_stem_mm) < 0.1
    assert abs(median(lambda s: s.throat_mm.value) - TRUTH.throat_mm) < 0.1
    assert abs(median(lambda s: s.convexity_mm.value) - TRUTH.convexity_mm) < 0.06
    for k, side in enumerate(("base", "stem")):
        assert abs(median(lambda s: getattr(s.toes, side).toe_radius_mm.value) - TRUTH.toe_radius_mm[k]) < 0.1
        assert abs(median(lambda s: getattr(s.toes, side).flank_angle_deg.value) - TRUTH.face_angle_deg[k]) < 4.0
        sigmas = [getattr(s.toes, side).toe_radius_mm.sigma for s in sections]  # each with its 1-sigma
        assert None not in sigmas and np.median(sigmas) > 0.005


def test_a_drawn_fillet_found_and_measured(tmp_path):
    scan = write_ply(tmp_path / "tee.ply", tjoint_corner())
    done = weldrecon("measure-weld", str(scan), "--joint", "fillet", "--out", str(tmp_path / "out"))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    doc = ScanWeld.model_validate_json((tmp_path / "out" / "tee.ply.weld.json").read_text())
    assert doc.weld_line.found == "auto" and doc.config.fillet is not None  # the settings used, written
    # the root line found where the plates cross: on the drawn one, along it
    for end in (doc.weld_line.start_mm, doc.weld_line.end_mm):
        rel = np.subtract(end, ROOT)
        assert np.linalg.norm(rel - (rel @ ALONG) * ALONG) < 0.05
    assert _angle_deg(np.subtract(doc.weld_line.end_mm, doc.weld_line.start_mm), ALONG) < 0.1
    _check_figures(doc)
    n = doc.geometry.summary.sections
    assert done.stdout.splitlines()[0].startswith(f"{scan}: {n} sections, {2 * n} of {2 * n} toes measured")


def test_a_drawn_fillet_along_a_given_root_line(tmp_path):
    scan = write_ply(tmp_path / "tee.ply", tjoint_corner(seed=2))
    a, b = ROOT - 25.0 * ALONG, ROOT + 25.0 * ALONG  # past the scan's ends: the sections run where the points are
    line = ":".join(",".join(f"{v:.4f}" for v in p) for p in (a, b))
    done = weldrecon("measure-weld", str(scan), "--joint", "fillet", "--weld-line", line, "--out", str(tmp_path))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    doc = ScanWeld.model_validate_json((tmp_path / "tee.ply.weld.json").read_text())
    assert doc.weld_line.found == "given"
    _check_figures(doc)


def test_a_fillet_past_its_limits_fails_with_a_line_per_finding(tmp_path):
    # 2 mm of convexity on legs of 7 and 6 mm: the face meets the stem at 92 deg (drawn), past the
    # catalog's 80 deg (ISO 5817 level C: toe angle >= 100 deg); measured 79-82, the base's 78-79 (drawn 81: the face past the rounding, tests/tasks/test_fillet_section.py);
    # the convexity itself within 1 mm + 0.15 b (b ~9.5 mm between the toes: 2.4 mm)
    bulging = constant_fillet(leg_base=7.0, leg_stem=6.0, convexity=2.0, toe_radius_base=1.0, toe_radius_stem=0.6)
    scan = write_ply(tmp_path / "tee.ply", tjoint_corner(fillet=bulging))
    done = weldrecon("measure-weld", str(scan), "--joint", "fillet", "--out", str(tmp_path))
    assert done.returncode == 1, done.stderr
    doc = ScanWeld.model_validate_json((tmp_path / "tee.ply.weld.json").read_text())
    g = doc.geometry
    assert g.summary.verdict == "fail" and g.summary.failing == g.summary.sections
    stem = [f for f in g.failing if (f.figure, f.toe) == ("flank_angle_deg", "stem")]
    # all but one: the fit's flank is bounded at 85 deg, short of the drawn 92, so every stem fit
    # misses the points (RMS 0.21 mm against the 0.01 mm noise) and at one section (32 mm) it takes
    # a false 1.1 mm undercut instead, which fails that section (noted in issue 27: a toe the model
    # cannot hold should say so)
    assert len(stem) >= g.summary.sections - 1 and all(f.limit == "<= 80" and f.value > 80 for f in stem)
    assert not any(f.figure == "convexity_mm" for f in g.failing + g.uncertain)
    lines = (done.stdout + done.stderr).splitlines()
    for f in g.failing:  # each finding one line: where, which toe, the figure, its value and limit
        assert sum(f"at {f.position_mm:.2f} mm, {f.toe} toe: {f.figure} {f.value}" in line and f"fails ({f.limit})" in line
                   for line in lines) == 1, f


@pytest.mark.parametrize("case, says", [
    ("flat", "no stem: "),
    ("across", "runs 90 deg off the corner where the scan's two plates meet"),
])
def test_a_fillet_scan_without_a_corner_or_a_line_across_it_is_one_line(tmp_path, case, says):
    scan = write_ply(tmp_path / "bad.ply", tjoint_corner(stem=case != "flat"))
    line = ["--weld-line", ":".join(",".join(f"{v:.4f}" for v in p) for p in (ROOT, ROOT + 10 * OUT))] \
        if case == "across" else []
    done = weldrecon("measure-weld", str(scan), "--joint", "fillet", *line, "--out", str(tmp_path))
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert done.stderr.startswith(f"weldrecon measure-weld: error: {scan}: ") and says in done.stderr, done.stderr
    assert not (tmp_path / "bad.ply.weld.json").exists()


def test_a_step_or_slab_out_of_bounds_is_one_line(tmp_path):
    scan = write_ply(tmp_path / "tee.ply", tjoint_corner())
    (tmp_path / "wide.yaml").write_text("section_half_width_mm: 20\n")  # a butt weld's slab may be 50 mm, a fillet's 10
    for args, says in ((["--step-mm", "150"], "--step-mm 150: Input should be less than or equal to 100"),
                       (["--config", str(tmp_path / "wide.yaml")],
                        "a fillet weld's section_half_width_mm: Input should be less than or equal to 10 (the step "
                        "and slab half width given for it)")):
        done = weldrecon("measure-weld", str(scan), "--joint", "fillet", *args, "--out", str(tmp_path))
        assert done.returncode == 2 and done.stderr.splitlines() == [f"weldrecon measure-weld: error: {says}"], done.stderr
