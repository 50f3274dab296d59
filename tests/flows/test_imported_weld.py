"""Imported scans of a weld (``weldrecon import-scans --joint ... --weld-line | --weld-auto``)
reconstructed and measured by the flow as a simulator sample is (stage weld): two overlapping
views of a butt weld's cap, each in its own frame with its pose (a .conf), the real scans' noise,
spikes and dropouts (``simulator.weld_profiles``), toe radius 1 mm at 45 deg drawn; two
overlapping halves of a T-joint's drawn fillet corner (the plates' sides found on the data, no
specimen given); and the weld options' bad input, one line each with nothing written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flows.cli import main
from schemas.manifest import SampleManifest
from simulator.weld_profiles import REAL_SCAN_NOISE, butt_weld_views
from tests.flows.cli import weldrecon
from tests.flows.test_import_scans_cli import _conf
from tests.flows.test_measure_fillet_cli import ALONG, ROOT, TRUTH, tjoint_corner, write_ply

RADIUS_MM, ANGLE_DEG, LENGTH_MM = 1.0, 45.0, 12.0


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """(the two views' files and their .conf, the toes' half width): the weld's centre line is
    x = 0 on the plate's face z = 0 of the world frame, along y from 0 to LENGTH_MM."""
    folder = tmp_path_factory.mktemp("weld-scans")
    views, half = butt_weld_views(toe_radius_mm=RADIUS_MM, toe_angle_deg=ANGLE_DEG, spacing_mm=0.05,
                                  profile_pitch_mm=0.25, length_mm=LENGTH_MM, noise=REAL_SCAN_NOISE,
                                  rng=np.random.default_rng(7))
    files = []
    for k, view in enumerate(views):
        files.append(folder / f"view{k}.ply")
        write_ply(files[-1], view.points_mm)
    _conf(folder / "poses.conf", {f.name: v.T_world_scan for f, v in zip(files, views)}, unit_mm=1.0)
    return [str(f) for f in files], str(folder / "poses.conf"), half


def test_a_weld_found_at_import_is_measured_by_the_reconstruction(scans, tmp_path):
    files, conf, half = scans
    sample = tmp_path / "sample"
    done = weldrecon("import-scans", str(sample), *files, "--units", "mm", "--poses", conf, "--joint", "butt",
                     "--weld-auto")
    assert done.returncode == 0, done.stderr
    manifest = SampleManifest.model_validate_json((sample / "manifest.json").read_text())
    (line,) = manifest.weld_lines()
    start, end = np.array(line.points_mm)
    # found on the scans: the cap's middle at the plates' level, along the weld (the world frame)
    assert abs(start[0]) < 0.1 and abs(end[0]) < 0.1 and abs(start[2]) < 0.02 and abs(end[2]) < 0.02
    assert abs(abs(end[1] - start[1]) - LENGTH_MM) < 0.5
    assert manifest.weld.joint == "double-sided butt" and manifest.specimen is None
    assert manifest.setups[0].T_world_specimen_nominal is not None  # the scans' frame states the lines' place
    assert "found on the scans at import" in done.stdout

    run = tmp_path / "run"
    done = weldrecon("reconstruct", str(sample), "--out", str(run), "--stop-after", "weld")
    assert done.returncode == 0, done.stderr
    (document,) = (run / "stages" / "weld").glob("*/weld_geometry.json")
    weld = json.loads(document.read_text())
    assert weld["measured"] and weld["frame"].startswith("the scans'")
    sections = weld["sections"]
    assert len(sections) >= LENGTH_MM - 6 and all(s["toes"]["minus"] and s["toes"]["plus"] for s in sections)
    radii = [s["toes"][side]["toe_radius_mm"]["value"] for s in sections for side in ("minus", "plus")]
    angles = [s["toes"][side]["flank_angle_deg"]["value"] for s in sections for side in ("minus", "plus")]
    # measured at 0.05 mm spacing, 0.25 mm between profiles, through the merge's 0.1 mm cells (9
    # sections: radius median 1.008, 0.94-1.07; angle median 45.13, 44.8-46.2; at 0.2 mm over 30 mm,
    # 26 sections: 1.017, 0.89-1.10; 45.10, 44.8-46.6): the issue's +-0.05 mm and +-1 deg on the
    # median; a section within 0.2 mm and 2.5 deg (its sigmas 0.02-0.03 mm and 0.4-0.6 deg, times 4-8)
    assert abs(np.median(radii) - RADIUS_MM) <= 0.05 and abs(np.median(angles) - ANGLE_DEG) <= 1.0
    assert max(abs(r - RADIUS_MM) for r in radii) <= 0.2 and max(abs(a - ANGLE_DEG) for a in angles) <= 2.5
    # the toes where they are drawn, either side of the weld's centre found on the data
    width = [s["toes"]["plus"]["position_u_mm"] - s["toes"]["minus"]["position_u_mm"] for s in sections]
    assert abs(np.median(width) - 2 * half) < 0.05
    assert abs(np.median([s["reinforcement_height_mm"]["value"] for s in sections]) - 3.0) < 0.02


