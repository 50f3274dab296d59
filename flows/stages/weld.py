"""Stage ``weld``: the weld measured on the specimen's merged points and judged against its
acceptance limits (``weld_geometry.json``, ``schemas.weld_document.WeldGeometry``), and the
measured toes as polylines in the common frame (``toes.zarr``, for the FE model).

The points are in the common frame; the specimen frame (where the manifest's weld lines are) comes
from the first setup that states its nominal placement (``T_world_specimen_nominal``) through its
first pass's refined pose; the lines are then refined on the data (``tasks.weld_geometry``). The
figures are fitted on the measured points (cell means of the merged passes), not on the Poisson
surface. A fillet weld (a T-joint's or a cruciform's) is measured in sections across its root
line (``tasks.fillet_section``: toes on the base plate and on the stem, legs, throat, convexity),
the plates' sides known from the specimen (the root on the stem's ``out`` side, the stem ``up``
from the base's face), or, where the manifest gives no specimen (imported scans), found on the
points around the root line (``tasks.scan_fillet``); it is judged as a butt weld is, on its legs,
throat, convexity, the legs' difference and both toes (``tasks.weld_acceptance.judge_fillet_weld``,
the catalog's rule for the joint and treatment). A sample whose setups state no nominal placement,
or whose joint is neither, is not measured (said in the file, not an error).

Each section's ``verdict`` is "pass", "fail", "uncertain" (a figure within its 1-sigma of a limit,
or a limited figure not measured: listed in its ``uncertain``, and all of them in the file's
``uncertain``; it does not fail the weld) or "not measured"; ``failing`` lists the violations.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from data_catalog.acceptance import load_acceptance_limits
from flows.stages.outputs import REFINED, SPECIMEN, WELD_GEOMETRY, WELD_TOES, WeldToes
from flows.stages.placement import weld_frame
from schemas.weld_document import (FILLET_SECTION_FIGURES, TOE_FIGURES, FilletToes, FilletWeldSection, Figure,
                                   FigureStatistics, Finding, GrooveFigures, SectionToes, ToeFigures, WeldGeometry,
                                   WeldLineFound, WeldSection, WeldSummary)
from tasks.fillet_section import FilletLine, measure_fillet_line
from tasks.frames import apply, invert, rotate
from tasks.scan_fillet import find_fillet_root
from tasks.weld_acceptance import fillet_section_measured, judge_fillet_weld, judge_weld, section_measured
from tasks.weld_fits import Measured, SectionSettings
from tasks.weld_geometry import SectionMeasurement, along_weld_statistics, measure_weld_line, toe_polylines

__all__ = ["weld", "MEASURABLE_JOINTS", "FILLET_JOINTS", "section_settings", "judged", "section_document",
           "section_statistics", "finding_document",
           "fillet_section_document", "fillet_weld_figures"]

MEASURABLE_JOINTS = ("double-sided butt", "single-V butt", "double-V butt")  # a cap between two plates
FILLET_JOINTS = ("fillet", "double fillet", "cruciform fillet")  # between a base plate and a stem on it
SECTION_WORKERS = 2  # weld sections measured at once (numpy releases the GIL; the result does not depend on it)


def _figure(m: Measured, digits: int = 4) -> Figure:
    return Figure(**m.as_dict(digits))


def _toe_figures(toe) -> ToeFigures | None:
    if toe is None:
        return None
    g = toe.groove
    groove = None if g is None else GrooveFigures(
        depth_mm=_figure(g.depth), width_mm=_figure(g.width), radius_mm=_figure(g.radius), toe_within_groove=g.toe_within,
        fit_rms_mm=round(g.rms_mm, 5), points=g.n_points)
    return ToeFigures(side=toe.side, position_u_mm=round(toe.position_u_mm, 4),
                      position_sigma_mm=None if not math.isfinite(toe.position_sigma_mm) else round(toe.position_sigma_mm, 4),
                      flank_angle_deg=_figure(toe.flank_angle_deg, 3), toe_radius_mm=_figure(toe.notch_radius),
                      undercut_depth_mm=_figure(toe.undercut_depth), fit_rms_mm=round(toe.rms_mm, 5), points=toe.n_points,
                      treated=g is not None, groove=groove, note=toe.note or None)


def finding_document(v) -> Finding:
    return Finding(line=v.line, position_mm=v.position_mm, toe=v.toe, figure=v.figure, value=v.value, limit=v.limit,
                   sigma=v.sigma)


def section_document(sec: SectionMeasurement, verdict) -> WeldSection:
    return WeldSection(line=sec.line, position_mm=round(sec.position_mm, 3),
                       centre_specimen_mm=tuple(round(v, 4) for v in sec.centre_mm), points=sec.n_points,
                       reinforcement_height_mm=_figure(sec.height), reinforcement_width_mm=_figure(sec.width),
                       axial_misalignment_mm=_figure(sec.axial_misalignment),
                       angular_misalignment_deg=_figure(sec.angular_misalignment_deg),
                       toes=SectionToes(minus=_toe_figures(sec.toes[0]), plus=_toe_figures(sec.toes[1])),
                       note=sec.note or None, **_verdict_fields(verdict))


def _verdict_fields(verdict) -> dict[str, Any]:
    """A section's verdict (``tasks.weld_acceptance.SectionVerdict``; None: no rule) as its document's fields."""
    return dict(passed=None if verdict is None else verdict.passed,
                verdict=None if verdict is None else verdict.verdict,
                violations=[] if verdict is None else [finding_document(v) for v in verdict.violations],
                uncertain=[] if verdict is None else [finding_document(v) for v in verdict.uncertain])


def judged(sections: list[SectionMeasurement], rule, lines: dict[str, int]):
    """The sections judged by ``rule`` (None: no rule): the verdict (None without a rule), the
    summary, the failing findings and the uncertain ones of passing sections. ``lines``: each weld
    line's name and how many of the sections are its."""
    return verdict_parts(judge_weld(sections, rule) if rule is not None else None,
                         [section_measured(s) for s in sections], lines_measured(lines, sections, section_measured))


