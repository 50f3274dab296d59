"""``weldrecon import`` and ``weldrecon export-cell`` as a user runs them: a summary line, bad
input refused in one line on stderr with nothing written, and a simulated sample that goes
out as cell logs and back in reconstructs like the original."""

from __future__ import annotations

from pathlib import Path

import pytest

from data_catalog.audit import read_trail
from flows.stages.outputs import STL
from schemas.provenance import StageRecord
from tests.conftest import SIX
from tests.data_catalog.test_cell_logs import BAD, EXAMPLE, _example_copy
from tests.flows.cli import run_cli, weldrecon

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")


def test_import_prints_one_summary_line(tmp_path):
    out = tmp_path / "sample"
    done = run_cli("import", str(EXAMPLE / "CELL.yaml"), str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"{out}: 2 passes, 9 profiles, 72 points\n"
    assert (out / "manifest.json").is_file()


@pytest.mark.parametrize("case", ["profile times not increasing", "a .gz that is not gzip",
                                  "unknown rotation convention", "poses do not cover the profiles"])
def test_bad_input_is_one_line_on_stderr_and_nothing_is_written(case, tmp_path):
    spoil, expected = BAD[case]
    cell = _example_copy(tmp_path)
    spoil(cell)
    out = tmp_path / "out" / "sample"
    done = weldrecon("import", str(cell / "CELL.yaml"), str(out))
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"weldrecon import: error: {expected.format(cell=cell)}"), done.stderr
    assert not out.exists() and not (out.parent.exists() and list(out.parent.iterdir()))


def test_an_existing_out_sample_is_refused_on_the_command_line(tmp_path):
    out = tmp_path / "sample"
    out.mkdir()
    done = weldrecon("import", str(EXAMPLE / "CELL.yaml"), str(out))
    assert done.returncode == 2
    assert done.stderr == f"weldrecon import: error: {out} already exists; choose a new folder (nothing was written)\n"
    assert list(out.iterdir()) == []


def test_export_cell_refuses_a_z_grid_of_a_scanner_without_one(six_sample, tmp_path):
    done = weldrecon("export-cell", str(six_sample), str(tmp_path / "logs"), "--layout", "z_grid")
    assert done.returncode == 2
    assert done.stderr.startswith("weldrecon export-cell: error: pass top-L02: profile 0, point 1: X is ")
    assert "the z_grid layout holds scanners that report on a fixed X grid: use layout xzi" in done.stderr
    assert len(done.stderr.splitlines()) == 1 and not (tmp_path / "logs").exists()


def test_a_sample_exported_and_imported_reconstructs(six_sample, tmp_path):
    logs, sample, run = tmp_path / "logs", tmp_path / "imported", tmp_path / "run"
    done = weldrecon("export-cell", str(six_sample), str(logs), "--gzip", "--orientation", "fanuc-wpr",
                   "--pose-every", "3", "--time-offset", "12.5", "--no-return", "empty")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"{logs}: 6 passes, ")
    done = weldrecon("import", str(logs / "CELL.yaml"), str(sample))
    assert done.returncode == 0, done.stderr
    # up to the exported surface mesh (the FE model and the pages after it read only the mesh)
    done = weldrecon("reconstruct", str(sample), "--config", CI_CONFIG, "--out", str(run), "--stop-after", "export")
    assert done.returncode == 0, done.stderr
    trail = read_trail(run)
    assert sorted(e["item"] for e in trail if e["kind"] == "stage" and e["stage"] == "denoise") == sorted(SIX)
    (mesh,) = (run / "stages" / "mesh").glob("*/record.json")
    assert StageRecord.model_validate_json(mesh.read_text()).metrics["watertight"]
    (stl,) = (run / "stages" / "export").glob(f"*/{STL.name}")
    assert stl.stat().st_size > 10_000
