"""Stage ``stress``: the stress concentration along every measured weld toe, from 2-D models of
the part's cross-sections pulled or bent as the fatigue test loads it (``tasks.section_model``).

Every ``stress.section_step_mm`` along the first measured weld line, the part's section across
the weld is read from the measured points (``tasks.plate_section``: both faces, smoothed, cut
straight across ``stress.cut_mm`` inside the measured length), meshed with 6-node triangles
finest at the toes the weld stage measured, and loaded in plane strain, its ends held straight
(as many sections in one CalculiX run as ``stress.max_nodes_per_solve`` nodes hold): pulled along
its length (the manifest's load ``axial``, or no load given: the butt weld's fatigue test) or bent,
each end turned about its mid-thickness, the top face stretched (``bending``: a 4-point bending
test's zone between its inner rollers). Each toe's factor is the highest maximum principal stress
on the outline within ``peak_reach_mm`` of it over the nominal stress at the toe's plate (its
measured thickness t): the force over t, or the moment over the section modulus, 6 M / t^2; each
toe line's hot spot is its highest section, and the highest of all is checked again with elements
half the size at the toes.

Checks that cannot pass by accident, in ``stress.json``: the two ends' reactions (forces;
moments) equal within 0.1 %, and the stress through each plate window (a line fitted through the
thickness) the nominal one within 1 %: pulled, its mid-plane value the force over the thickness;
bent, its surface value 6 M / t^2 and its mid-plane value ~0. A T-joint's fillet welds: the
section through both fillets' roots, the stem cut ``stress.stem_cut_mm`` above the base; a
cruciform's: the lower stem's roots and fillets too (``_tee``); the base plate loaded. A sample
with no measured weld gets no model (said in ``stress.json``, not an error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from data_catalog.volume_meshes import write_section_vtu
from flows.stages.outputs import (HOT_SECTION, REFINED, SPECIMEN, STRESS_SUMMARY, STRESS_VTU, WELD_GEOMETRY,
                                  HotSection)
from flows.stages.placement import weld_frame
from schemas.stage_documents import (DrawnStress, DrawnToe, FatigueEstimate, RefusedSection, StressConvergence,
                                     StressSection, StressSummary, ToeHotSpot, ToeStress)
from schemas.weld_document import FilletWeldSection, WeldGeometry, WeldSection
from tasks.arrays import distinct
from tasks.frames import apply, invert, rotate
from tasks.plate_section import (PlateProfile, SectionFrame, TeeProfile, drawn_profile, plate_profile,
                                 profile_section, rounded_notches, rounded_tee, tee_profile, tee_section,
                                 drawn_tee_section)
from tasks.section_model import (PlaneSection, SectionMeshError, SectionMeshSettings, SectionMesh, SectionSolution,
                                 bend_sections, each_solved, mesh_sections, peaks_near, pull_sections)
from tasks.fatigue import notch_cycles
from tasks.fe_solve import CalculixNotFound, FESolveError

__all__ = ["stress", "MODEL", "MODEL_BENDING", "TEE", "notch_mesh"]

_SECTIONS = "2-D sections across the weld, plane strain, 6-node triangles (CalculiX CPE6), steel (210 GPa, 0.3); "
MODEL = _SECTIONS + "axial tension across the weld, both ends held straight"
MODEL_BENDING = (_SECTIONS + "pure bending about the weld's axis, the top face stretched: both ends held straight and "
                 "turned about their mid-thickness")

# what a T-joint's sections are (the load follows: pulled or bent, the base plate's ends held straight)
TEE = ("; a T-joint: the base plate with the stem and its two fillets, the stem cut stress.stem_cut_mm above the "
       "base and free (the non-load-carrying fillet weld's test)")
CRUCIFORM = ("; a cruciform joint: the base plate with both stems and their four fillets, each stem cut "
             "stress.stem_cut_mm out from the base and free (the non-load-carrying cruciform's test)")
_STEMMED = ("t-joint", "cruciform")  # the specimens whose fillet welds' sections are modelled

_FINEST_MM = 0.02  # the smallest element the toes get (a measured radius of 0.08 mm or under)


def _not_made(ctx, why: str) -> dict[str, Any]:
    STRESS_SUMMARY.write(ctx.out, StressSummary(made=False, why=why))
    HOT_SECTION.write(ctx.out, HotSection(points_mm=np.zeros((0, 2)), triangles=np.zeros((0, 3), np.int64),
                                          factor=np.zeros(0, np.float32), toe_mm=np.full(2, np.nan)))
    return {"made": False, "why": why}


def _toe_lines(geometry: WeldGeometry) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]:
    """(line, side) -> the measured toe's points (k, 3), specimen frame, in order along the line,
    and its measured radius at each (k,; NaN: not measured): each section's toe on its line's
    across direction from the section's centre (midway between its toes), as the weld stage's
    toes.zarr has them."""
    across = {line.name: np.asarray(line.across, np.float64) for line in geometry.lines}
    found: dict[tuple[str, str], list[tuple[float, np.ndarray, float]]] = {}
    for sec in geometry.sections:
        if not sec.toes.both():
            continue
        fillet = isinstance(sec, FilletWeldSection)
        mid = None if fillet else 0.5 * (sec.toes.minus.position_u_mm + sec.toes.plus.position_u_mm)
        for side, toe in sec.toes.sides():
            point = np.asarray(sec.toe_specimen_mm(side) if fillet else
                               np.asarray(sec.centre_specimen_mm) + (toe.position_u_mm - mid) * across[sec.line])
            radius = toe.toe_radius_mm.value
            found.setdefault((sec.line, side), []).append((sec.position_mm, point, math.nan if radius is None else radius))
    out = {}
    for key, rows in sorted(found.items()):
        if len(rows) >= 2:
            rows = sorted(rows, key=lambda r: r[0])
            out[key] = (np.array([r[1] for r in rows]), np.array([r[2] for r in rows], np.float64))
    return out


@dataclass(frozen=True)
class _Toe:
    """A measured toe where a section crosses it: its line and side, where in the section (x, y; mm),
    where in the specimen frame, its measured radius (NaN: not measured)."""

    line: str
    side: str
    xy: np.ndarray
    specimen: np.ndarray
    radius_mm: float


@dataclass(frozen=True)
class _Model:
    """One section to solve: the weld stage's section, its plane, the measured profile, the outline
    and the toes it crosses."""

    section: WeldSection | FilletWeldSection
    frame: SectionFrame
    profile: PlateProfile | TeeProfile
    plane: PlaneSection
    toes: list[_Toe]


def _crossing(polyline: np.ndarray, frame: SectionFrame) -> np.ndarray | None:
    """Where the polyline crosses the section's plane, in the points' frame; None: it does not.
    Each measured toe point stands for the toe half-way to its neighbours, so a plane past the
    line's first or last point by no more than half the step to the next meets that end point: a
    line's first section meets its own first toes whatever the sign of the rounding that puts them
    on its plane, and the other line's, which lie a few um before or after it as the registration
    has it (before 2026-11-29 a section met them only when they happened to lie after)."""
    s = (polyline - frame.origin) @ frame.along
    for k in np.flatnonzero(np.sign(s[:-1]) != np.sign(s[1:])):
        t = s[k] / (s[k] - s[k + 1])
        return polyline[k] + t * (polyline[k + 1] - polyline[k])
    hit = np.flatnonzero(s == 0)
    if len(hit):
        return polyline[hit[0]]
    if len(s) >= 2:
        for end, inner in ((0, 1), (-1, -2)):
            if abs(s[end]) <= 0.5 * abs(s[end] - s[inner]):
                return polyline[end]
    return None


def _load(bending: bool):
    """The load case's solve (``tasks.section_model``): the sections bent, or pulled."""
    return bend_sections if bending else pull_sections