def lines_measured(lines: dict[str, int], sections: list, measured) -> dict[str, int]:
    """Each weld line's count of measured sections (``measured(section)``; a section's ``line``
    names its line), every line of ``lines`` present."""
    count = dict.fromkeys(lines, 0)
    for sec in sections:
        count[sec.line] = count.get(sec.line, 0) + bool(measured(sec))
    return count


def verdict_parts(verdict, measured: list[bool], per_line: dict[str, int]):
    """A weld's verdict (``tasks.weld_acceptance``; None: no rule) as the document has it: the
    verdict, the summary, the failing findings and the uncertain ones of passing sections.
    ``measured``: per section, whether it was; ``per_line``: each weld line's measured sections.
    Every section's evidence counts whether or not a rule judges it: the summary counts the measured
    sections always; a weld with none measured, or with a line that has none, does not pass, and its
    verdict says which (no weld found at the lines; the lines without a section)."""
    failing = [] if verdict is None else [finding_document(v) for sv in verdict.sections for v in sv.violations]
    uncertain = [] if verdict is None else [finding_document(v) for sv in verdict.sections if sv.passed
                                            for v in sv.uncertain]
    n, n_measured = len(measured), sum(measured)
    empty = sorted(name for name, k in per_line.items() if k == 0)
    if n_measured == 0:
        said = (f"not measured: no weld found at the weld line{'s' if len(per_line) != 1 else ''} "
                f"({', '.join(sorted(per_line)) or 'none'})")
        passed = None if verdict is None else False
    elif empty:
        said = (f"incomplete: weld line{'s' if len(empty) > 1 else ''} {', '.join(empty)} without a measured section "
                f"(not scanned there, or no weld found at {'them' if len(empty) > 1 else 'it'})")
        passed = None if verdict is None else False
    elif verdict is None:
        said, passed = "no acceptance rule for this joint and treatment", None
    else:
        said, passed = ("pass" if verdict.passed else "fail"), verdict.passed
    summary = WeldSummary(sections=n, sections_measured=n_measured, sections_not_measured=n - n_measured,
                          failing=None if verdict is None else verdict.n_failing,
                          sections_uncertain=None if verdict is None else verdict.n_uncertain,
                          passed=passed, verdict=said, lines_without_sections=empty)
    return verdict, summary, failing, uncertain