def test_a_weld_line_given_by_hand_is_found_on_the_data(scans, tmp_path):
    """A line 0.6 mm off the weld's centre and turned a little is written as given; the
    reconstruction would refine it on the data (its tolerance says how far it may be off)."""
    files, conf, _ = scans
    sample = tmp_path / "sample"
    done = weldrecon("import-scans", str(sample), *files, "--units", "mm", "--poses", conf, "--joint", "butt",
                     "--weld-line", "0.6,1,0:0.4,11,0", "--treatment", "hfmi")
    assert done.returncode == 0, done.stderr
    manifest = SampleManifest.model_validate_json((sample / "manifest.json").read_text())
    assert manifest.weld.weld_lines[0].points_mm == [(0.6, 1.0, 0.0), (0.4, 11.0, 0.0)]
    assert manifest.weld.treatment == "hfmi-treated" and manifest.setups[0].placement_tolerance_mm == 2.0


def test_an_imported_fillet_weld_is_measured_with_its_plates_found_on_the_data(tmp_path):
    """The drawn corner of ``test_measure_fillet_cli`` (legs 7.0 / 6.0 mm, toe radii 1.0 / 0.6 mm,
    10 um of noise, profiles 0.5 mm apart, turned into the file's frame) in two halves overlapping
    by 6 mm, each in a frame of its own: its root found at import, the sample reconstructed up to
    the weld, every section with both toes, the figures within the bounds that command's test holds
    the same corner to (0.1 mm, 4 deg: the per-section errors of tests/tasks/test_fillet_section.py)."""
    world = tjoint_corner()
    s = (world - ROOT) @ ALONG
    folder = tmp_path / "scans"
    folder.mkdir()
    files, poses = [], {}
    for k, half in enumerate((world[s < 3.0], world[s >= -3.0])):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("zx", [30.0 + 40.0 * k, 10.0], degrees=True).as_matrix()
        T[:3, 3] = [20.0 * k, -30.0, 5.0]
        files.append(folder / f"half{k}.ply")
        write_ply(files[-1], (half - T[:3, 3]) @ T[:3, :3])
        poses[files[-1].name] = T
    _conf(folder / "poses.conf", poses, unit_mm=1.0)
    sample = tmp_path / "sample"
    done = weldrecon("import-scans", str(sample), *map(str, files), "--units", "mm", "--poses",
                     str(folder / "poses.conf"), "--joint", "fillet", "--weld-auto")
    assert done.returncode == 0, done.stderr
    (line,) = SampleManifest.model_validate_json((sample / "manifest.json").read_text()).weld_lines()
    for end in np.array(line.points_mm):  # the root found where the plates cross, on the drawn root line
        rel = end - ROOT
        assert np.linalg.norm(rel - (rel @ ALONG) * ALONG) < 0.05
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--stop-after", "weld")
    assert done.returncode == 0, done.stderr
    (document,) = (tmp_path / "run" / "stages" / "weld").glob("*/weld_geometry.json")
    weld = json.loads(document.read_text())
    assert weld["measured"] and weld["joint"] == "fillet", weld.get("why_not")
    sections = weld["sections"]
    assert len(sections) >= 30 and all(x["toes"]["base"] and x["toes"]["stem"] for x in sections)

    def median(get):
        return float(np.median([get(x) for x in sections]))

    assert abs(median(lambda x: x["leg_base_mm"]["value"]) - TRUTH.leg_base_mm) < 0.1
    assert abs(median(lambda x: x["leg_stem_mm"]["value"]) - TRUTH.leg_stem_mm) < 0.1
    assert abs(median(lambda x: x["toes"]["base"]["toe_radius_mm"]["value"]) - 1.0) < 0.1
    assert abs(median(lambda x: x["toes"]["stem"]["toe_radius_mm"]["value"]) - 0.6) < 0.1
    assert abs(median(lambda x: x["throat_mm"]["value"]) - TRUTH.throat_mm) < 0.1