def _load_sections(meshes: list[SectionMesh], s, bending: bool) -> list[SectionSolution]:
    """The sections pulled, or bent, in runs of ``s.max_nodes_per_solve`` nodes."""
    return _load(bending)(meshes, timeout_s=s.timeout_s, max_nodes_per_run=s.max_nodes_per_solve)


def _nominal_mpa(solution: SectionSolution, thickness_mm: float, bending: bool) -> float:
    """The nominal stress at a toe whose plate is ``thickness_mm`` thick: the force over it, or bent
    6 M / t^2 (the top face's); NaN where no plate was measured."""
    if not thickness_mm > 0:
        return math.nan
    return 6 * solution.moment_nmm / thickness_mm ** 2 if bending else solution.force_n / thickness_mm


def _plate_error(solution: SectionSolution, profile, x_from: float, x_to: float, bending: bool) -> float:
    """The stress through the plate window (a line through the thickness fitted to the nodes'
    sigma_xx within 1 mm of the window's middle) against the nominal one there, relative. Pulled:
    its mid-plane value against the force over the thickness. Bent: the larger of its surface
    value (slope times half the thickness) against 6 M / t^2 and its mid-plane value over that."""
    x_mid = 0.5 * (x_from + x_to)
    p = solution.mesh.points
    band = (np.abs(p[:, 0] - x_mid) < 1.0) & np.isfinite(solution.stress_mpa[:, 0])
    top, bottom = (float(np.interp(x_mid, profile.x_mm, f)) for f in (profile.top_mm, profile.bottom_mm))
    if band.sum() < 6 or not top > bottom:
        return float("nan")
    A = np.c_[np.ones(int(band.sum())), p[band, 1] - 0.5 * (top + bottom)]
    coef, *_ = np.linalg.lstsq(A, solution.stress_mpa[band, 0], rcond=None)
    if not bending:
        return float(coef[0] / (solution.force_n / (top - bottom)) - 1)
    surface = 6 * solution.moment_nmm / (top - bottom) ** 2
    return max(float(coef[1] * (top - bottom) / 2 / surface - 1), float(coef[0] / surface), key=abs)