def section_statistics(sections: list[SectionMeasurement]) -> dict[str, FigureStatistics]:
    return _along(sections, {"reinforcement_height_mm": lambda s: s.height.value,
                             "reinforcement_width_mm": lambda s: s.width.value,
                             "axial_misalignment_mm": lambda s: s.axial_misalignment.value,
                             "angular_misalignment_deg": lambda s: s.angular_misalignment_deg.value},
                  lambda s: (s.line, s.position_mm, s.toes))


def _along(sections: list, per_section: dict, where_and_toes) -> dict[str, FigureStatistics]:
    """The statistics along the weld of each section figure (``per_section``: name -> getter) and
    of each toe figure (``where_and_toes(section)``: its line, position and toe fits)."""
    rows_where = [where_and_toes(s) for s in sections]
    where = [{"line": line, "position_mm": round(position, 3)} for line, position, _ in rows_where]
    figures: dict[str, FigureStatistics] = {}
    for name, get in per_section.items():
        figures[name] = FigureStatistics(**along_weld_statistics(np.array([get(s) for s in sections], float), where))
    toe_where, rows = [], []
    for line, position, toes in rows_where:
        for t in toes:
            if t is not None:
                toe_where.append({"line": line, "position_mm": round(position, 3), "toe": t.side})
                g = t.groove
                rows.append([t.notch_radius.value, t.flank_angle_deg.value, t.undercut_depth.value,
                             g.depth.value if g else math.nan, g.width.value if g else math.nan,
                             g.radius.value if g else math.nan])
    rows = np.array(rows, float).reshape(-1, 6)
    for k, name in enumerate(TOE_FIGURES):
        figures[name] = FigureStatistics(**along_weld_statistics(rows[:, k], toe_where))
    return figures


def _no_toes(ctx) -> None:
    WELD_TOES.write(ctx.out, WeldToes(points_mm=np.zeros((0, 3)), polyline=np.zeros(0, np.int64),
                                      position_mm=np.zeros(0)))


def _not_measured(ctx, document: WeldGeometry) -> dict[str, Any]:
    WELD_GEOMETRY.write(ctx.out, document)
    _no_toes(ctx)
    return {"measured": False, "why_not": document.why_not}


def section_settings(s) -> SectionSettings:
    """How a section is read, from the weld settings (``schemas.reconstruction.WeldGeometryConfig``)."""
    return SectionSettings(plate_window_mm=tuple(s.plate_window_mm), toe_window_mm=tuple(s.toe_window_mm),
                           toe_threshold_mm=s.toe_threshold_mm, groove_min_depth_mm=s.groove_min_depth_mm,
                           groove_plate_gap_mm=s.groove_plate_gap_mm, undercut_min_depth_mm=s.undercut_min_depth_mm,
                           height_half_width_mm=s.height_half_width_mm, min_points=s.min_points,
                           min_height_mm=s.min_height_mm)


def _fillet_sides(manifest, line) -> tuple[np.ndarray, np.ndarray] | str:
    """A fillet root line's ``out`` (along the base plate, away from the stem) and ``up`` (along
    the stem, away from the base), specimen frame, from the specimen's stem; or why not."""
    specimen = manifest.specimen
    if getattr(specimen, "kind", None) not in ("t-joint", "cruciform"):
        return (f"the specimen ({getattr(specimen, 'kind', None)}) does not say where the stem stands: the "
                "fillet's plates cannot be told apart")
    mid = np.mean(np.asarray(line.points_mm, np.float64), axis=0)
    side, face = mid[0] - specimen.stem_x_mm, mid[2]
    if abs(side) < 1e-6 or abs(face) < 1e-6:
        return (f"weld line {line.name!r} runs in the stem's mid-plane or the base plate's: its root must lie "
                "on a stem face where it meets a base plate face")
    return np.array([math.copysign(1.0, side), 0.0, 0.0]), np.array([0.0, 0.0, math.copysign(1.0, face)])


