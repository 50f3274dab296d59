"""The batch index: one self-contained HTML page over every sample in a workspace's catalog
(``WORKSPACE/index.html``): each sample's state, its verdicts, a picture of its mesh and a link to
its QA report (``runs/<id>/results/report.html``, relative, so the workspace can be copied or
served as a folder), and a chart of the samples' registration residuals and weld verdicts.

Rewritten after every batch (``flows.batch``) and by ``weldrecon catalog index``.
"""

from __future__ import annotations

import base64
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog.atomic import atomic_write_text
from data_catalog.catalog import Catalog, SampleRecord
from flows.stages.outputs import REPORT
from flows.stages.qa_report import TEMPLATES
from tasks.report_figures import sample_chart

__all__ = ["write_index", "INDEX_NAME"]

INDEX_NAME = "index.html"
_MESH_PICTURE = re.compile(r'<img src="(data:image/png;base64,[A-Za-z0-9+/=]+)" alt="mesh from above">')


def _summary(record: SampleRecord, root: Path) -> dict[str, Any]:
    row: dict[str, Any] = {"sample_id": record.sample_id, "state": record.state, "stage": record.failed_stage,
                           "error": record.error, "updated": record.updated, "changed": record.state == "done" and record.due,
                           "link": None, "thumbnail": None, "checks": None, "weld": None, "fe": None,
                           "residual_um": None}
    if not record.out_dir:
        return row
    results = Path(record.out_dir) / "results"
    html_path, json_path = results / "report.html", results / "report.json"
    if html_path.is_file():
        row["link"] = Path(os.path.relpath(html_path, root)).as_posix()
        found = _MESH_PICTURE.search(html_path.read_text(encoding="utf-8", errors="replace"))
        row["thumbnail"] = found.group(1) if found else None
    if json_path.is_file():
        try:
            report = REPORT.read_path(json_path)
        except (OSError, ValueError):
            return row
        checks = report.checks
        flagged = sum(c.result != "ok" for c in checks)
        row["checks"] = {"ok": len(checks) - flagged, "total": len(checks)}
        weld = report.weld
        row["weld"] = ({"verdict": weld.verdict, "sections": weld.sections, "failing": weld.failing or 0}
                       if weld.measured else {"verdict": "not measured", "sections": 0, "failing": 0})
        volume = report.volume_mesh
        row["fe"] = volume.solid.tetrahedra if volume.made else None
        refine = report.stages.get("refine", {})
        value = refine.get("target_residual_median_mm") if isinstance(refine, dict) else None
        row["residual_um"] = None if value is None else round(value * 1000, 1)
    return row


def write_index(workspace: Path) -> Path:
    """Write ``workspace/index.html`` from the catalog and each sample's published results."""
    workspace = Path(workspace).resolve()
    records = Catalog(workspace).list()
    rows = [_summary(r, workspace) for r in records]
    chart = None
    measured = [r for r in rows if r["residual_um"] is not None]
    if measured:
        png = sample_chart([r["sample_id"] for r in measured], np.array([r["residual_um"] for r in measured], float),
                           [(r["weld"] or {}).get("verdict", "") for r in measured])
        chart = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    counts = {state: sum(r["state"] == state for r in rows) for state in dict.fromkeys(r["state"] for r in rows)}
    page = TEMPLATES.get_template("qa_index.html.j2").render(workspace=str(workspace), rows=rows, chart=chart, counts=counts)
    path = workspace / INDEX_NAME
    atomic_write_text(path, page)
    return path