def _to_specimen(frame: SectionFrame, xy) -> tuple[float, float, float]:
    x, y = float(xy[0]), float(xy[1])
    return tuple(round(float(v), 4) for v in frame.origin + x * frame.across + y * frame.up)


def stress(ctx) -> dict[str, Any]:
    s = ctx.settings
    geometry = WELD_GEOMETRY.read(ctx.inputs["weld"])
    if not geometry.measured:
        return _not_made(ctx, f"the weld was not measured ({geometry.why_not}): no toes to load")
    fillet = any(isinstance(sec, FilletWeldSection) for sec in geometry.sections)
    kind = getattr(ctx.manifest.specimen, "kind", None)
    if fillet and kind not in _STEMMED:
        return _not_made(ctx, f"fillet welds of a {kind}: only a T-joint's or a cruciform's sections (a stem on one or "
                              "both faces of the base plate) are modelled; the fillets' figures are in "
                              "weld_geometry.json")
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
    models: list[_Model] = []
    for sec in chosen:
        if fillet:  # the T-joint's (cruciform's) section through the fillets' roots here
            frame, profile = _tee(sec, geometry, points, normals, across, up, along, s)
        else:
            frame = SectionFrame(np.asarray(sec.centre_specimen_mm, np.float64), across, up, along)
            profile = plate_profile(points, normals, frame, half_width_mm=s.half_width_mm, bin_mm=s.bin_mm,
                                    smooth_mm=s.smooth_mm)
        if profile is None:
            continue
        crossing = []
        for (line, side), (polyline, radii) in toes.items():
            hit = _crossing(polyline, frame)
            if hit is not None:
                rel = hit - frame.origin
                radius = radii[int(np.argmin(np.linalg.norm(polyline - hit, axis=1)))]
                crossing.append(_Toe(line, side, np.array([rel @ across, rel @ up]), hit, float(radius)))
        if not crossing:
            continue
        try:
            plane = (tee_section if fillet else profile_section)(profile, cut_mm=s.cut_mm,
                                                                 fine_mm=np.array([c.xy for c in crossing]))
        except ValueError:
            continue
        # elements at the toes a quarter of the sharpest measured radius or finer (IIW), not under 0.02 mm
        radii = [c.radius_mm for c in crossing if math.isfinite(c.radius_mm)]
        if radii and min(radii) / 4 < s.toe_size_mm:
            plane = replace(plane, fine_size_mm=max(min(radii) / 4, _FINEST_MM))
        models.append(_Model(sec, frame, profile, plane, crossing))
    if not models:
        return _not_made(ctx, "no section of the weld has both faces measured across it")
    bending = ctx.manifest.load is not None and ctx.manifest.load.kind == "bending"
    try:
        meshes = mesh_sections([m.plane for m in models], settings, timeout_s=s.timeout_s)
        # a section CalculiX refuses is left out, and said, instead of failing the others with it
        solved = each_solved(_load(bending), meshes, timeout_s=s.timeout_s,
                             max_nodes_per_run=s.max_nodes_per_solve)
        refused = [RefusedSection(position_mm=m.section.position_mm, why=str(x))
                   for m, x in zip(models, solved) if isinstance(x, FESolveError)]
        models = [m for m, x in zip(models, solved) if not isinstance(x, FESolveError)]
        solutions = [x for x in solved if not isinstance(x, FESolveError)]
        if not models:
            return _not_made(ctx, f"CalculiX refused every section: {refused[0].why}")
        notch_peaks = _notch_peaks(models, s, bending) if s.notch_stress else None
    except (SectionMeshError, FESolveError, CalculixNotFound) as exc:
        return _not_made(ctx, str(exc))
    spacing = _point_spacing(points, [m.frame for m in models], s.half_width_mm)
    sections, factors, notch_factors = [], {}, {}
    near, far = s.plate_window_mm
    for index, (model, solution) in enumerate(zip(models, solutions)):
        sec, frame = model.section, model.frame
        profile = model.profile.plate if isinstance(model.profile, TeeProfile) else model.profile
        peaks = peaks_near(solution, np.array([c.xy for c in model.toes]), s.peak_reach_mm)
        toe_rows, errors = [], []
        for j, (toe, (peak, at)) in enumerate(zip(model.toes, peaks)):
            sign = -1.0 if toe.xy[0] < 0 else 1.0  # the toe's plate: the window on its side of the weld's centre
            window = (sign * near, sign * far)
            thickness = profile.thickness_mm(*window)
            nominal = _nominal_mpa(solution, thickness, bending)
            errors.append(_plate_error(solution, profile, *window, bending))
            factor = peak / nominal if math.isfinite(peak) and math.isfinite(nominal) else None
            notch = None
            if notch_peaks is not None:
                peaks_rounded, notch_solution = notch_peaks[index]
                notch_peak, notch_at = peaks_rounded[j]
                notch_nominal = _nominal_mpa(notch_solution, thickness, bending)
                if math.isfinite(notch_peak) and math.isfinite(notch_nominal):
                    notch = notch_peak / notch_nominal
                    notch_factors.setdefault((toe.line, toe.side), []).append(
                        (sec.position_mm, notch, _to_specimen(frame, notch_at)))
            toe_rows.append(ToeStress(line=toe.line, side=toe.side, factor=None if factor is None else round(factor, 4),
                                      peak_mpa=None if factor is None else round(peak, 3),
                                      nominal_mpa=round(nominal, 4) if math.isfinite(nominal) else None,
                                      plate_thickness_mm=round(thickness, 4) if math.isfinite(thickness) else None,
                                      toe_specimen_mm=tuple(round(float(v), 4) for v in toe.specimen),
                                      peak_specimen_mm=None if factor is None else _to_specimen(frame, at),
                                      toe_radius_mm=round(toe.radius_mm, 4) if math.isfinite(toe.radius_mm) else None,
                                      notch_factor=None if notch is None else round(notch, 4)))
            if factor is not None:
                factors.setdefault((toe.line, toe.side), []).append((sec.position_mm, factor, _to_specimen(frame, at)))
        finite = [e for e in errors if math.isfinite(e)]
        sections.append(StressSection(
            position_mm=sec.position_mm, origin_specimen_mm=tuple(round(float(v), 4) for v in frame.origin),
            nodes=len(solution.mesh.points), elements=len(solution.mesh.triangles),
            force_n_per_mm=round(solution.force_n, 4), imbalance=round(solution.imbalance, 8),
            membrane_error=round(max(finite, key=abs), 6) if finite else None, toes=toe_rows))
    hot_spots = _hot_spots(factors)
    notch_hot_spots = _hot_spots(notch_factors)
    hot = max(hot_spots, key=lambda h: h.factor) if hot_spots else None
    convergence, convergence_refused = None, None
    if hot is None:
        HOT_SECTION.write(ctx.out, HotSection(points_mm=np.zeros((0, 2)), triangles=np.zeros((0, 3), np.int64),
                                              factor=np.zeros(0, np.float32), toe_mm=np.full(2, np.nan)))
    else:
        k = next(i for i, m in enumerate(models) if m.section.position_mm == hot.position_mm)
        model = models[k]
        j = next(i for i, c in enumerate(model.toes) if (c.line, c.side) == (hot.line, hot.side))
        toe = sections[k].toes[j]
        hot_solution = solutions[k]
        HOT_SECTION.write(ctx.out, HotSection(
            points_mm=hot_solution.mesh.points, triangles=hot_solution.mesh.triangles[:, :3].astype(np.int64),
            factor=(hot_solution.max_principal_mpa / toe.nominal_mpa).astype(np.float32), toe_mm=model.toes[j].xy))
        half = (model.plane.fine_size_mm or s.toe_size_mm) / 2
        try:
            (solution,) = _load_sections(mesh_sections([replace(model.plane, fine_size_mm=half)], settings,
                                                       timeout_s=s.timeout_s), s, bending)
            (peak, _), = peaks_near(solution, model.toes[j].xy[None], s.peak_reach_mm)
            finer_factor = peak / _nominal_mpa(solution, toe.plate_thickness_mm, bending)
            convergence = StressConvergence(position_mm=hot.position_mm, line=hot.line, side=hot.side,
                                            toe_size_mm=round(half, 5), factor=hot.factor,
                                            finer_factor=round(finer_factor, 4),
                                            change=round(finer_factor / hot.factor - 1, 5))
        except (SectionMeshError, FESolveError) as exc:
            # the stress stands on the sections solved; only its convergence is not known, and said
            convergence_refused = f"the hot spot's section with elements of {half:g} mm at the toe: {exc}"
    drawn = (_drawn_tee if fillet else _drawn)(ctx.manifest, geometry, up, across, s, bending)
    fatigue, basis = _fatigue(ctx.manifest, notch_hot_spots, s)
    write_section_vtu(ctx.out / STRESS_VTU.name, [(m.frame.origin, m.frame.across, m.frame.up) for m in models],
                      solutions)
    imbalance = max(x.imbalance for x in sections)
    membrane = [x.membrane_error for x in sections if x.membrane_error is not None]
    radii = [t.toe_radius_mm for x in sections for t in x.toes if t.toe_radius_mm is not None]
    summary = StressSummary(
        made=True, model=(MODEL_BENDING if bending else MODEL) + ((CRUCIFORM if kind == "cruciform" else TEE) if fillet
                                                                  else ""), driving_line=driving.name,
        sections=sections, sections_refused=refused,
        hot_spots=hot_spots, hot_spot=hot,
        convergence=convergence, convergence_refused=convergence_refused, max_imbalance=imbalance,
        max_membrane_error=max(membrane, key=abs) if membrane else None,
        notch_radius_mm=s.notch_radius_mm if s.notch_stress else None, notch_hot_spots=notch_hot_spots,
        fatigue=fatigue, fatigue_basis=basis, drawn=drawn,
        point_spacing_mm=None if spacing is None else round(spacing, 4),
        toes_finer_than_points=None if spacing is None else sum(r < spacing for r in radii))
    STRESS_SUMMARY.write(ctx.out, summary)
    return {"made": True, "sections": len(sections), **({"sections_refused": len(refused)} if refused else {}),
            **({"convergence_refused": True} if convergence_refused else {}),
            "hot_spot_factor": None if hot is None else hot.factor,
            "hot_spot": None if hot is None else f"{hot.line} {hot.side} at {hot.position_mm:g} mm",
            "max_imbalance": imbalance,
            "notch_hot_spot_factor": max((h.factor for h in notch_hot_spots), default=None)}