def fillet_section_document(line: FilletLine, position: float, sec, verdict=None) -> FilletWeldSection:
    """A fillet section (``tasks.fillet_section``) at ``position`` along ``line`` as the document's,
    with its verdict (``tasks.weld_acceptance.SectionVerdict``; None: no rule)."""
    ok = math.isfinite(sec.root_ab_mm[0])
    root = line.to_frame(position, sec.root_ab_mm) if ok else line.to_frame(position, (0.0, 0.0))
    return FilletWeldSection(
        line=line.name, position_mm=round(position, 3), centre_specimen_mm=tuple(round(float(v), 4) for v in root),
        points=sec.n_points, base_direction=tuple(round(float(v), 6) for v in line.direction(sec.base_direction)),
        stem_direction=tuple(round(float(v), 6) for v in line.direction(sec.stem_direction)),
        plates_angle_deg=round(sec.plates_angle_deg, 4) if ok else None,
        leg_base_mm=_figure(sec.leg_base), leg_stem_mm=_figure(sec.leg_stem), throat_mm=_figure(sec.throat),
        convexity_mm=_figure(sec.convexity),
        toes=FilletToes(base=_toe_figures(sec.base_toe), stem=_toe_figures(sec.stem_toe)),
        note=sec.note or None, **_verdict_fields(verdict))


def fillet_weld_figures(found: list[FilletLine], rule) -> tuple[list[FilletWeldSection], list[WeldLineFound],
                                                               WeldSummary, dict[str, FigureStatistics], list, list]:
    """The document's parts of a fillet weld measured along its root lines (``found``) and judged
    by ``rule`` (None: not judged): its sections, its lines, the summary, the statistics along it,
    the failing findings and the uncertain ones."""
    along = [(line, position, sec) for line in found for position, sec in line.sections]
    rows = [(line.name, position, sec) for line, position, sec in along]
    measured = [fillet_section_measured(sec) for _, _, sec in rows]
    per_line = dict.fromkeys((line.name for line in found), 0)
    for (name, _, _), ok in zip(rows, measured):
        per_line[name] += ok
    verdict, summary, failing, uncertain = verdict_parts(
        judge_fillet_weld(rows, rule) if rule is not None else None, measured, per_line)
    sections = [fillet_section_document(line, position, sec, None if verdict is None else verdict.sections[k])
                for k, (line, position, sec) in enumerate(along)]
    lines = []
    for line in found:
        roots = [sec.root_ab_mm for _, sec in line.sections if math.isfinite(sec.root_ab_mm[0])]
        lines.append(WeldLineFound(
            name=line.name, sections=len(line.sections),
            offset_mm=round(float(np.median([r[0] for r in roots])), 4) if roots else 0.0, turn_deg=0.0,
            face_normal=tuple(float(v) for v in line.up), across=tuple(float(v) for v in line.out),
            measured_extent_mm=tuple(round(v, 3) for v in line.extent_mm)))
    statistics = _along(rows, dict(zip(FILLET_SECTION_FIGURES, (
        lambda r: r[2].leg_base.value, lambda r: r[2].leg_stem.value, lambda r: r[2].throat.value,
        lambda r: r[2].convexity.value))), lambda r: (r[0], r[1], (r[2].base_toe, r[2].stem_toe)))
    return sections, lines, summary, statistics, failing, uncertain


