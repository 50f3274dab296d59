"""``<scan>.weld.html``, the QA page beside each ``<scan>.weld.json`` of ``weldrecon measure-weld``:
opened offline in a real browser (Debian's chromium, headless, through Playwright, as the
pipeline's QA page is tested) with every picture loaded, nothing fetched, a clean console; the
representative sections, their toes close up and the figures along the weld shown; the same
bytes when measured again."""

from __future__ import annotations

import shutil

import pytest

from schemas.profile_weld import ScanWeld
from tests.flows.cli import weldrecon
from tests.flows.test_measure_fillet_cli import tjoint_corner, write_ply
from tests.flows.test_measure_weld_cli import _write_scan
from tests.flows.test_qa_report import _open_in_chromium

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed "
                                                         "(deploy/install-system-deps.sh installs it)")


def _check_page(page, tmp_path, *, sections: int) -> dict:
    found = _open_in_chromium(page, tmp_path / "page.png")
    assert found["errors"] == [] and [m for m in found["console"] if m[0] in ("error", "warning")] == []
    assert [u for u in found["requests"] if not u.startswith("data:") and u != page.as_uri()] == []
    images = found["images"]
    assert images and all(loaded and width > 300 for _, loaded, width in images), images
    alts = [alt for alt, _, _ in images]
    assert sum(a.startswith("weld section weld ") for a in alts) == sections
    assert sum(a.startswith("toe close-up weld ") for a in alts) == sections  # each drawn section's toes, close
    assert "weld figures along the weld" in alts
    return found


def test_a_fillet_welds_page_shows_its_sections_and_figures(tmp_path):
    scan = write_ply(tmp_path / "tee.ply", tjoint_corner())
    done = weldrecon("measure-weld", str(scan), "--joint", "fillet", "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    page = tmp_path / "out" / "tee.ply.weld.html"
    found = _check_page(page, tmp_path, sections=4)
    text = found["text"]
    doc = ScanWeld.model_validate_json((tmp_path / "out" / "tee.ply.weld.json").read_text())
    assert "Weld: tee.ply" in text and doc.geometry.summary.verdict in text
    # the table of each figure along the weld: toe radius and angle over both toes, the legs
    for figure in ("toe_radius_mm\t74\t", "flank_angle_deg\t74\t", "leg_base_mm\t37\t", "throat_mm\t37\t"):
        assert figure.replace("37", str(doc.geometry.summary.sections)).replace(
            "74", str(2 * doc.geometry.summary.sections)) in text
    # each drawn section's caption: its legs, throat and both toes' radius and angle
    assert text.count("within the limits. legs ") == 4 and text.count("; base: r ") == 4 and text.count("; stem: r ") == 4
    assert "None: every toe measured" in text
    # the same scan measured again: the same page, byte for byte
    assert weldrecon("measure-weld", str(scan), "--joint", "fillet", "--out", str(tmp_path / "again")).returncode == 0
    assert (tmp_path / "again" / "tee.ply.weld.html").read_bytes() == page.read_bytes()


def test_a_failing_butt_welds_page_shows_the_failing_sections(tmp_path):
    scan = _write_scan(tmp_path / "high.xyz", height_mm=5.0)
    done = weldrecon("measure-weld", str(scan), "--out", str(tmp_path))
    assert done.returncode == 1, done.stderr
    found = _check_page(tmp_path / "high.xyz.weld.html", tmp_path, sections=4)
    text = found["text"]
    assert "fail: 20 failing section(s)" in text and text.count("FAILS: reinforcement_height_mm ") == 4
    assert "20 problem(s)" in text
