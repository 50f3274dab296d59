"""The manifest describes any welded part: the specimen kinds and their weld lines, schema 1.0
read as it was, bad parts refused with the field named, and the merge's weld zone round the
lines whatever the kind."""

from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from data_catalog.manifests import ManifestError, check_sample_files, load_manifest
from flows.stages.views import weld_lines_view as merge_view
from flows.stages.placement import sample_weld_zone


T_JOINT = {"kind": "t-joint", "base_length_mm": 300, "base_width_mm": 120, "base_thickness_mm": 12,
           "stem_height_mm": 100, "stem_thickness_mm": 10}
# each kind, a joint it takes, and lines where its welds are (specimen frame, mm)
PARTS = {
    "dog-bone": ({"kind": "dog-bone", "length_mm": 240, "grip_width_mm": 60, "gauge_width_mm": 44,
                  "gauge_length_mm": 60, "transition_radius_mm": 40, "thickness_mm": 20},
                 "single-V butt", [[[0, -30, 10], [0, 30, 10]]]),
    "plate": ({"kind": "plate", "length_mm": 400, "width_mm": 200, "thickness_mm": 15},
              "double-V butt", [[[0, -100, 7.5], [0, 100, 7.5]], [[0, -100, -7.5], [0, 100, -7.5]]]),
    "t-joint": (T_JOINT, "double fillet", [[[-5, -60, 6], [-5, 60, 6]], [[5, -60, 6], [5, 60, 6]]]),
    "cruciform": ({**T_JOINT, "kind": "cruciform"}, "cruciform fillet",
                  [[[s * 5, -60, z], [s * 5, 60, z]] for s in (-1, 1) for z in (6, -6)]),
    "drawing": ({"kind": "drawing", "file": "drawing/part.stl", "units": "m", "sha256": "0" * 64,
                 "bounds": [[-150, -60, -6], [150, 60, 106]]},
                "other", [[[-5, -60, 6], [-5, 0, 6], [-40, 60, 6]]]),
}


def _as_1_0(raw: dict) -> dict:
    """A dog-bone manifest as weldrecon wrote it before 1.1 (the same part, the weld at x = 0)."""
    out = copy.deepcopy(raw)
    out["schema_version"] = "1.0"
    out["weld"] = {"process": out["weld"]["process"], "joint": "double-sided butt", "centre_x_mm": 0.0,
                   "treatment": out["weld"]["treatment"]}
    return out


def _as_part(raw: dict, specimen: dict, joint: str, lines: list) -> dict:
    """``raw`` as a 1.1 manifest of ``specimen``, its ``joint`` along ``lines`` ((k, 3) lists)."""
    out = copy.deepcopy(raw)
    out["schema_version"] = "1.1"
    out["specimen"] = copy.deepcopy(specimen)
    out["weld"] = {"process": "GMAW", "joint": joint, "treatment": "as-welded",
                   "weld_lines": [{"name": f"line-{k}", "points_mm": points} for k, points in enumerate(lines)]}
    return out


def _load(folder: Path, raw: dict):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(json.dumps(raw))
    return load_manifest(folder)


def _refused(folder: Path, raw: dict) -> str:
    with pytest.raises(ManifestError) as info:
        _load(folder, raw)
    return str(info.value)


@pytest.fixture(scope="module")
def ci(ci_sample) -> dict:
    """The ci sample's manifest, as the simulator writes it (1.1, a dog-bone, two weld lines)."""
    return json.loads((ci_sample / "manifest.json").read_text())


@pytest.mark.parametrize("kind", list(PARTS))
def test_each_kind_validates_from_a_minimal_example(tmp_path, ci, kind):
    specimen, joint, lines = PARTS[kind]
    manifest = _load(tmp_path, _as_part(ci, specimen, joint, lines))
    assert manifest.specimen.kind == kind and manifest.weld.joint == joint
    assert [[list(p) for p in line.points_mm] for line in manifest.weld_lines()] == lines
    lo, hi = manifest.specimen.bounds_mm()
    assert all(a < b for a, b in zip(lo, hi))


def test_the_simulator_writes_1_1_and_a_1_0_manifest_loads_with_the_same_lines_and_zone(tmp_path, ci):
    """A 1.0 manifest (every sample written before 1.1) loads unchanged; its weld's lines, derived
    from centre_x_mm, are the ones the simulator now writes: the merge reads the same view (the
    same cache key) and puts the same zones in the common frame."""
    assert ci["schema_version"] == "1.1" and "centre_x_mm" not in ci["weld"]
    new = _load(tmp_path / "new", ci)
    old = _load(tmp_path / "old", _as_1_0(ci))
    assert old.schema_version == "1.0" and old.weld.centre_x_mm == 0.0
    assert old.weld_lines() == new.weld_lines()
    assert [[list(p) for p in line.points_mm] for line in old.weld_lines()] == [
        [[0.0, -30.0, 10.0], [0.0, 30.0, 10.0]], [[0.0, -30.0, -10.0], [0.0, 30.0, -10.0]]]
    assert merge_view(old) == merge_view(new)
    T = np.tile(np.eye(4), (len(new.passes()), 1, 1))
    T[:, :3, 3] = [12.5, -3.0, 0.25]
    assert sample_weld_zone(old, T, 15.0, widened=True) == sample_weld_zone(new, T, 15.0, widened=True)
    assert len(sample_weld_zone(new, T, 15.0, widened=True).zones) == 2  # the weld frame's two lines
    # and it stays 1.0 when written back: a loaded manifest is what the file says
    assert json.loads(old.model_dump_json())["weld"] == _as_1_0(ci)["weld"]