def _fillet_sides_on_data(points: np.ndarray, line, reach_mm: float) -> tuple[np.ndarray, np.ndarray] | str:
    """A fillet root line's ``out`` and ``up`` found on the points within ``reach_mm`` of it (where
    the plates lie: ``tasks.scan_fillet``), for a sample that gives no specimen (imported scans)."""
    ends = np.asarray(line.points_mm, np.float64)[[0, -1]]
    t = ends[1] - ends[0]
    length = float(np.linalg.norm(t))
    t /= length
    rel = points - ends[0]
    along = rel @ t
    near = points[(along >= -reach_mm) & (along <= length + reach_mm)
                  & (np.linalg.norm(rel - along[:, None] * t, axis=1) <= reach_mm)]
    try:
        root = find_fillet_root(near, line_mm=(tuple(ends[0]), tuple(ends[1])), reach_mm=reach_mm)
    except ValueError as exc:
        return f"weld line {line.name!r}: the plates' sides were not found on the data: {exc}"
    return np.asarray(root.out, np.float64), np.asarray(root.up, np.float64)


def _fillet_weld(ctx, points: np.ndarray, T: np.ndarray, head: dict) -> dict[str, Any]:
    """A fillet weld's sections along each root line (module description), its document and toes."""
    s, manifest = ctx.settings, ctx.manifest
    sides = {line.name: (_fillet_sides(manifest, line) if manifest.specimen is not None
                         else _fillet_sides_on_data(points, line, s.reach_mm)) for line in manifest.weld_lines()}
    why = next((v for v in sides.values() if isinstance(v, str)), None)
    if why:
        return _not_measured(ctx, WeldGeometry(measured=False, why_not=why, **head))
    treated = manifest.weld.treatment != "as-welded"
    found = [measure_fillet_line(points, np.asarray(line.points_mm, np.float64), *sides[line.name], name=line.name,
                                 step_mm=s.section_step_mm, section_half_width_mm=s.section_half_width_mm,
                                 reach_mm=s.reach_mm, end_margin_mm=s.end_margin_mm, settings=section_settings(s),
                                 treated=treated)
             for line in manifest.weld_lines()]
    sections, lines, summary, statistics, failing, uncertain = fillet_weld_figures(found, head["acceptance"])
    WELD_GEOMETRY.write(ctx.out, WeldGeometry(measured=True, lines=lines, summary=summary, statistics=statistics,
                                              failing=failing, uncertain=uncertain, sections=sections, **head))
    # the toes as polylines in the common frame (the FE model grades its elements toward them)
    polylines = []
    for line in found:
        for side in ("base", "stem"):
            rows = [(position, sec) for position, sec in line.sections if sec.toe_ab_mm(side) is not None]
            if len(rows) >= 2:
                polylines.append((np.array([p for p, _ in rows]),
                                  np.array([line.to_frame(p, sec.toe_ab_mm(side)) for p, sec in rows])))
    WELD_TOES.write(ctx.out, WeldToes(
        points_mm=np.vstack([apply(T, q) for _, q in polylines] or [np.zeros((0, 3))]),
        polyline=np.concatenate([np.full(len(q), k, np.int64) for k, (_, q) in enumerate(polylines)]
                                or [np.zeros(0, np.int64)]),
        position_mm=np.concatenate([p for p, _ in polylines] or [np.zeros(0)])))
    return {**summary.model_dump(), "toe_radius_min_mm": statistics["toe_radius_mm"].min,
            "flank_angle_max_deg": statistics["flank_angle_deg"].max, "leg_min_mm": min(
                (v for v in (statistics["leg_base_mm"].min, statistics["leg_stem_mm"].min) if v is not None), default=None)}


