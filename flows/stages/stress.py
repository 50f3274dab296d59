"""Stage ``stress``: the stress concentration along every measured weld toe, from 2-D models of
the part's cross-sections pulled as the fatigue test pulls it (``tasks.section_model``).

Every ``stress.section_step_mm`` along the first measured weld line, the part's section across
the weld is read from the measured points (``tasks.plate_section``: both faces, smoothed, cut
straight across ``stress.cut_mm`` inside the measured length), meshed with 6-node triangles
finest at the toes the weld stage measured, and pulled along its length in plane strain, its
ends held straight (as many sections in one CalculiX run as ``stress.max_nodes_per_solve`` nodes hold). Each toe's factor is the highest maximum
principal stress on the outline within ``peak_reach_mm`` of it over the nominal stress, the force
over the measured thickness of the toe's plate; each toe line's hot spot is its highest section,
and the highest of all is checked again with elements half the size at the toes.

Checks that cannot pass by accident, in ``stress.json``: the two ends' reactions equal (within
0.1 %), and the membrane stress in each plate window (a line fitted through the thickness, read
at mid-plane) the force over the thickness within 1 %. The load case is the butt weld's fatigue
test: axial tension across the weld. A sample with no measured butt weld gets no model (said in
``stress.json``, not an error).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from data_catalog.volume_meshes import write_section_vtu
from flows.stages.outputs import (HOT_SECTION, REFINED, SPECIMEN, STRESS_SUMMARY, STRESS_VTU, WELD_GEOMETRY,
                                  HotSection)
from flows.stages.placement import weld_frame
from schemas.stage_documents import StressConvergence, StressSection, StressSummary, ToeHotSpot, ToeStress
from schemas.weld_document import WeldGeometry
from tasks.frames import apply, invert, rotate
from tasks.plate_section import SectionFrame, plate_profile, profile_section
from tasks.section_model import SectionMeshError, SectionMeshSettings, mesh_sections, peaks_near, pull_sections
from tasks.fe_solve import CalculixNotFound, FESolveError

__all__ = ["stress", "MODEL"]

MODEL = ("2-D sections across the weld, plane strain, 6-node triangles (CalculiX CPE6), steel (210 GPa, 0.3); "
         "axial tension across the weld, both ends held straight")


def _not_made(ctx, why: str) -> dict[str, Any]:
    STRESS_SUMMARY.write(ctx.out, StressSummary(made=False, why=why))
    HOT_SECTION.write(ctx.out, HotSection(points_mm=np.zeros((0, 2)), triangles=np.zeros((0, 3), np.int64),
                                          factor=np.zeros(0, np.float32), toe_mm=np.full(2, np.nan)))
    return {"made": False, "why": why}


def _toe_lines(geometry: WeldGeometry) -> dict[tuple[str, str], np.ndarray]:
    """(line, side) -> the measured toe's points (k, 3), specimen frame, in order along the line:
    each section's toe on its line's across direction from the section's centre (midway between
    its toes), as the weld stage's toes.zarr has them."""
    across = {line.name: np.asarray(line.across, np.float64) for line in geometry.lines}
    found: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = {}
    for sec in geometry.sections:
        if not sec.toes.both():
            continue
        mid = 0.5 * (sec.toes.minus.position_u_mm + sec.toes.plus.position_u_mm)
        for side, toe in sec.toes.sides():
            point = np.asarray(sec.centre_specimen_mm) + (toe.position_u_mm - mid) * across[sec.line]
            found.setdefault((sec.line, side), []).append((sec.position_mm, point))
    return {key: np.array([p for _, p in sorted(rows, key=lambda r: r[0])]) for key, rows in sorted(found.items())
            if len(rows) >= 2}


def _crossing(polyline: np.ndarray, frame: SectionFrame) -> np.ndarray | None:
    """Where the polyline crosses the section's plane, in the points' frame; None: it does not."""
    s = (polyline - frame.origin) @ frame.along
    for k in np.flatnonzero(np.sign(s[:-1]) != np.sign(s[1:])):
        t = s[k] / (s[k] - s[k + 1])
        return polyline[k] + t * (polyline[k + 1] - polyline[k])
    hit = np.flatnonzero(s == 0)
    return polyline[hit[0]] if len(hit) else None


