"""A part of another kind through the whole flow: the six-pass ci subset declared as a
butt-welded plate (tests/schemas/test_manifest_parts.py checks the parts' manifests themselves)."""

from __future__ import annotations

import json

from tests.flows.samples import QUICK_CONFIG, as_published


def test_a_plate_reconstructs_with_the_dog_bones_weld_zone(six_sample, six_run, tmp_path):
    """The six-pass ci subset declared as a butt-welded plate (the dog-bone's length, grip width
    and thickness; the same weld lines) reconstructs, and its weld zone is the dog-bone run's:
    the merge reads the weld lines, never the kind (measured: 55,786 of 241,679 merged points in
    the weld zone, both)."""
    from flows.reconstruct import reconstruct_sample
    from tests.flows.samples import copy_sample

    raw = json.loads((six_sample / "manifest.json").read_text())
    dog = raw["specimen"]
    plate = {"kind": "plate", "length_mm": dog["length_mm"], "width_mm": dog["grip_width_mm"],
             "thickness_mm": dog["thickness_mm"]}
    sample = copy_sample(six_sample, tmp_path / "plate")
    (sample / "manifest.json").write_text(json.dumps({**raw, "specimen": plate}))
    # the quick settings, as the dog-bone run's: the stages that read the part's kind are made again
    # for it; what is compared is the merge (the same key as the dog-bone run's)
    report = as_published(reconstruct_sample(str(sample), str(tmp_path / "run"), QUICK_CONFIG, started_by="pytest"))
    dog_merge, plate_merge = six_run[1]["stages"]["merge"], report["stages"]["merge"]
    assert plate_merge["weld_zone_points_out"] > 0
    assert plate_merge["weld_zone_points_out"] == dog_merge["weld_zone_points_out"]
    assert plate_merge["weld_zones"] == dog_merge["weld_zones"]
    assert report["stage_keys"]["merge"] == six_run[1]["stage_keys"]["merge"]