def weld(ctx) -> dict[str, Any]:
    s = ctx.settings
    manifest = ctx.manifest
    if manifest.weld is None:  # imported scans of a part the manifest says nothing of
        return _not_measured(ctx, WeldGeometry(
            measured=False, why_not="the manifest describes no weld (a sample of imported scans): nothing to measure",
            joint=None, treatment=None))
    joint = getattr(manifest.weld, "joint", "double-sided butt")
    treatment = manifest.weld.treatment
    limits = s.acceptance if s.acceptance is not None else load_acceptance_limits(None)
    rule = limits.rule_for(joint, treatment)
    frame = ("the scans' (their weld lines given or found at import; lines refined on the data)"
             if manifest.surfaces and manifest.specimen is None else "specimen (nominal placement, lines refined on the data)")
    head = dict(joint=joint, treatment=treatment, frame=frame,
                acceptance=rule, acceptance_source="settings (weld.acceptance)" if s.acceptance is not None
                else "data_catalog/weld_acceptance.yaml")
    T = weld_frame(manifest, np.asarray(REFINED.open(ctx.inputs["refine"]).T_common_pass[...]))
    why = None
    if joint not in MEASURABLE_JOINTS + FILLET_JOINTS:
        why = (f"joint {joint!r}: the sections measure a butt weld between two plates (one of {list(MEASURABLE_JOINTS)}) "
               f"or a fillet weld between a base plate and a stem (one of {list(FILLET_JOINTS)})")
    elif T is None:
        why = "no setup states the specimen's nominal placement (T_world_specimen_nominal): the weld lines cannot be found"
    if why:
        return _not_measured(ctx, WeldGeometry(measured=False, why_not=why, **head))
    cloud = SPECIMEN.read(ctx.inputs["segment"])
    keep = cloud.measured.astype(bool)
    T_specimen_common = invert(T)
    points = apply(T_specimen_common, cloud.points[keep])
    normals = rotate(T_specimen_common, cloud.normals[keep].astype(np.float64))
    if joint in FILLET_JOINTS:
        return _fillet_weld(ctx, points, T, head)
    settings = section_settings(s)
    treated = treatment != "as-welded"
    found_lines = [measure_weld_line(points, normals, np.asarray(line.points_mm, np.float64), name=line.name,
                                     step_mm=s.section_step_mm, section_half_width_mm=s.section_half_width_mm,
                                     reach_mm=s.reach_mm, end_margin_mm=s.end_margin_mm, min_normal_cos=s.min_normal_cos,
                                     settings=settings, treated=treated, workers=SECTION_WORKERS)
                   for line in manifest.weld_lines()]
    lines = [WeldLineFound(name=f.line, sections=len(f.sections), offset_mm=round(f.offset_mm, 4),
                           turn_deg=round(f.turn_deg, 4), face_normal=tuple(round(v, 5) for v in f.normal),
                           across=tuple(round(v, 5) for v in f.across),
                           measured_extent_mm=tuple(round(v, 3) for v in f.extent_mm)) for f in found_lines]
    sections = [sec for f in found_lines for sec in f.sections]
    verdict, summary, failing, uncertain = judged(sections, rule, {f.line: len(f.sections) for f in found_lines})
    statistics = section_statistics(sections)
    WELD_GEOMETRY.write(ctx.out, WeldGeometry(
        measured=True, lines=lines, summary=summary, statistics=statistics, failing=failing, uncertain=uncertain,
        sections=[section_document(sec, None if verdict is None else verdict.sections[k]) for k, sec in enumerate(sections)],
        **head))
    # the toes as polylines in the common frame, at full precision (the FE model grades its elements toward them)
    toes = toe_polylines(found_lines)
    WELD_TOES.write(ctx.out, WeldToes(
        points_mm=np.vstack([apply(T, q) for *_, q in toes] or [np.zeros((0, 3))]),
        polyline=np.concatenate([np.full(len(q), k, np.int64) for k, (*_, q) in enumerate(toes)] or [np.zeros(0, np.int64)]),
        position_mm=np.concatenate([p for _, _, p, _ in toes] or [np.zeros(0)])))
    return {**summary.model_dump(), "failing_first": [f.model_dump() for f in failing[:5]],
            "uncertain_first": [f.model_dump() for f in uncertain[:5]],
            "toe_radius_min_mm": statistics["toe_radius_mm"].min, "flank_angle_max_deg": statistics["flank_angle_deg"].max,
            "height_max_mm": statistics["reinforcement_height_mm"].max,
            "groove_depth_min_mm": statistics["groove_depth_mm"].min}