def _membrane_error(solution, profile, x_from: float, x_to: float) -> float:
    """The membrane stress in the plate window (a line through the thickness fitted to the nodes'
    sigma_xx within 1 mm of the window's middle, read at mid-plane) against the force over the
    model's thickness there, relative."""
    x_mid = 0.5 * (x_from + x_to)
    p = solution.mesh.points
    band = (np.abs(p[:, 0] - x_mid) < 1.0) & np.isfinite(solution.stress_mpa[:, 0])
    top, bottom = (float(np.interp(x_mid, profile.x_mm, f)) for f in (profile.top_mm, profile.bottom_mm))
    if band.sum() < 6 or not top > bottom:
        return float("nan")
    A = np.c_[np.ones(int(band.sum())), p[band, 1] - 0.5 * (top + bottom)]
    coef, *_ = np.linalg.lstsq(A, solution.stress_mpa[band, 0], rcond=None)
    return float(coef[0] / (solution.force_n / (top - bottom)) - 1)


def _to_specimen(frame: SectionFrame, xy) -> tuple[float, float, float]:
    x, y = float(xy[0]), float(xy[1])
    return tuple(round(float(v), 4) for v in frame.origin + x * frame.across + y * frame.up)


def stress(ctx) -> dict[str, Any]:
    s = ctx.settings
    geometry = WELD_GEOMETRY.read(ctx.inputs["weld"])
    if not geometry.measured:
        return _not_made(ctx, f"the weld was not measured ({geometry.why_not}): no toes to load")
    toes = _toe_lines(geometry)
    driving = next((line for line in geometry.lines if any(key[0] == line.name for key in toes)), None)
    if driving is None:
        return _not_made(ctx, "no weld line has toes measured in two sections or more")
    T = weld_frame(ctx.manifest, np.asarray(REFINED.open(ctx.inputs["refine"]).T_common_pass[...]))
    cloud = SPECIMEN.read(ctx.inputs["segment"])
    keep = cloud.measured.astype(bool)
    S = invert(T)
    points = apply(S, cloud.points[keep])
    normals = rotate(S, cloud.normals[keep].astype(np.float64))
    up = np.asarray(driving.face_normal, np.float64)
    across = np.asarray(driving.across, np.float64)
    along = np.cross(across, up)
    along /= np.linalg.norm(along)
    # the weld stage's sections of the driving line with both toes, one every section_step_mm
    candidates = sorted((sec for sec in geometry.sections if sec.line == driving.name and sec.toes.both()),
                        key=lambda sec: sec.position_mm)
    chosen, last = [], -math.inf
    for sec in candidates:
        if sec.position_mm >= last + s.section_step_mm - 1e-9:
            chosen.append(sec)
            last = sec.position_mm
    settings = SectionMeshSettings(fine_size_mm=s.toe_size_mm, fine_reach_mm=s.toe_zone_mm, size_mm=s.size_mm,
                                   growth=s.growth)
    models = []  # (section, frame, profile, plane section, [(line, side, toe xy, toe 3-D)])
    for sec in chosen:
        frame = SectionFrame(np.asarray(sec.centre_specimen_mm, np.float64), across, up, along)
        profile = plate_profile(points, normals, frame, half_width_mm=s.half_width_mm, bin_mm=s.bin_mm,
                                smooth_mm=s.smooth_mm)
        if profile is None:
            continue
        crossing = []
        for (line, side), polyline in toes.items():
            hit = _crossing(polyline, frame)
            if hit is not None:
                rel = hit - frame.origin
                crossing.append((line, side, np.array([rel @ across, rel @ up]), hit))
        if not crossing:
            continue
        try:
            plane = profile_section(profile, cut_mm=s.cut_mm, fine_mm=np.array([c[2] for c in crossing]))
        except ValueError:
            continue
        models.append((sec, frame, profile, plane, crossing))
    if not models:
        return _not_made(ctx, "no section of the weld has both faces measured across it")
    try:
        meshes = mesh_sections([m[3] for m in models], settings, timeout_s=s.timeout_s)
        solutions = pull_sections(meshes, timeout_s=s.timeout_s, max_nodes_per_run=s.max_nodes_per_solve)
    except (SectionMeshError, FESolveError, CalculixNotFound) as exc:
        return _not_made(ctx, str(exc))
    sections, factors = [], {}
    near, far = s.plate_window_mm
    for (sec, frame, profile, _, crossing), solution in zip(models, solutions):
        peaks = peaks_near(solution, np.array([c[2] for c in crossing]), s.peak_reach_mm)
        toe_rows, errors = [], []
        for (line, side, xy, hit), (peak, at) in zip(crossing, peaks):
            sign = -1.0 if side == "minus" else 1.0
            window = (sign * near, sign * far)
            thickness = profile.thickness_mm(*window)
            nominal = solution.force_n / thickness if thickness > 0 else math.nan  # NaN: no plate measured there
            errors.append(_membrane_error(solution, profile, *window))
            factor = peak / nominal if math.isfinite(peak) and math.isfinite(nominal) else None
            toe_rows.append(ToeStress(line=line, side=side, factor=None if factor is None else round(factor, 4),
                                      peak_mpa=None if factor is None else round(peak, 3),
                                      nominal_mpa=round(nominal, 4) if math.isfinite(nominal) else None,
                                      plate_thickness_mm=round(thickness, 4) if math.isfinite(thickness) else None,
                                      toe_specimen_mm=tuple(round(float(v), 4) for v in hit),
                                      peak_specimen_mm=None if factor is None else _to_specimen(frame, at)))
            if factor is not None:
                factors.setdefault((line, side), []).append((sec.position_mm, factor, _to_specimen(frame, at)))
        finite = [e for e in errors if math.isfinite(e)]
        sections.append(StressSection(
            position_mm=sec.position_mm, origin_specimen_mm=tuple(round(float(v), 4) for v in frame.origin),
            nodes=len(solution.mesh.points), elements=len(solution.mesh.triangles),
            force_n_per_mm=round(solution.force_n, 4), imbalance=round(solution.imbalance, 8),
            membrane_error=round(max(finite, key=abs), 6) if finite else None, toes=toe_rows))
    hot_spots = []
    for (line, side), rows in sorted(factors.items()):
        position, factor, at = max(rows, key=lambda r: r[1])
        hot_spots.append(ToeHotSpot(line=line, side=side, position_mm=position, factor=round(factor, 4), at_specimen_mm=at,
                                    sections=len(rows), median_factor=round(float(np.median([r[1] for r in rows])), 4)))
    hot = max(hot_spots, key=lambda h: h.factor) if hot_spots else None
    convergence = None
    if hot is None:
        HOT_SECTION.write(ctx.out, HotSection(points_mm=np.zeros((0, 2)), triangles=np.zeros((0, 3), np.int64),
                                              factor=np.zeros(0, np.float32), toe_mm=np.full(2, np.nan)))
    else:
        k = next(i for i, m in enumerate(models) if m[0].position_mm == hot.position_mm)
        sec, frame, profile, plane, crossing = models[k]
        finer = SectionMeshSettings(fine_size_mm=s.toe_size_mm / 2, fine_reach_mm=s.toe_zone_mm, size_mm=s.size_mm,
                                    growth=s.growth)
        try:
            (solution,) = pull_sections(mesh_sections([plane], finer, timeout_s=s.timeout_s), timeout_s=s.timeout_s,
                                        max_nodes_per_run=s.max_nodes_per_solve)
            j = next(i for i, c in enumerate(crossing) if (c[0], c[1]) == (hot.line, hot.side))
            (peak, _), = peaks_near(solution, crossing[j][2][None], s.peak_reach_mm)
            toe = sections[k].toes[j]
            hot_solution = solutions[k]
            HOT_SECTION.write(ctx.out, HotSection(
                points_mm=hot_solution.mesh.points, triangles=hot_solution.mesh.triangles[:, :3].astype(np.int64),
                factor=(hot_solution.max_principal_mpa / toe.nominal_mpa).astype(np.float32), toe_mm=crossing[j][2]))
            finer_factor = peak / (solution.force_n / toe.plate_thickness_mm)
            convergence = StressConvergence(position_mm=hot.position_mm, line=hot.line, side=hot.side,
                                            toe_size_mm=s.toe_size_mm / 2, factor=hot.factor,
                                            finer_factor=round(finer_factor, 4),
                                            change=round(finer_factor / hot.factor - 1, 5))
        except (SectionMeshError, FESolveError) as exc:
            return _not_made(ctx, f"the hot spot's section did not solve with finer elements: {exc}")
    write_section_vtu(ctx.out / STRESS_VTU.name,
                      [(m[1].origin, m[1].across, m[1].up) for m in models], solutions)
    imbalance = max(x.imbalance for x in sections)
    membrane = [x.membrane_error for x in sections if x.membrane_error is not None]
    summary = StressSummary(made=True, model=MODEL, driving_line=driving.name, sections=sections, hot_spots=hot_spots,
                            hot_spot=hot, convergence=convergence, max_imbalance=imbalance,
                            max_membrane_error=max(membrane, key=abs) if membrane else None)
    STRESS_SUMMARY.write(ctx.out, summary)
    return {"made": True, "sections": len(sections), "hot_spot_factor": None if hot is None else hot.factor,
            "hot_spot": None if hot is None else f"{hot.line} {hot.side} at {hot.position_mm:g} mm",
            "max_imbalance": imbalance}
