"""The sample manifest: the exported JSON schema is current, and bad manifests are refused with
the field named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from data_catalog.manifests import ManifestError, load_manifest, manifest_json_schema

REPO = Path(__file__).resolve().parents[2]


def test_exported_json_schema_is_current():
    assert (REPO / "schemas" / "manifest.schema.json").read_text() == manifest_json_schema()


@pytest.fixture
def good(ci_sample):
    return json.loads((ci_sample / "manifest.json").read_text())


def _load(tmp_path, raw):
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(raw) if not isinstance(raw, str) else raw)
    return load_manifest(tmp_path)


def test_good_manifest_loads(tmp_path, good):
    manifest = _load(tmp_path, good)
    assert manifest.units == "mm" and len(manifest.passes()) == 14


def test_the_load_reads_as_written_and_a_load_without_its_kind_is_axial(tmp_path, good):
    """Schema 1.1's optional load: none is left out when written back, a load without ``kind`` (every
    manifest written before bending) is axial, a bending load reads and writes back as bending."""
    assert "load" not in json.loads(_load(tmp_path, good).model_dump_json())
    axial = _load(tmp_path, {**good, "load": {"nominal_stress_range_mpa": 80.0}})
    assert axial.load.kind == "axial" and axial.schema_version == "1.1"
    bending = _load(tmp_path, {**good, "load": {"kind": "bending", "nominal_stress_range_mpa": 120.0,
                                                "stress_ratio": 0.1}})
    written = json.loads(bending.model_dump_json())
    assert written["load"] == {"kind": "bending", "nominal_stress_range_mpa": 120.0, "stress_ratio": 0.1}
    assert _load(tmp_path, written) == bending


@pytest.mark.parametrize(
    ("edit", "where", "message"),
    [
        (lambda m: m.update(units="inch"), "units", "Input should be 'mm'"),
        (lambda m: m.pop("schema_version"), "schema_version", "Field required"),
        (lambda m: m.update(colour="red"), "colour", "Extra inputs are not permitted"),
        (lambda m: m["setups"][0]["passes"][0].update(file="../../etc/passwd"), "setups.0.passes.0.file",
         "must not leave the sample folder"),
        (lambda m: m["setups"][0]["passes"][0].update(file="/etc/passwd"), "setups.0.passes.0.file",
         "relative POSIX path"),
        (lambda m: m["setups"][0]["passes"][1]["nominal_motion"]["T_world_flange_start"][0].__setitem__(3, float("nan")),
         "setups.0.passes.1.nominal_motion.T_world_flange_start", "finite"),
        (lambda m: m["setups"][0]["passes"][1]["nominal_motion"]["T_world_flange_start"][0].__setitem__(0, 2.0),
         "setups.0.passes.1.nominal_motion.T_world_flange_start", "orthonormal"),
        (lambda m: m["setups"][0]["passes"][2]["nominal_motion"].update(speed_mm_s=-15), 
         "setups.0.passes.2.nominal_motion.speed_mm_s", "greater than 0"),
        (lambda m: m["setups"][1]["passes"][0].update(pass_id=m["setups"][0]["passes"][0]["pass_id"]),
         "(top level)", "pass ids must be unique"),
        (lambda m: m.update(created="2026-01-05T08:00:00"), "created", "timezone"),
        (lambda m: m["scanner"].update(z_range_mm=[300, 100]), "scanner.z_range_mm", "near < far"),
        (lambda m: m.update(load={"kind": "torsion"}), "load.kind", "'axial' or 'bending'"),
    ],
)
def test_bad_manifest_names_the_field(tmp_path, good, edit, where, message):
    edit(good)
    with pytest.raises(ManifestError) as info:
        _load(tmp_path, good)
    text = str(info.value)
    assert str(tmp_path / "manifest.json") in text
    assert f"  {where}:" in text and message in text, text


def test_not_json_and_missing(tmp_path):
    with pytest.raises(ManifestError, match="not valid JSON"):
        _load(tmp_path, "{nope")
    with pytest.raises(ManifestError, match="no manifest file there"):
        load_manifest(tmp_path / "empty")


def test_a_field_given_twice_a_missing_unit_and_a_shared_file_are_named(tmp_path, good):
    text = json.dumps(good)
    with pytest.raises(ManifestError, match="field 'sample_id' given twice in one object; expected each field once"):
        _load(tmp_path, text.replace('"sample_id": ', '"sample_id": "other", "sample_id": ', 1))
    del good["units"]
    with pytest.raises(ManifestError) as info:
        _load(tmp_path, good)
    assert "  units: Field required" in str(info.value)
    good["units"] = "mm"
    first, second = good["setups"][0]["passes"][:2]
    second["file"] = first["file"]
    with pytest.raises(ManifestError, match=f"passes {first['pass_id']}, {second['pass_id']} all refer to "
                                            f"{first['file']}"):
        _load(tmp_path, good)


def test_a_specimen_in_metres_is_named(tmp_path, good):
    good["specimen"].update(length_mm=0.24, grip_width_mm=0.06, gauge_width_mm=0.04, gauge_length_mm=0.07,
                            transition_radius_mm=0.1, thickness_mm=0.02)
    with pytest.raises(ManifestError) as info:
        _load(tmp_path, good)
    assert ("specimen: Value error, length_mm 0.24, grip_width_mm 0.06, thickness_mm 0.02: under 1 mm, not a part a "
            "scanning cell measures; were the dimensions given in metres? expected millimetres") in str(info.value)
