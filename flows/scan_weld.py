"""A scan's weld measured and written as its document (``schemas.profile_weld.ScanWeld``): the
file read (``data_catalog.pointclouds``), the weld line given or found, the sections measured
(``tasks.scan_weld``), judged (``tasks.weld_acceptance``, the catalog's rule for the joint and
treatment) and put in the pipeline's weld document (``flows.stages.weld``'s own conversion), with
the problems as one line each for the terminal."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from data_catalog.acceptance import load_acceptance_limits
from data_catalog.pointclouds import read_point_cloud
from flows.stages.weld import judged, section_document, section_statistics
from schemas.profile_weld import MeasureWeldConfig, ScanSource, ScanToe, ScanWeld, ScanWeldLine
from schemas.weld_document import WeldGeometry, WeldLineFound
from tasks.profile_weld import ProfileSettings
from tasks.scan_weld import find_weld_line, given_weld_line, measure_scan

__all__ = ["scan_weld_document", "profile_settings"]


def profile_settings(config: MeasureWeldConfig) -> ProfileSettings:
    """The task's settings from the command's config."""
    return ProfileSettings(**{k: getattr(config, k) for k in ProfileSettings.__dataclass_fields__})


def scan_weld_document(path: str | Path, *, units: str, line, joint: str, treatment: str,
                       config: MeasureWeldConfig) -> tuple[ScanWeld, list[str]]:
    """The weld in the scan at ``path`` (``line``: two points, mm, or None: found on the data) and
    its problems, one line each (a toe not measured, a failing or uncertain figure). ValueError,
    naming the file: no weld, a line outside the scan, a scan too small (its unit), a side with
    no plate in any section."""
    cloud = read_point_cloud(path, units=units)
    points = cloud.points_mm
    name = Path(path).name
    try:
        found = (given_weld_line(points, *line) if line is not None
                 else find_weld_line(points, min_rise_mm=config.min_rise_mm))
        scan = measure_scan(points, found, settings=profile_settings(config), treated=treatment != "as-welded",
                            step_mm=config.step_mm, half_width_mm=config.section_half_width_mm, name="weld")
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    sections = [r.section for r in scan.sections]
    rule = load_acceptance_limits(None).rule_for(joint, treatment)
    verdict, summary, failing, uncertain = judged(sections, rule)
    length = float(np.linalg.norm(np.subtract(found.end_mm, found.start_mm)))
    geometry = WeldGeometry(
        measured=True, joint=joint, treatment=treatment, frame=f"the scan's own ({name})", acceptance=rule,
        acceptance_source="data_catalog/weld_acceptance.yaml",
        lines=[WeldLineFound(name="weld", sections=len(sections), offset_mm=0.0, turn_deg=0.0,
                             face_normal=tuple(round(v, 5) for v in found.normal),
                             across=tuple(round(v, 5) for v in found.across), measured_extent_mm=(0.0, round(length, 3)))],
        summary=summary, statistics=section_statistics(sections), failing=failing, uncertain=uncertain,
        sections=[section_document(sec, None if verdict is None else verdict.sections[k]) for k, sec in enumerate(sections)])
    toes, problems = [], []
    for r in scan.sections:
        where = f"{name} at {r.section.position_mm:.2f} mm"
        for side, toe in zip(("minus", "plus"), r.toes):
            toes.append(ScanToe(position_mm=round(r.section.position_mm, 3), side=side, measured=toe.fit is not None,
                                toe_radius_below_mm=toe.radius_below_mm, reason=toe.reason or None))
            if toe.fit is None:
                problems.append(f"{where}, {side} toe: not measured: {toe.reason}")
    for f in failing + uncertain:
        kind = "fails" if f in failing else "uncertain"
        sd = "" if f.sigma is None else f" ± {f.sigma:g}"
        problems.append(f"{name} at {f.position_mm:.2f} mm{', ' + f.toe + ' toe' if f.toe else ''}: {f.figure} "
                        f"{f.value}{sd} {kind} ({f.limit})")
    spacing = [r.spacing_mm for r in scan.sections if math.isfinite(r.spacing_mm)]
    source = ScanSource(file=str(path), points=len(points), profile_scan=scan.profile_scan,
                        profile_pitch_mm=None if scan.profile_pitch_mm is None else round(scan.profile_pitch_mm, 4),
                        point_spacing_mm=round(float(np.median(spacing)), 4) if spacing else None,
                        spikes_dropped=sum(r.spikes for r in scan.sections))
    weld_line = ScanWeldLine(start_mm=tuple(round(v, 4) for v in found.start_mm),
                             end_mm=tuple(round(v, 4) for v in found.end_mm),
                             face_normal=tuple(round(v, 6) for v in found.normal),
                             across=tuple(round(v, 6) for v in found.across), found=found.found)
    return ScanWeld(source=source, config=config, weld_line=weld_line, geometry=geometry, toes=toes), problems
