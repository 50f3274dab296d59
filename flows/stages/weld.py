"""Stage ``weld``: the weld measured on the specimen's merged points and judged against its
acceptance limits (``weld_geometry.json``).

The points are in the common frame; the specimen frame (where the manifest's weld lines are) comes
from the first setup that states its nominal placement (``T_world_specimen_nominal``) through its
first pass's refined pose; the lines are then refined on the data (``tasks.weld_geometry``). The
figures are fitted on the measured points (cell means of the merged passes), not on the Poisson
surface. A sample whose setups state no nominal placement, or whose joint is not a butt weld
between two plates, is not measured (said in the file, not an error).

Each section's ``verdict`` is "pass", "fail", "uncertain" (a figure within its 1-sigma of a limit,
or a limited figure not measured: listed in its ``uncertain``, and all of them in the file's
``uncertain``; it does not fail the weld) or "not measured"; ``failing`` lists the violations.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from data_catalog.acceptance import DEFAULT_ACCEPTANCE_FILE, load_acceptance_limits
from data_catalog.hashing import sha256_file
from flows.stages.outputs import REFINED, SPECIMEN, WELD_GEOMETRY
from flows.stages.weld_lines import weld_frame
from schemas.manifest import SampleManifest
from tasks.weld_acceptance import judge_weld
from tasks.weld_fits import SectionSettings
from tasks.weld_geometry import TOE_SIDES, SectionMeasurement, along_weld_statistics, measure_weld_line

__all__ = ["weld", "weld_view", "MEASURABLE_JOINTS"]

MEASURABLE_JOINTS = ("double-sided butt", "single-V butt", "double-V butt")  # a cap between two plates


def weld_view(manifest: SampleManifest, entry=None) -> dict[str, Any]:
    """What the weld stage reads: the passes (in order), the weld (lines, joint, treatment), each
    setup's nominal placement, and the default acceptance limits' file (by sha256)."""
    weld = manifest.weld
    return {"passes": [e.pass_id for _, e in manifest.passes()],
            "weld_lines_mm": {line.name: [list(p) for p in line.points_mm] for line in manifest.weld_lines()},
            "joint": getattr(weld, "joint", "double-sided butt"), "treatment": None if weld is None else weld.treatment,
            "setups": [{"name": s.name, "first_pass": s.passes[0].pass_id,
                        "T_world_specimen_nominal": s.T_world_specimen_nominal} for s in manifest.setups],
            "default_acceptance_sha256": sha256_file(DEFAULT_ACCEPTANCE_FILE)}


def _toe_json(toe) -> dict[str, Any] | None:
    if toe is None:
        return None
    out = {"side": toe.side, "position_u_mm": round(toe.position_u_mm, 4),
           "position_sigma_mm": None if not math.isfinite(toe.position_sigma_mm) else round(toe.position_sigma_mm, 4),
           "flank_angle_deg": toe.flank_angle_deg.as_dict(3), "toe_radius_mm": toe.radius.as_dict(),
           "undercut_depth_mm": toe.undercut_depth.as_dict(), "fit_rms_mm": round(toe.rms_mm, 5),
           "points": toe.n_points, "treated": toe.groove is not None}
    if toe.groove is not None:
        g = toe.groove
        out["groove"] = {"depth_mm": g.depth.as_dict(), "width_mm": g.width.as_dict(), "radius_mm": g.radius.as_dict(),
                         "toe_within_groove": g.toe_within, "fit_rms_mm": round(g.rms_mm, 5), "points": g.n_points}
    if toe.note:
        out["note"] = toe.note
    return out


def _section_json(sec: SectionMeasurement, verdict) -> dict[str, Any]:
    return {"line": sec.line, "position_mm": round(sec.position_mm, 3),
            "centre_specimen_mm": [round(v, 4) for v in sec.centre_mm], "points": sec.n_points,
            "reinforcement_height_mm": sec.height.as_dict(), "reinforcement_width_mm": sec.width.as_dict(),
            "axial_misalignment_mm": sec.axial_misalignment.as_dict(),
            "angular_misalignment_deg": sec.angular_misalignment_deg.as_dict(),
            "toes": {side: _toe_json(t) for side, t in zip(TOE_SIDES, sec.toes)},
            "passed": None if verdict is None else verdict.passed,
            "violations": [] if verdict is None else [v.__dict__ for v in verdict.violations],
            "verdict": None if verdict is None else verdict.verdict,
            "uncertain": [] if verdict is None else [v.__dict__ for v in verdict.uncertain],
            **({"note": sec.note} if sec.note else {})}


def _statistics(sections: list[SectionMeasurement]) -> dict[str, Any]:
    where = [{"line": s.line, "position_mm": round(s.position_mm, 3)} for s in sections]
    figures: dict[str, Any] = {}

    def per_section(name, get):
        figures[name] = along_weld_statistics(np.array([get(s) for s in sections], float), where)

    per_section("reinforcement_height_mm", lambda s: s.height.value)
    per_section("reinforcement_width_mm", lambda s: s.width.value)
    per_section("axial_misalignment_mm", lambda s: s.axial_misalignment.value)
    per_section("angular_misalignment_deg", lambda s: s.angular_misalignment_deg.value)
    toe_where, rows = [], []
    for s in sections:
        for t in s.toes:
            if t is not None:
                toe_where.append({"line": s.line, "position_mm": round(s.position_mm, 3), "toe": t.side})
                g = t.groove
                rows.append([t.radius.value, t.flank_angle_deg.value, t.undercut_depth.value,
                             g.depth.value if g else math.nan, g.width.value if g else math.nan,
                             g.radius.value if g else math.nan])
    rows = np.array(rows, float).reshape(-1, 6)
    for k, name in enumerate(("toe_radius_mm", "flank_angle_deg", "undercut_depth_mm", "groove_depth_mm",
                              "groove_width_mm", "groove_radius_mm")):
        figures[name] = along_weld_statistics(rows[:, k], toe_where)
    return figures


def weld(ctx) -> dict[str, Any]:
    s = ctx.settings
    manifest = ctx.manifest
    if manifest.weld is None:  # imported scans of a part the manifest says nothing of
        why = "the manifest describes no weld (a sample of imported scans): nothing to measure"
        WELD_GEOMETRY.write(ctx.out, {"joint": None, "treatment": None, "measured": False, "why_not": why,
                                      "lines": [], "sections": []})
        return {"measured": False, "why_not": why}
    joint = getattr(manifest.weld, "joint", "double-sided butt")
    treatment = manifest.weld.treatment
    limits = s.acceptance if s.acceptance is not None else load_acceptance_limits(None)
    rule = limits.rule_for(joint, treatment)
    body: dict[str, Any] = {"joint": joint, "treatment": treatment, "frame": "specimen (nominal placement, lines refined on the data)",
                            "acceptance": None if rule is None else rule.model_dump(mode="json"),
                            "acceptance_source": "settings (weld.acceptance)" if s.acceptance is not None
                            else "data_catalog/weld_acceptance.yaml"}
    T = weld_frame(manifest, np.asarray(REFINED.open(ctx.inputs["refine"]).T_common_pass[...]))
    why = None
    if joint not in MEASURABLE_JOINTS:
        why = f"joint {joint!r}: the sections measure a butt weld between two plates (one of {list(MEASURABLE_JOINTS)})"
    elif T is None:
        why = "no setup states the specimen's nominal placement (T_world_specimen_nominal): the weld lines cannot be found"
    if why:
        WELD_GEOMETRY.write(ctx.out, {**body, "measured": False, "why_not": why, "lines": [], "sections": []})
        return {"measured": False, "why_not": why}
    cloud = SPECIMEN.read(ctx.inputs["segment"])
    keep = cloud.measured.astype(bool)
    T_inv = np.linalg.inv(T)
    points = cloud.points[keep] @ T_inv[:3, :3].T + T_inv[:3, 3]
    normals = cloud.normals[keep].astype(np.float64) @ T_inv[:3, :3].T
    settings = SectionSettings(plate_window_mm=tuple(s.plate_window_mm), toe_window_mm=tuple(s.toe_window_mm),
                               toe_threshold_mm=s.toe_threshold_mm, groove_min_depth_mm=s.groove_min_depth_mm,
                               groove_plate_gap_mm=s.groove_plate_gap_mm,
                               undercut_min_depth_mm=s.undercut_min_depth_mm,
                               height_half_width_mm=s.height_half_width_mm, min_points=s.min_points)
    treated = treatment != "as-welded"
    lines, sections = [], []
    for line in manifest.weld_lines():
        found = measure_weld_line(points, normals, np.asarray(line.points_mm, np.float64), name=line.name,
                                  step_mm=s.section_step_mm, section_half_width_mm=s.section_half_width_mm,
                                  reach_mm=s.reach_mm, end_margin_mm=s.end_margin_mm, min_normal_cos=s.min_normal_cos,
                                  settings=settings, treated=treated)
        lines.append({"name": line.name, "sections": len(found.sections), "offset_mm": round(found.offset_mm, 4),
                      "turn_deg": round(found.turn_deg, 4), "face_normal": [round(v, 5) for v in found.normal],
                      "across": [round(v, 5) for v in found.across],
                      "measured_extent_mm": [round(v, 3) for v in found.extent_mm]})
        sections += found.sections
    verdict = judge_weld(sections, rule) if rule is not None else None
    failing = [] if verdict is None else [v.__dict__ for sv in verdict.sections for v in sv.violations]
    uncertain = [] if verdict is None else [v.__dict__ for sv in verdict.sections if sv.passed for v in sv.uncertain]
    section_rows = [_section_json(sec, None if verdict is None else verdict.sections[k]) for k, sec in enumerate(sections)]
    summary = {"sections": len(sections),
               "sections_measured": None if verdict is None else verdict.n_measured,
               "sections_not_measured": None if verdict is None else verdict.n_not_measured,
               "failing": None if verdict is None else verdict.n_failing,
               "sections_uncertain": None if verdict is None else verdict.n_uncertain,
               "passed": None if verdict is None else verdict.passed,
               "verdict": ("no acceptance rule for this joint and treatment" if verdict is None
                           else "pass" if verdict.passed else "fail")}
    body.update({"measured": True, "lines": lines, "summary": summary, "statistics": _statistics(sections),
                 "failing": failing, "uncertain": uncertain, "sections": section_rows})
    WELD_GEOMETRY.write(ctx.out, body)
    stats = body["statistics"]
    return {**summary, "failing_first": failing[:5], "uncertain_first": uncertain[:5],
            "toe_radius_min_mm": stats["toe_radius_mm"].get("min"), "flank_angle_max_deg": stats["flank_angle_deg"].get("max"),
            "height_max_mm": stats["reinforcement_height_mm"].get("max"),
            "groove_depth_min_mm": stats["groove_depth_mm"].get("min")}