@pytest.mark.parametrize(
    ("edit", "where", "message"),
    [
        (lambda m: m["specimen"].update(kind="box"), "specimen",
         "kind 'box' is not a specimen kind weldrecon knows; expected one of dog-bone, plate, t-joint, cruciform, "
         "drawing"),
        (lambda m: m["weld"].update(joint="fillet"), "(top level)",
         "weld.joint 'fillet' does not fit specimen.kind 'dog-bone'; expected one of double-sided butt, "
         "single-V butt, double-V butt, other"),
        (lambda m: m["weld"]["weld_lines"][0].update(points_mm=[[0.0, 0.0, 10.0]]), "weld.weld_lines.0.points_mm",
         "at least 2 items"),
        (lambda m: m["weld"]["weld_lines"][1].update(points_mm=[[0.0, -30.0, -10.0], [0.0, -30.0, -10.0]]),
         "weld.weld_lines.1.points_mm", "points 0 and 1 are the same point"),
        (lambda m: m["weld"]["weld_lines"][1]["points_mm"][1].__setitem__(0, 300.0), "(top level)",
         "weld.weld_lines.1 (bottom): point 1 [300.0, 30.0, -10.0] lies 180.0 mm outside the dog-bone's bounding "
         "box [-120.0, -30.0, -10.0] .. [120.0, 30.0, 10.0] mm"),
        (lambda m: m["weld"].update(weld_lines=[]), "weld.weld_lines", "at least 1 item"),
        (lambda m: m.update(schema_version="2.0"), "schema_version", "Input should be '1.0' or '1.1'"),
        (lambda m: m["weld"].update(centre_x_mm=5.0), "weld.centre_x_mm", "Extra inputs are not permitted"),
        (lambda m: m["setups"][0]["passes"][0].update(direction=""), "setups.0.passes.0.direction",
         "at least 1 character"),
        (lambda m: m["setups"][0]["passes"][0].update(direction="x" * 65), "setups.0.passes.0.direction",
         "at most 64 characters"),
        (lambda m: m.update(specimen={**T_JOINT, "stem_x_mm": 148.0}), "specimen",
         "the stem (stem_x_mm 148, stem_thickness_mm 10) overhangs the base plate (base_length_mm 300)"),
        (lambda m: m.update(specimen={**PARTS["drawing"][0], "file": "part.step"}), "specimen.file",
         "drawing file 'part.step': expected a mesh file, .stl or .ply"),
    ],
)
def test_a_bad_part_is_refused_naming_the_field(tmp_path, ci, edit, where, message):
    raw = copy.deepcopy(ci)
    edit(raw)
    text = _refused(tmp_path, raw)
    assert f"  {where}:" in text and message in text, text


def test_a_1_0_manifest_is_a_dog_bone_with_its_centre_line(tmp_path, ci):
    old = _as_1_0(ci)
    old["specimen"] = PARTS["plate"][0]
    assert "specimen.kind 'plate': schema_version 1.0 describes dog-bones only" in _refused(tmp_path, old)
    old = _as_1_0(ci)
    old["weld"]["joint"] = "fillet"
    assert "  weld.joint: Input should be 'double-sided butt'" in _refused(tmp_path, old)
    old = _as_1_0(ci)
    old["weld"]["weld_lines"] = []
    assert "  weld.weld_lines: Extra inputs are not permitted" in _refused(tmp_path, old)


def test_pass_directions_are_free_labels(tmp_path, ci):
    raw = copy.deepcopy(ci)
    labels = ["along-weld", "across-weld", "rolled 45"]
    for label, entry in zip(labels, raw["setups"][0]["passes"]):
        entry["direction"] = label
    assert [e.direction for _, e in _load(tmp_path, raw).passes()][:3] == labels


def test_a_drawing_is_checked_with_the_sample_files(tmp_path, ci):
    """The drawing a manifest names must be in the sample folder, its own file (no link), with
    the sha256 the manifest states."""
    specimen, joint, lines = PARTS["drawing"]
    stl = b"solid part\nendsolid part\n"
    raw = _as_part(ci, {**specimen, "sha256": hashlib.sha256(stl).hexdigest()}, joint, lines)
    sample = tmp_path / "sample"
    manifest = _load(sample, raw)
    with pytest.raises(ManifestError, match=r"specimen.file drawing/part.stl: .*part.stl does not exist; expected "
                                            r"the part's drawing \(STL or PLY\)"):
        check_sample_files(sample, manifest)
    (sample / "drawing").mkdir()
    (sample / "drawing" / "part.stl").write_bytes(stl + b"\n")
    with pytest.raises(ManifestError, match="has sha256 .*, the manifest states specimen.sha256"):
        check_sample_files(sample, manifest)
    (sample / "drawing" / "part.stl").write_bytes(stl)
    check_sample_files(sample, manifest)
    (tmp_path / "elsewhere.stl").write_bytes(stl)
    (sample / "drawing" / "part.stl").unlink()
    (sample / "drawing" / "part.stl").symlink_to(tmp_path / "elsewhere.stl")
    with pytest.raises(ManifestError, match="is a symbolic link; expected the part.s drawing"):
        check_sample_files(sample, manifest)
