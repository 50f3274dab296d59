"""A scan's weld measured and written as its document (``schemas.profile_weld.ScanWeld``): the
points read (``flows.scan_sources``: a point file, a sample of imported scans or a run folder),
the weld line given or found, the sections measured and put in the pipeline's weld document
(``flows.stages.weld``'s own conversion), with the problems as one line each for the terminal.

- A butt weld (``tasks.scan_weld``): judged (``tasks.weld_acceptance``, the catalog's rule for
  the joint and treatment).
- A fillet weld: its root line given or found where the scan's two plates meet, the plates' sides
  from where the points lie (``tasks.scan_fillet``), the sections measured as stage weld measures
  a T-joint's (``tasks.fillet_section.measure_fillet_line``, the settings ``config.fillet``), and
  judged as in the stage (the catalog's rule for "fillet" and the treatment)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from data_catalog.acceptance import load_acceptance_limits
from flows.scan_sources import ScanPoints, read_scan_points
from flows.stages.weld import fillet_weld_figures, judged, section_document, section_settings, section_statistics
from schemas.profile_weld import MeasureWeldConfig, ScanSource, ScanToe, ScanWeld, ScanWeldLine
from schemas.reconstruction import WeldGeometryConfig
from schemas.weld_document import WeldGeometry, WeldLineFound
from tasks.fillet_section import measure_fillet_line
from tasks.profile_weld import ProfileSettings
from tasks.scan_fillet import find_fillet_root
from tasks.scan_weld import check_scan_scale, find_weld_line, given_weld_line, measure_scan

__all__ = ["MeasuredScan", "measure_scan_weld", "scan_weld_document", "profile_settings", "fillet_settings",
           "FILLET_JOINT"]

FILLET_JOINT = "fillet"  # the acceptance catalog's and the manifest's name


@dataclass(frozen=True)
class MeasuredScan:
    """A scan's weld: its document, its problems (one line each), the points it was measured on
    (``points_mm`` (n, 3), the document's frame) and how thick a slab a drawn section shows."""

    document: ScanWeld
    problems: list[str]
    points_mm: np.ndarray
    section_half_width_mm: float
    reach_mm: float


def profile_settings(config: MeasureWeldConfig) -> ProfileSettings:
    """The task's settings from the command's config."""
    return ProfileSettings(**{k: getattr(config, k) for k in ProfileSettings.__dataclass_fields__})


def fillet_settings(config: MeasureWeldConfig) -> WeldGeometryConfig:
    """The settings a fillet weld is read with: ``config.fillet`` (default the stage's), its step and
    slab half width replaced by the command's where given."""
    fillet = config.fillet if config.fillet is not None else WeldGeometryConfig()
    update = {k: v for k, v in (("section_step_mm", config.step_mm),
                                ("section_half_width_mm", config.section_half_width_mm)) if v is not None}
    if not update:
        return fillet
    try:
        return WeldGeometryConfig.model_validate({**fillet.model_dump(), **update})
    except ValidationError as exc:
        first = exc.errors()[0]
        raise ValueError(f"a fillet weld's {'.'.join(map(str, first['loc']))}: {first['msg']} (the step and slab "
                         "half width given for it)") from None


def scan_weld_document(path: str | Path, *, units: str, line, joint: str, treatment: str,
                       config: MeasureWeldConfig) -> tuple[ScanWeld, list[str]]:
    """The weld in the scan at ``path`` and its problems (``measure_scan_weld``)."""
    measured = measure_scan_weld(path, units=units, line=line, joint=joint, treatment=treatment, config=config)
    return measured.document, measured.problems


def measure_scan_weld(path: str | Path, *, units: str, line, joint: str, treatment: str,
                      config: MeasureWeldConfig) -> MeasuredScan:
    """The weld in the scan at ``path`` (a point file, a sample of imported scans or a run folder;
    ``line``: two points, mm, or None: found on the data) and its problems, one line each (a toe
    not measured, a failing or uncertain figure). ValueError, naming the file: no weld, a line
    outside the scan, a scan too small (its unit), a side with no plate in any section; a fillet
    scan without a stem."""
    scan_points = read_scan_points(path, units=units)
    if joint == FILLET_JOINT:
        return _fillet(scan_points, line=line, treatment=treatment, config=config)
    points = scan_points.points_mm
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
    verdict, summary, failing, uncertain = judged(sections, rule, {"weld": len(sections)})
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
    problems += _finding_lines(name, failing, uncertain)
    spacing = [r.spacing_mm for r in scan.sections if math.isfinite(r.spacing_mm)]
    source = ScanSource(file=str(path), kind=scan_points.kind, files=scan_points.files, points=len(points),
                        profile_scan=scan.profile_scan,
                        profile_pitch_mm=None if scan.profile_pitch_mm is None else round(scan.profile_pitch_mm, 4),
                        point_spacing_mm=round(float(np.median(spacing)), 4) if spacing else None,
                        spikes_dropped=sum(r.spikes for r in scan.sections))
    weld_line = ScanWeldLine(start_mm=tuple(round(v, 4) for v in found.start_mm),
                             end_mm=tuple(round(v, 4) for v in found.end_mm),
                             face_normal=tuple(round(v, 6) for v in found.normal),
                             across=tuple(round(v, 6) for v in found.across), found=found.found)
    document = ScanWeld(source=source, config=config, weld_line=weld_line, geometry=geometry, toes=toes)
    half = (config.section_half_width_mm or (scan.profile_pitch_mm or config.step_mm or 1.0) / 2)
    across = [abs(r.section.toes[k].position_u_mm) for r in scan.sections for k in (0, 1) if r.section.toes[k] is not None]
    return MeasuredScan(document, problems, points, half, 2 * max(across, default=10.0) + 10.0)


def _fillet(scan_points: ScanPoints, *, line, treatment: str, config: MeasureWeldConfig) -> MeasuredScan:
    """A fillet weld in the points (module description)."""
    points, path = scan_points.points_mm, scan_points.path
    name = Path(path).name
    s = fillet_settings(config)
    config = config.model_copy(update={"fillet": s})  # the settings used, in the document
    try:
        check_scan_scale(points)
        root = find_fillet_root(points, line_mm=line, tolerance_mm=config.fillet_plane_tolerance_mm, reach_mm=s.reach_mm)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    found = measure_fillet_line(points, np.array([root.start_mm, root.end_mm]), np.asarray(root.out), np.asarray(root.up),
                                name="weld", step_mm=s.section_step_mm, section_half_width_mm=s.section_half_width_mm,
                                reach_mm=s.reach_mm, end_margin_mm=s.end_margin_mm, settings=section_settings(s),
                                treated=treatment != "as-welded")
    if not found.sections:
        raise ValueError(f"{path}: no fillet section along the root line {_xyz(root.start_mm)}:{_xyz(root.end_mm)}: "
                         f"the points within {s.reach_mm:g} mm of it span less than twice the end margin "
                         f"({s.end_margin_mm:g} mm) along it")
    rule = load_acceptance_limits(None).rule_for(FILLET_JOINT, treatment)
    sections, lines, summary, statistics, failing, uncertain = fillet_weld_figures([found], rule)
    geometry = WeldGeometry(measured=True, joint=FILLET_JOINT, treatment=treatment, frame=f"the scan's own ({name})",
                            acceptance=rule, acceptance_source=None if rule is None else "data_catalog/weld_acceptance.yaml",
                            lines=lines, summary=summary, statistics=statistics, failing=failing, uncertain=uncertain,
                            sections=sections)
    toes, problems = [], []
    for position, sec in found.sections:
        for side, fit in (("base", sec.base_toe), ("stem", sec.stem_toe)):
            toes.append(ScanToe(position_mm=round(position, 3), side=side, measured=fit is not None,
                                reason=None if fit is not None else (_reason(sec.note, side) or "not measured")))
        if sec.note:
            problems.append(f"{name} at {position:.2f} mm: {sec.note}")
    problems += _finding_lines(name, failing, uncertain)
    source = ScanSource(file=str(path), kind=scan_points.kind, files=scan_points.files, points=len(points),
                        profile_scan=False, profile_pitch_mm=None, point_spacing_mm=None, spikes_dropped=0)
    weld_line = ScanWeldLine(start_mm=tuple(round(v, 4) for v in root.start_mm),
                             end_mm=tuple(round(v, 4) for v in root.end_mm),
                             face_normal=tuple(round(v, 6) for v in root.up),
                             across=tuple(round(v, 6) for v in root.out), found=root.found)
    document = ScanWeld(source=source, config=config, weld_line=weld_line, geometry=geometry, toes=toes)
    return MeasuredScan(document, problems, points, s.section_half_width_mm, s.reach_mm)


def _finding_lines(name: str, failing: list, uncertain: list) -> list[str]:
    """A line for each failing or uncertain figure (the document's findings)."""
    return [f"{name} at {f.position_mm:.2f} mm{', ' + f.toe + ' toe' if f.toe else ''}: {f.figure} "
            f"{f.value}{'' if f.sigma is None else f' ± {f.sigma:g}'} {kind} ({f.limit})"
            for kind, findings in (("fails", failing), ("uncertain", uncertain)) for f in findings]


def _reason(note: str, side: str) -> str:
    """The part of a section's note about the toe on ``side`` (all of it when none names it)."""
    parts = [p for p in note.split("; ") if p.startswith(f"{side} toe")]
    return "; ".join(parts) if parts else note


def _xyz(p) -> str:
    return ",".join(f"{v:g}" for v in np.round(p, 3))