@pytest.fixture
def flat(tmp_path):
    x, y = np.meshgrid(np.arange(0.0, 30.0, 0.2), np.arange(0.0, 20.0, 0.2))
    write_ply(tmp_path / "flat.ply", np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]))
    return str(tmp_path / "flat.ply")


@pytest.mark.parametrize("case", ["no joint", "no line", "line outside", "bad line", "no weld", "auto fillet"])
def test_bad_weld_options_are_one_line_and_nothing_is_written(case, scans, flat, tmp_path, capsys):
    files, conf, _ = scans
    posed = [*files, "--units", "mm", "--poses", conf]
    args, expected = {
        "no joint": ([*posed, "--weld-auto"], "--weld-line and --weld-auto describe a weld: give its --joint"),
        "no line": ([*posed, "--joint", "butt"], "--joint butt: where is the weld? give --weld-line"),
        "line outside": ([*posed, "--joint", "butt", "--weld-line", "200,0,0:200,10,0"],
                         "--weld-line 200,0,0:200,10,0: the weld line 200,0,0:200,10,0 lies outside the scan"),
        "bad line": ([*posed, "--joint", "butt", "--weld-line", "0,0:1,1"], "--weld-line must be X0,Y0,Z0:X1,Y1,Z1"),
        "no weld": ([flat, "--units", "mm", "--joint", "butt", "--weld-auto"], "--weld-auto: no weld in the scan"),
        "auto fillet": ([flat, "--units", "mm", "--joint", "fillet", "--weld-auto"], "--weld-auto: no stem"),
    }[case]
    out = tmp_path / "out" / "sample"
    assert main(["import-scans", str(out), *args]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"weldrecon import-scans: error: {expected}"), lines
    assert not out.exists()


def test_a_scans_sample_may_give_its_weld_alone_not_a_specimen_alone():
    base = {"schema_version": "1.1", "units": "mm", "sample_id": "s", "created": "2026-11-24T00:00:00+00:00",
            "registration": "surfaces", "setups": [{"name": "scans", "T_world_specimen_nominal": np.eye(4).tolist(),
                                                    "passes": [{"kind": "scan", "pass_id": "a", "file": "passes/a.zarr",
                                                                "n_points": 3, "has_pose": True,
                                                                "view_direction": [0, 0, 1]}]}]}
    weld = {"joint": "double-sided butt", "weld_lines": [{"name": "weld", "points_mm": [[0, 0, 0], [0, 10, 0]]}]}
    assert SampleManifest.model_validate({**base, "weld": weld}).weld_lines()[0].points_mm[1] == (0, 10, 0)
    plate = {"kind": "plate", "length_mm": 100, "width_mm": 50, "thickness_mm": 10}
    with pytest.raises(ValueError, match="a specimen without its weld"):
        SampleManifest.model_validate({**base, "specimen": plate})