def _tee(sec: FilletWeldSection, geometry: WeldGeometry, points: np.ndarray, normals: np.ndarray, across: np.ndarray,
         up: np.ndarray, along: np.ndarray, s) -> tuple[SectionFrame, TeeProfile | None]:
    """A T-joint's section at ``sec`` (a fillet's section with both toes): its frame, centred between
    the two fillets' roots there, and its outline (``tasks.plate_section.tee_profile``); None when
    the other fillet has no section with both toes within half a step of it. A cruciform's (weld
    lines on the base's other face too, their ``face_normal`` against ``up``): the lower stem's
    roots from its two fillets' sections nearest, within half a step, as well."""
    upper = {line.name for line in geometry.lines if np.dot(line.face_normal, up) > 0}
    partner = min((o for o in geometry.sections if o.line != sec.line and o.line in upper and o.toes.both()),
                  key=lambda o: abs(o.position_mm - sec.position_mm), default=None)
    mine = np.asarray(sec.centre_specimen_mm, np.float64)
    if partner is None or abs(partner.position_mm - sec.position_mm) > s.section_step_mm / 2:
        return SectionFrame(mine, across, up, along), None
    theirs = np.asarray(partner.centre_specimen_mm, np.float64)
    theirs = theirs - ((theirs - mine) @ along) * along  # the other root, in this section's plane
    frame = SectionFrame(0.5 * (mine + theirs), across, up, along)

    def in_section(found: list[np.ndarray]) -> dict[int, np.ndarray]:
        roots = {}
        for root in found:
            rel = root - frame.origin
            roots[1 if rel @ across > 0 else -1] = np.array([rel @ across, rel @ up])
        return roots

    roots = in_section([mine, theirs])
    if len(roots) != 2:
        return frame, None
    roots_below = None
    lower = [line.name for line in geometry.lines if line.name not in upper]
    if lower:
        found = []
        for name in lower:
            near = min((o for o in geometry.sections if o.line == name and o.toes.both()),
                       key=lambda o: abs(o.position_mm - sec.position_mm), default=None)
            if near is None or abs(near.position_mm - sec.position_mm) > s.section_step_mm / 2:
                return frame, None
            root = np.asarray(near.centre_specimen_mm, np.float64)
            found.append(root - ((root - mine) @ along) * along)
        roots_below = in_section(found)
        if len(roots_below) != 2:
            return frame, None
    return frame, tee_profile(points, normals, frame, roots_mm=roots, stem_cut_mm=s.stem_cut_mm,
                              half_width_mm=s.half_width_mm, bin_mm=s.bin_mm, smooth_mm=s.smooth_mm,
                              roots_below_mm=roots_below)


