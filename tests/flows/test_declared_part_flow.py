"""A part declared as another (issue 28: a T-joint declared as a 12 mm dog-bone reconstructed with
every check ok): through the command line, the run finishes, and the report's check "part as
declared" and one warning line on the terminal name the disagreement with both figures; the sample
is left as it was. (tests/tasks/test_declared_part.py: the evidence on parts of known size; the
T-joint declared as a plate through the real command line: bench/adversarial.py, group doors.)"""

from __future__ import annotations

import json

from data_catalog.hashing import sha256_tree
from tests.flows.cli import weldrecon
from tests.flows.samples import QUICK_CONFIG, copy_sample


def test_a_dog_bone_declared_as_a_thinner_plate_is_flagged_with_both_thicknesses(six_sample, six_run, tmp_path):
    sample = copy_sample(six_sample, tmp_path / "s")
    manifest = json.loads((sample / "manifest.json").read_text())
    dog = manifest["specimen"]
    manifest["specimen"] = {"kind": "plate", "length_mm": dog["length_mm"], "width_mm": dog["grip_width_mm"],
                            "thickness_mm": 12.0}  # the ci dog-bone is 20 mm thick
    (sample / "manifest.json").write_text(json.dumps(manifest))
    before = sha256_tree(sample)
    done = weldrecon("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--config", QUICK_CONFIG)
    assert done.returncode == 0, done.stderr
    warnings = [line for line in done.stderr.splitlines() if "part as declared" in line]
    assert len(warnings) == 1
    assert warnings[0].startswith("weldrecon reconstruct: warning: pass all: part as declared: the part measured is 20.")
    assert warnings[0].endswith(" mm thick (between its faces), declared 12 mm thick")
    report = json.loads((tmp_path / "run" / "results" / "report.json").read_text())
    [check] = [c for c in report["checks"] if c["check"] == "part as declared"]
    assert check["result"] == "flagged" and abs(check["measured"]["thickness_mm"] - 20.0) < 0.3
    assert sha256_tree(sample) == before
    # the same sample declared as it is: ok
    [honest] = [c for c in six_run[1]["checks"] if c["check"] == "part as declared"]
    assert honest["result"] == "ok" and honest["what"].endswith("is the part declared")
