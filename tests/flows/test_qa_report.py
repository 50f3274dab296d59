"""The QA report (stage ``qa_report``) of the ci sample: opened offline in a real browser
(Debian's chromium, headless, through Playwright) with every picture loaded and a clean console;
the same bytes when drawn again; the audit section filled in when published, and a publication of
an altered page refused; the Prefect flow run linked to it."""

from __future__ import annotations

import dataclasses
import shutil
import uuid
from pathlib import Path

import pytest

from data_catalog.audit import read_trail
from data_catalog.manifests import load_manifest
from data_catalog.stages import StageStore
from flows.preflight import load_config
from flows.stages import run_in_process
from flows.stages.outputs import QA_REPORT
from flows.stages.qa_audit import AUDIT_MARK, fill_audit, strip_audit
from flows.stages.report import publish

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = REPO / "deploy" / "configs" / "ci.yaml"
CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed "
                                                         "(deploy/install-system-deps.sh installs it)")


def _open_in_chromium(page: Path, screenshot: Path) -> dict:
    """The page loaded from disk in headless chromium: its pictures (alt, loaded, width), console
    messages, page errors, every URL it requested, its text; a full-page screenshot saved."""
    from playwright.sync_api import sync_playwright

    found: dict = {"console": [], "errors": [], "requests": []}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            tab = browser.new_page(viewport={"width": 1280, "height": 900})
            tab.on("console", lambda m: found["console"].append((m.type, m.text)))
            tab.on("pageerror", lambda e: found["errors"].append(str(e)))
            tab.on("request", lambda r: found["requests"].append(r.url))
            tab.goto(page.as_uri(), wait_until="load")
            found["images"] = tab.evaluate(
                "Array.from(document.images).map(i => [i.alt, i.complete && i.naturalWidth > 0, i.naturalWidth])")
            found["text"] = tab.inner_text("body")
            tab.screenshot(path=str(screenshot), full_page=True)
        finally:
            browser.close()
    return found


def test_the_report_opens_offline_in_chromium_with_every_picture_loaded(ci_run, tmp_path):
    out, report = ci_run
    page = out / "results" / "report.html"
    shot = tmp_path / "report.png"
    found = _open_in_chromium(page, shot)
    assert found["errors"] == [] and [m for m in found["console"] if m[0] in ("error", "warning")] == []
    # one self-contained file: nothing fetched but the page itself and its inline pictures
    assert [u for u in found["requests"] if not u.startswith("data:") and u != page.as_uri()] == []
    images = found["images"]
    assert images and all(loaded and width > 100 for _, loaded, width in images), \
        [alt for alt, loaded, _ in images if not loaded]
    alts = [alt for alt, _, _ in images]
    for expected in ("scan plan and coverage", "disagreement of overlapping passes", "registration graph",
                     "mesh from above", "mesh from below", "mesh weld zone", "FE model element quality",
                     "stress concentration along the toes", "stress map of the hot spot's section"):
        assert expected in alts
    assert sum(a.startswith("pass ") and a.endswith(" intensity") for a in alts) == len(report["passes"])
    lines = {line["name"] for line in report["weld"]["lines"]}
    assert sum(a.startswith("weld section ") for a in alts) == 4 * len(lines)  # sections_per_line, every line
    assert sum(a.startswith("toe close-up ") for a in alts) == 4 * len(lines)  # each drawn section's toes, close
    assert "weld figures along the weld" in alts
    text = found["text"]
    assert f"QA report: {report['sample_id']}" in text and "Audit trail intact" in text
    hot = report["stress"]["hot_spot"]
    assert f"{hot['line']} weld, {hot['side']} toe, {hot['position_mm']} mm along it: stress concentration " \
           f"{hot['factor']:.2f}" in text
    assert f"{len(report['checks'])} of {len(report['checks'])} ok" in text
    from PIL import Image

    with Image.open(shot) as im:  # the whole page was drawn: every section, not a blank tab
        assert im.width == 1280 and im.height > 4000
        assert len(set(im.convert("L").resize((64, 256)).getdata())) > 50


def test_the_report_is_the_same_bytes_when_drawn_again(ci_run, ci_sample, tmp_path, monkeypatch):
    """Drawn again in this process, each picture at once (the run drew them on worker processes)."""
    from flows.stages import qa_report

    assert qa_report.PICTURE_WORKERS >= 1
    monkeypatch.setattr(qa_report, "PICTURE_WORKERS", 0)
    out, _ = ci_run
    stored = next((out / "stages" / "qa_report").glob(f"*/{QA_REPORT.name}"))
    again = tmp_path / "run"
    shutil.copytree(out / "stages", again / "stages", ignore=lambda d, names: ["qa_report"] if d.endswith("stages") else [])
    refs = run_in_process(store=StageStore(again, shared=False), sample_dir=ci_sample, manifest=load_manifest(ci_sample),
                          config=load_config(CI_CONFIG))
    assert not refs["qa_report"].cached and all(refs[n].cached for n in ("refine", "weld", "mesh", "volume", "stress",
                                                                          "report"))
    assert refs["qa_report"].file(QA_REPORT.name).read_bytes() == stored.read_bytes()
    # the published page is the stage's, its audit section filled in and nothing else changed
    drawn = stored.read_text()
    published = (out / "results" / QA_REPORT.name).read_text()
    before, after = drawn.split(AUDIT_MARK)
    assert AUDIT_MARK not in published and published.startswith(before) and published.endswith(after)
    assert strip_audit(published) == drawn