def _hot_spots(factors: dict[tuple[str, str], list[tuple[float, float, tuple]]]) -> list[ToeHotSpot]:
    """Each toe line's highest section (the first of equals) and its median."""
    out = []
    for (line, side), rows in sorted(factors.items()):
        position, factor, at = max(rows, key=lambda r: r[1])
        out.append(ToeHotSpot(line=line, side=side, position_mm=position, factor=round(factor, 4), at_specimen_mm=at,
                              sections=len(rows), median_factor=round(float(np.median([r[1] for r in rows])), 4)))
    return out


def notch_mesh(s) -> tuple[SectionMeshSettings, float]:
    """How a section rounded to ``s.notch_radius_mm`` is meshed and read (the stage's notch
    sections, its drawn weld, bench/stress_truth.py's true ones): elements at the toes a quarter of
    the radius or finer (IIW) over a radius at least, and how far from the measured toe its peak
    is looked for (the rounded toe's arc may start up to a radius from it)."""
    settings = SectionMeshSettings(fine_size_mm=min(s.toe_size_mm, s.notch_radius_mm / 4),
                                   fine_reach_mm=max(s.toe_zone_mm, s.notch_radius_mm), size_mm=s.size_mm,
                                   growth=s.growth)
    return settings, max(s.peak_reach_mm, 1.5 * s.notch_radius_mm)


