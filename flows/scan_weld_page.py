"""``<scan>.weld.html``: the QA page of a weld measured by ``weldrecon measure-weld``, one
self-contained HTML file (pictures inline, no script, no link out): the summary and verdict, a few
representative sections (the measured points, the fitted toes, each toe close up) and every
figure along the weld with its 1-sigma as error bars, drawn by the pipeline's own QA page's
helpers (``flows.stages.qa_report``: ``section_pictures``, ``along_weld_pictures``) from the weld
document and the points it was measured on. Same document and points, same bytes."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

from flows.scan_weld import MeasuredScan
from flows.stages.qa_report import TEMPLATES, along_weld_pictures, section_pictures

__all__ = ["scan_weld_page", "SECTIONS_SHOWN"]

SECTIONS_SHOWN = 4  # sections drawn per weld line


def scan_weld_page(measured: MeasuredScan) -> str:
    """The page of ``measured`` (module description)."""
    doc = measured.document
    g = doc.geometry
    pictures = section_pictures(g, measured.points_mm, per_line=SECTIONS_SHOWN,
                                half_width_mm=measured.section_half_width_mm, reach_mm=measured.reach_mm)
    try:
        version = importlib.metadata.version("weldrecon")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return TEMPLATES.get_template("scan_weld.html.j2").render(
        name=Path(doc.source.file).name, version=version, doc=doc, g=g, pictures=pictures,
        along=along_weld_pictures(g, error_bars=True), statistics=sorted(g.statistics.items()),
        measured=sum(t.measured for t in doc.toes), below=sum(t.toe_radius_below_mm is not None for t in doc.toes),
        problems=measured.problems)
