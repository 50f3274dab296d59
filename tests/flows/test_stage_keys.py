"""Cache keys cover all the code a stage runs: an edited helper recomputes its stage and the
stages downstream of it, never the others (a real flow on the ``ci`` sample's six-pass subset,
run from an edited copy of the code, up to the mesh's export: the FE model, the report and the QA
page downstream of it are keyed the same way, by ``downstream_of``, and their recomputation after
an upstream change is what every other rerun test sees)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from data_catalog.audit import read_trail, verify_trail
from flows.stages import downstream_of, needed_for
from tests.flows.samples import QUICK_CONFIG

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("schemas", "tasks", "data_catalog", "flows", "simulator")

# a real change of behaviour in a helper the merge stage runs (not its body): every merged cell's
# mean point 1 nm further along y and 2 nm along z, so that the merged cloud and everything made
# from it change a little (the merge is the cheapest stage with per-pass stages, registration and
# refine upstream of it to stay cached; this test once edited the denoise helper, and paid for
# the six passes, refine and merge again)
HELPER_EDIT = ("tasks/merge.py", "            points[m, d] = point_sums[m, d] / c\n",
               "            points[m, d] = point_sums[m, d] / c + 1e-6 * d\n")
LAST = "export"  # the edited run stops after this stage


def _code_copy(root: Path, edit: tuple[str, str, str] | None = None) -> Path:
    for package in PACKAGES:
        shutil.copytree(REPO / package, root / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "deploy", root / "deploy")
    if edit is not None:
        path, old, new = edit
        source = (root / path).read_text()
        if not old:  # append
            (root / path).write_text(source + new)
            return root
        assert source.count(old) == 1, f"{path} no longer holds the line this test edits: {old!r}"
        (root / path).write_text(source.replace(old, new))
    return root


def _run_python(code_root: Path, script: str, **added: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(code_root), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_LOGGING_LEVEL="WARNING", **added)
    done = subprocess.run([sys.executable, "-c", script], cwd=code_root, env=env, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


_VERSIONS = ("import json, flows.stages as s; assert s.__file__.startswith(%r); "
             "print(json.dumps({x.name: s.code_version(x) for x in s.STAGES}))")


def _versions(code_root: Path, **added: str) -> dict[str, str]:
    return json.loads(_run_python(code_root, _VERSIONS % str(code_root), **added))


@pytest.fixture(scope="module")
def base_versions(tmp_path_factory) -> dict[str, str]:
    """The stages' code versions in an unedited copy of the code."""
    return _versions(_code_copy(tmp_path_factory.mktemp("base")))


@pytest.mark.parametrize(("path", "old", "new", "changed"), [
    (*HELPER_EDIT, {"merge"}),
    ("tasks/ingest.py", "    out += T[:, None, :3, 3]", "    out += 1.0 * T[:, None, :3, 3]", {"denoise", "targets"}),
    ("tasks/checks.py", "", "# edited\n", {"denoise", "refine", "merge", "segment", "mesh", "export", "volume",
                                           "qa_report"}),
    ("data_catalog/passes.py", "", "# edited\n", {"denoise", "targets", "registration", "refine", "merge", "segment",
                                                      "weld", "mesh", "export", "volume", "stress", "report",
                                                      "qa_report"}),
    ("tasks/report_figures.py", "", "# edited\n", {"qa_report"}),
    ("tasks/weld_fits.py", "", "# edited\n", {"weld"}),
])
def test_editing_a_module_changes_the_code_version_of_the_stages_that_run_it(base_versions, tmp_path, path, old, new,
                                                                            changed):
    edited = _versions(_code_copy(tmp_path / "edited", (path, old, new)))
    assert {name for name in base_versions if base_versions[name] != edited[name]} == changed