def test_a_page_altered_in_the_store_is_not_published(ci_run, tmp_path):
    out, report = ci_run
    refs = report["refs"]
    copy = tmp_path / "qa_report"
    shutil.copytree(refs["qa_report"].path, copy)
    (copy / QA_REPORT.name).write_text((copy / QA_REPORT.name).read_text().replace("Verdicts", "Verdict!"))
    altered = {**refs, "qa_report": dataclasses.replace(refs["qa_report"], path=str(copy))}
    target = tmp_path / "out"
    target.mkdir()
    with pytest.raises(OSError, match=r"report\.html changed while it was published"):
        publish(target, report["sample_id"], refs["report"], altered, "{}\n")
    assert list(target.iterdir()) == []  # nothing half published


def test_fill_audit_needs_the_marked_place():
    with pytest.raises(ValueError, match="no place for the audit status"):
        fill_audit("<html></html>", {"intact": True, "entries": 1, "head_seq": 0, "head_hash": "ab", "problems": []})
    shown = fill_audit(f"<p>{AUDIT_MARK}</p>", {"intact": False, "entries": 3, "head_seq": 2, "head_hash": "ab",
                                                  "problems": ["trail line 2: <edited>"]})
    assert "NOT intact: 1 problem(s)" in shown and "&lt;edited&gt;" in shown and AUDIT_MARK not in shown


def test_the_flow_run_links_its_report_in_prefect(ci_run):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId

    out, report = ci_run
    # the session run's own start (the shared run folder may hold later runs: another test's rerun)
    started = [e for e in read_trail(out) if e["kind"] == "run-started" and e["seq"] <= report["trail_head"]["seq"]][-1]
    with get_client(sync_client=True) as client:
        artifacts = client.read_artifacts(artifact_filter=ArtifactFilter(
            flow_run_id=ArtifactFilterFlowRunId(any_=[uuid.UUID(started["flow_run_id"])])))
    key = f"qa-report-{report['sample_id'].lower()}"
    by_key = {a.key: a for a in artifacts}
    assert set(by_key) == {key, f"{key}-summary"}
    # Prefect stores a link artifact as a markdown link
    assert f"({(out / 'results' / 'report.html').resolve().as_uri()})" in str(by_key[key].data)
    summary = str(by_key[f"{key}-summary"].data)
    assert "QA report" in summary and f"{len(report['checks'])} of {len(report['checks'])} ok" in summary



def test_a_thinned_copy_serves_the_steps_that_are_multiples_of_its_own():
    from flows.stages.qa_report import steps_on_copy

    assert steps_on_copy((16, 3), (16, 3)) == (slice(None, None, 1), slice(None, None, 1))
    assert steps_on_copy((32, 6), (16, 3)) == (slice(None, None, 2), slice(None, None, 2))
    assert steps_on_copy((24, 3), (16, 3)) is None and steps_on_copy((8, 3), (16, 3)) is None
    assert steps_on_copy((16, 3), (0, 0)) is None  # an imported scan: no copy


def test_the_maps_get_the_whole_passes_values_from_the_thinned_copies(ci_run, ci_sample):
    """Each pass's thinned copy (stage denoise's preview.zarr) gives the page's maps the values the
    whole pass gives, at the page's cells and at twice and 1.5 times them."""
    import types

    import numpy as np

    from flows.stages.outputs import PREVIEW
    from flows.stages.qa_report import _thinned

    _, report = ci_run
    manifest = load_manifest(ci_sample / "manifest.json")
    config = load_config(CI_CONFIG)
    entries = [e for _, e in manifest.passes()]
    for cell_mm in (config.qa_report.cell_mm, 2 * config.qa_report.cell_mm, 1.5 * config.qa_report.cell_mm):
        ctx = types.SimpleNamespace(settings=config.qa_report.model_copy(update={"cell_mm": cell_mm}), manifest=manifest)
        for ref, entry in zip(report["refs"]["denoise"], entries):
            whole = dataclasses.replace(ref, outputs={k: v for k, v in ref.outputs.items() if k != PREVIEW.name})
            read, expected = _thinned(ctx, ref, entry), _thinned(ctx, whole, entry)
            assert len(read[0]) > 0 and all(np.array_equal(a, b, equal_nan=True) for a, b in zip(read, expected))
    assert [int(s) for s in PREVIEW.read(report["refs"]["denoise"][0]).steps] == [2, 2]  # 0.32 mm points, 2 mm cells