def _notch_peaks(models: list[_Model], s,
                 bending: bool) -> list[tuple[list[tuple[float, np.ndarray]], SectionSolution]]:
    """Per model: each toe's (peak, where) with the section's notches rounded to
    ``s.notch_radius_mm`` (``tasks.plate_section.rounded_notches``, meshed as ``notch_mesh``), and
    its solution (loaded as the measured sections are)."""
    planes = [tee_section(rounded_tee(m.profile, s.notch_radius_mm), cut_mm=s.cut_mm,
                          fine_mm=np.array([c.xy for c in m.toes])) if isinstance(m.profile, TeeProfile) else
              profile_section(rounded_notches(m.profile, s.notch_radius_mm), cut_mm=s.cut_mm,
                              fine_mm=np.array([c.xy for c in m.toes])) for m in models]
    settings, reach = notch_mesh(s)
    solutions = _load_sections(mesh_sections(planes, settings, timeout_s=s.timeout_s), s, bending)
    return [(peaks_near(sol, np.array([c.xy for c in m.toes]), reach), sol) for m, sol in zip(models, solutions)]


def _point_spacing(points: np.ndarray, frames: list[SectionFrame], half_width_mm: float) -> float | None:
    """The measured points' median spacing (to the nearest other point) in the sections' slabs
    (a margin of a millimetre either side kept, so that a slab's edge does not lengthen it)."""
    slabs = [np.flatnonzero(np.abs((points - f.origin) @ f.along) <= half_width_mm + 1.0) for f in frames]
    inside = distinct(np.concatenate(slabs)) if slabs else np.zeros(0, np.int64)
    if len(inside) < 10:
        return None
    mine = distinct(np.concatenate([k[np.abs((points[k] - f.origin) @ f.along) <= half_width_mm]
                                     for k, f in zip(slabs, frames)]))
    mine = mine[:: max(1, len(mine) // 20000)]
    distance, _ = cKDTree(points[inside]).query(points[mine], k=2)
    return float(np.median(distance[:, 1]))


def _drawn(manifest, geometry: WeldGeometry, up: np.ndarray, across: np.ndarray, s, bending: bool) -> DrawnStress:
    """The drawn weld's section (``tasks.plate_section.drawn_profile``): the manifest's plate
    thickness, each weld line's cap the median width and height measured along it, its toes
    rounded to ``s.notch_radius_mm``; pulled or bent as the measured sections are."""
    thickness = getattr(manifest.specimen, "thickness_mm", None)
    if thickness is None:
        return DrawnStress(made=False, why=f"the manifest's {manifest.specimen.kind if manifest.specimen else 'sample'} "
                                           "states no plate thickness")
    caps, toes = {}, []
    for line in geometry.lines:
        rows = [sec for sec in geometry.sections if sec.line == line.name]
        width = np.median([v for sec in rows if (v := sec.reinforcement_width_mm.value) is not None] or [np.nan])
        height = np.median([v for sec in rows if (v := sec.reinforcement_height_mm.value) is not None] or [np.nan])
        if not (width > 0 and height > 0):
            continue
        face = "top" if np.dot(line.face_normal, up) > 0 else "bottom"
        caps[face] = (round(float(width), 4), round(float(height), 4))
        turn = 1.0 if np.dot(line.across, across) > 0 else -1.0  # the line's minus side in the section's x
        for side, sign in (("minus", -1.0), ("plus", 1.0)):
            toes.append((line.name, side, np.array([sign * turn * width / 2,
                                                    (1 if face == "top" else -1) * thickness / 2])))
    if not caps:
        return DrawnStress(made=False, why="no weld line has its cap's width and height measured")
    near, far = s.plate_window_mm
    half = max(far, max(w for w, _ in caps.values()) / 2 + 2 * s.notch_radius_mm) + 5.0
    profile = rounded_notches(drawn_profile(thickness_mm=thickness, caps=caps, half_length_mm=half, bin_mm=s.bin_mm / 2),
                              s.notch_radius_mm)
    plane = profile_section(profile, cut_mm=0.0, fine_mm=np.array([t[2] for t in toes]))
    settings, reach = notch_mesh(s)
    try:
        (solution,) = _load_sections(mesh_sections([plane], settings, timeout_s=s.timeout_s), s, bending)
    except (SectionMeshError, FESolveError, CalculixNotFound) as exc:
        return DrawnStress(made=False, why=f"the drawn weld's section did not solve: {exc}")
    nominal = _nominal_mpa(solution, thickness, bending)
    peaks = peaks_near(solution, np.array([t[2] for t in toes]), reach)
    return DrawnStress(made=True, thickness_mm=float(thickness), notch_radius_mm=s.notch_radius_mm, caps=caps, toes=[
        DrawnToe(line=line, side=side, factor=round(peak / nominal, 4) if math.isfinite(peak) else None,
                 at_section_mm=(round(float(xy[0]), 4), round(float(xy[1]), 4)))
        for (line, side, xy), (peak, _) in zip(toes, peaks)])


def _drawn_tee(manifest, geometry: WeldGeometry, up: np.ndarray, across: np.ndarray, s, bending: bool) -> DrawnStress:
    """A T-joint's drawn section (``tasks.plate_section.drawn_tee_section``): the manifest's base
    and stem, each fillet's face straight between the median legs measured along its line, the
    toes rounded to ``s.notch_radius_mm``; pulled or bent as the measured sections are. A
    cruciform's: its lower stem and fillets too (the lines on the base's other face)."""
    specimen = manifest.specimen
    cruciform = specimen.kind == "cruciform"
    legs, names = {1: {}, -1: {}}, {1: {}, -1: {}}  # by face (+1: up's), then side
    for line in geometry.lines:
        rows = [sec for sec in geometry.sections if sec.line == line.name]
        base = np.median([v for sec in rows if (v := sec.leg_base_mm.value) is not None] or [np.nan])
        stem = np.median([v for sec in rows if (v := sec.leg_stem_mm.value) is not None] or [np.nan])
        if base > 0 and stem > 0:
            side = 1 if np.dot(line.across, across) > 0 else -1
            face = 1 if np.dot(line.face_normal, up) > 0 else -1
            legs[face][side], names[face][side] = (round(float(base), 4), round(float(stem), 4)), line.name
    if set(legs[1]) != {-1, 1} or (cruciform and set(legs[-1]) != {-1, 1}):
        return DrawnStress(made=False, why="the drawn cruciform needs its four fillets' legs measured" if cruciform
                           else "the drawn T-joint needs both fillets' legs measured")
    every = [v[0] for face in legs.values() for v in face.values()]
    half = max(s.plate_window_mm[1], specimen.stem_thickness_mm / 2 + max(every)) + 10.0
    plane = drawn_tee_section(base_thickness_mm=specimen.base_thickness_mm, stem_thickness_mm=specimen.stem_thickness_mm,
                              legs=legs[1], half_length_mm=half, stem_cut_mm=s.stem_cut_mm, radius_mm=s.notch_radius_mm,
                              step_mm=s.bin_mm / 2, legs_below=legs[-1] if cruciform else None)
    settings, reach = notch_mesh(s)
    try:
        (solution,) = _load_sections(mesh_sections([plane], settings, timeout_s=s.timeout_s), s, bending)
    except (SectionMeshError, FESolveError, CalculixNotFound) as exc:
        return DrawnStress(made=False, why=f"the drawn T-joint's section did not solve: {exc}")
    nominal = _nominal_mpa(solution, specimen.base_thickness_mm, bending)
    peaks = peaks_near(solution, plane.fine_mm, reach)
    # drawn_tee_section's toes: each face's base +1, base -1, stem +1, stem -1
    where = [(names[face][side], plate) for face in ((1, -1) if cruciform else (1,)) for plate in ("base", "stem")
             for side in (1, -1)]
    return DrawnStress(made=True, thickness_mm=float(specimen.base_thickness_mm), notch_radius_mm=s.notch_radius_mm,
                       legs={names[face][side]: legs[face][side] for face in ((1, -1) if cruciform else (1,))
                             for side in (-1, 1)}, toes=[
        DrawnToe(line=line, side=side, factor=round(peak / nominal, 4) if math.isfinite(peak) else None,
                 at_section_mm=(round(float(xy[0]), 4), round(float(xy[1]), 4)))
        for (line, side), (peak, _), xy in zip(where, peaks, plane.fine_mm)])


def _fatigue(manifest, notch_hot_spots: list[ToeHotSpot], s) -> tuple[list[FatigueEstimate], str]:
    """Each toe line's fatigue life at its notch hot spot, and the basis in words (or why none)."""
    if not s.notch_stress:
        return [], "no estimate: the notch stress is off (stress.notch_stress)"
    load = manifest.load
    if load is None or load.nominal_stress_range_mpa is None:
        return [], "no estimate: the manifest gives no load range (load.nominal_stress_range_mpa)"
    basis = (f"IIW effective notch stress: the notches rounded to r = {s.notch_radius_mm:g} mm, maximum principal "
             f"stress, FAT {s.fat_mpa:g} MPa at 2e6 cycles, slope {s.fat_slope:g} to 1e7 cycles and 22 beyond, "
             f"97.7 % survival; nominal stress range {load.nominal_stress_range_mpa:g} MPa (the manifest's load), "
             "linear elastic, as welded (no credit for HFMI unless fat_mpa says so), no thickness or mean stress "
             "correction")
    out = []
    for h in notch_hot_spots:
        notch_range = h.factor * load.nominal_stress_range_mpa
        out.append(FatigueEstimate(line=h.line, side=h.side, position_mm=h.position_mm, notch_factor=h.factor,
                                   nominal_range_mpa=load.nominal_stress_range_mpa,
                                   notch_range_mpa=round(notch_range, 3), fat_mpa=s.fat_mpa, slope=s.fat_slope,
                                   cycles=float(f"{notch_cycles(notch_range, s.fat_mpa, s.fat_slope):.4g}")))
    return out, basis