def test_an_edited_helper_recomputes_its_stage_and_downstream_only(six_run, six_sample, tmp_path):
    out, first = six_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    code = _code_copy(tmp_path / "code", HELPER_EDIT)
    script = (f"import json; from flows.reconstruct import reconstruct_sample; "
              f"r = reconstruct_sample({str(six_sample)!r}, {str(run)!r}, {QUICK_CONFIG!r}, started_by='pytest edited', "
              f"stop_after={LAST!r}); "
              f"print(json.dumps({{'cached': r.cached, 'keys': {{n: [x.key for x in v] if isinstance(v, list) else v.key "
              f"for n, v in r.refs.items()}}}}))")
    again = json.loads(_run_python(code, script))
    entries = read_trail(run)
    last = max(i for i, e in enumerate(entries) if e["kind"] == "run-started")
    reused = {(e["stage"], e.get("item")): e["cached"] for e in entries[last:] if e["kind"] == "stage"}
    expected_rerun = {"merge", *downstream_of("merge")}
    for (stage, item), cached in reused.items():
        assert cached == (stage not in expected_rerun), (stage, item, cached)
    ran = {s.name for s in needed_for(LAST)}
    assert {s for s, _ in reused} == ran
    assert {"denoise", "targets", "registration", "refine"} == ran - expected_rerun
    assert {"merge", "segment", "mesh", "export"} == ran & expected_rerun
    for name in ("denoise", "targets", "registration", "refine"):  # per pass, or once
        assert again["keys"][name] == first["stage_keys"][name], name
    for name in ("merge", "segment", "mesh", "export"):
        assert again["keys"][name] != first["stage_keys"][name], name
    assert verify_trail(run) == []


def test_code_versions_read_back_from_the_cache_are_the_ones_computed(tmp_path):
    """The code versions' ingredients (each module's imports, the installed distributions' top-level
    packages) are kept between processes in $WELDRECON_CACHE_DIR: a second process reads them back
    and gets the same versions; damaged cache files are computed again, and a cache that cannot be
    written is done without."""
    def versions(cache: Path) -> dict[str, str]:
        return _versions(REPO, WELDRECON_CACHE_DIR=str(cache))

    cache = tmp_path / "cache"
    computed = versions(cache)
    files = sorted((cache / "code").glob("*.json"))
    assert {f.name.split("-")[0] for f in files} == {"imports", "owners"}
    assert versions(cache) == computed  # read back
    for f in files:
        f.write_text("{damaged", encoding="utf-8")
    assert versions(cache) == computed
    assert all(json.loads(f.read_text(encoding="utf-8")) for f in files)  # written again
    (tmp_path / "a-file").write_text("")
    assert versions(tmp_path / "a-file") == computed  # not a folder: no cache


def test_the_reports_key_holds_its_inputs_figures_not_only_their_files(ci_sample):
    """A segment that kept the same points of a part declared otherwise (issue 28: a 20 mm dog-bone
    declared 12 mm thick) writes the same file with another finding; the report reads the finding,
    so its key must differ (it had been taken from the stage cache with the other run's figures).
    Stages that read only files keep one key; a stage's own time never counts."""
    from data_catalog.manifests import load_manifest
    from flows.stages import STAGES
    from flows.stages.contracts import StageRef
    from flows.stages.runner import _input_hashes

    manifest = load_manifest(ci_sample)
    stage = {s.name: s for s in STAGES}

    def segment(**metrics) -> StageRef:
        return StageRef("segment", None, "k", "/nowhere", {"specimen.zarr": "same"}, False, metrics)

    agrees, differs = segment(declared_part={"agrees": True}, seconds=1.0), segment(declared_part={"agrees": False})
    for name, reads in (("report", True), ("mesh", False)):
        a, b = (_input_hashes(stage[name], ci_sample, manifest, None, {"segment": ref}) for ref in (agrees, differs))
        assert (a != b) is reads, name
    slower = segment(declared_part={"agrees": True}, seconds=9.0)
    assert (_input_hashes(stage["report"], ci_sample, manifest, None, {"segment": agrees})
            == _input_hashes(stage["report"], ci_sample, manifest, None, {"segment": slower}))
