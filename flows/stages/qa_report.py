"""Stage ``qa_report``: the sample's QA report, one self-contained HTML file (``report.html``) that
opens offline: every picture is inside it (PNG, base64), no script, no link out.

What it shows, in the order a person checks a sample: the verdicts (checks, weld, FE model); the
scan plan over the passes' coverage of each face; each pass's intensity image with the stickers
found on it; the registration graph with its residuals; how far overlapping passes disagree, as a
colour map on the faces; renderings of the mesh, the weld zone coloured; the weld's cross-sections
measured over the drawing's plates and its figures along the weld with the acceptance limits; the
FE model's element quality; the provenance (settings, inputs, code, every stage's key).

The file is a function of the stages' outputs and records (same inputs, same bytes). The audit
trail's state belongs to the moment of publication, not to the stage: the stage leaves a marked
place (``AUDIT_MARK``) that ``flows.stages.report.publish`` fills with the trail's verification.
"""

from __future__ import annotations

import base64
import importlib.metadata
import json
import math
from collections import Counter
from typing import Any

import numpy as np
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

from flows.stages.contracts import zarr_array
from flows.stages.qa_audit import AUDIT_MARK
from flows.stages.outputs import (CLOUD, ELEMENT_QUALITY, MESH, QA_REPORT, REFINE_SUMMARY, REFINED, REGISTRATION,
                                  REGISTRATION_SUMMARY, REPORT, SPECIMEN, TARGETS, VOLUME_SUMMARY, WELD_GEOMETRY)
from flows.stages.placement import model_weld_zone, weld_frame, weld_lines_common
from schemas.acceptance import AcceptanceRule
from schemas.manifest import SampleManifest
from schemas.weld_document import TOE_SIDES, Figure, Finding, WeldGeometry, WeldSection
from tasks.frames import apply, invert, rotate
from tasks.weld_zone import WeldZone
from tasks.coverage import FaceAccumulator
from tasks.mesh import simplify_surface
from tasks.report_figures import (AlongWeldSeries, ViewedFace, along_weld, face_map, histogram, intensity_image,
                                  mesh_view, registration_graph, weld_section)

__all__ = ["qa_report", "qa_report_view"]

_ENV = Environment(loader=PackageLoader("flows", "templates"), autoescape=select_autoescape(["html", "j2"]),
                   undefined=StrictUndefined, keep_trailing_newline=True, trim_blocks=True, lstrip_blocks=True)


def qa_report_view(manifest: SampleManifest, entry=None) -> dict[str, Any]:
    """What the report reads of the manifest: the passes by setup, the part, the weld, the stickers."""
    return {"sample_id": manifest.sample_id, "passes": [[s, e.pass_id] for s, e in manifest.passes()],
            "specimen": manifest.specimen.model_dump(mode="json") if manifest.specimen is not None else None,
            "weld": None if manifest.weld is None else manifest.weld.model_dump(mode="json"),
            "weld_lines_mm": [[list(p) for p in line.points_mm] for line in manifest.weld_lines()],
            "setups": [{"name": s.name, "first_pass": s.passes[0].pass_id,
                        "T_world_specimen_nominal": s.T_world_specimen_nominal} for s in manifest.setups],
            "sticker_diameter_mm": manifest.sticker_diameter_mm}


def _uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _picture(png: bytes, alt: str, caption: str = "") -> dict[str, str]:
    return {"src": _uri(png), "alt": alt, "caption": caption}


def _view_frame(manifest: SampleManifest, T_common_pass: np.ndarray, specimen_points: np.ndarray) -> tuple[np.ndarray, str]:
    """common frame -> the frame the maps are drawn in: the specimen's (its nominal placement
    through the first placed setup's pose) or, for parts placed nowhere, the points' principal axes
    (z the least spread, signs fixed by the third moments)."""
    frame = weld_frame(manifest, T_common_pass)
    if frame is not None:
        return invert(frame), "the specimen frame (the drawing's)"
    centre = specimen_points.mean(axis=0)
    d = specimen_points - centre
    _, vectors = np.linalg.eigh(d.T @ d)
    axes = vectors[:, ::-1].T.copy()  # largest spread first: x, y, z
    for k in range(3):
        if np.mean((d @ axes[k]) ** 3) < 0:
            axes[k] = -axes[k]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    T = np.eye(4)
    T[:3, :3] = axes
    T[:3, 3] = -axes @ centre
    return T, "the points' principal axes (no nominal placement)"


def _steps(manifest: SampleManifest, entry, shape: tuple[int, ...], cell_mm: float, points_per_pass: int) -> tuple[int, ...]:
    """How a pass is thinned for the maps: a grid pass every k-th profile and column, k as large as
    keeps its points at most a third of a cell apart (about nine to a cell, enough for a cell's
    mean); an imported scan (n, 3) evenly to ``points_per_pass``."""
    if len(shape) == 3 and manifest.scanner is not None:
        pitches = manifest.grid_pitch_mm(entry)
        return tuple(max(1, int(cell_mm / (3 * p))) for p in pitches)
    return (max(1, shape[0] // points_per_pass),)


def _maps(ctx, T_view_common: np.ndarray, T_common_pass: np.ndarray, surface: np.ndarray, surface_normals: np.ndarray,
          lines_view: list[np.ndarray]) -> tuple[list[dict[str, str]], dict[str, Any]]:
    """The scan plan over the coverage, and the passes' disagreement, on the part's two faces."""
    s = ctx.settings
    lo = surface[:, :2].min(axis=0) - 2 * s.cell_mm
    hi = surface[:, :2].max(axis=0) + 2 * s.cell_mm
    faces = FaceAccumulator(surface, surface_normals, lo_mm=tuple(lo), hi_mm=tuple(hi), cell_mm=s.cell_mm)
    paths: dict[str, list[tuple[str, np.ndarray]]] = {"top": [], "bottom": []}
    entries = [e for _, e in ctx.manifest.passes()]
    for k, (name, ref) in enumerate(zip(ctx.names, ctx.inputs["denoise"])):
        stored_points, stored_normals = zarr_array(ref, CLOUD, "points"), zarr_array(ref, CLOUD, "normals")
        T = T_view_common @ T_common_pass[k]
        step = tuple(slice(None, None, n) for n in _steps(ctx.manifest, entries[k], stored_points.shape, s.cell_mm,
                                                          s.points_per_pass))
        points, normals = stored_points[step], stored_normals[step]
        points = apply(T, np.asarray(points, np.float64).reshape(-1, 3))
        normals = np.asarray(normals, np.float64).reshape(-1, 3) @ T[:3, :3].T
        faces.add(points, normals)
        origins = np.asarray(zarr_array(ref, CLOUD, "sensor_origins")[...], np.float64)
        if len(origins) >= 2 and np.isfinite(origins[[0, -1]]).all():
            ends = apply(T, origins[[0, -1]])
            face = "top" if np.nanmean(normals[:, 2]) >= 0 else "bottom"  # normals face the sensor
            paths[face].append((name, ends[:, :2]))
    grids = faces.faces()
    coverage = [ViewedFace(f"{g.name} face: passes that measured each {s.cell_mm:g} mm cell",
                           np.where(g.passes > 0, g.passes, np.nan).astype(float), g.origin_mm, g.cell_mm) for g in grids]
    spread = [ViewedFace(f"{g.name} face", g.spread_mm * 1000, g.origin_mm, g.cell_mm) for g in grids]
    most = max(int(max(g.passes.max() for g in grids)), 1)
    pictures = [_picture(face_map(coverage, title="Scan plan and coverage", unit="passes", cmap="viridis", discrete=True, vmax=most,
                                  paths=[paths[g.name] for g in grids], lines=lines_view),
                         "scan plan and coverage", "Arrows: each pass's sweep, start to end, over the number of passes that "
                         "measured each cell; dashed: the weld lines.")]
    values = np.concatenate([g.spread_mm[np.isfinite(g.spread_mm)] for g in grids])
    top = float(np.percentile(values, 99) * 1000) if len(values) else 1.0
    pictures.append(_picture(face_map(spread, title="Disagreement of overlapping passes", unit="um", cmap="magma",
                                      vmax=max(top, 1.0), lines=lines_view),
                             "disagreement of overlapping passes", "Where two or more passes measured a cell: the largest minus the "
                             "smallest of their mean distances to the merged surface (colour scale to the 99th percentile)."))
    figures = {"cells_seen": int(sum((g.passes > 0).sum() for g in grids)),
               "cells_two_or_more": int(sum((g.passes >= 2).sum() for g in grids)),
               "disagreement_median_um": round(float(np.median(values)) * 1000, 1) if len(values) else None,
               "disagreement_p95_um": round(float(np.percentile(values, 95)) * 1000, 1) if len(values) else None,
               "disagreement_max_um": round(float(values.max()) * 1000, 1) if len(values) else None}
    return pictures, figures


def _pass_images(ctx) -> list[dict[str, str]]:
    """Each pass's searched intensity image with the stickers found on it."""
    out = []
    radius = (ctx.manifest.sticker_diameter_mm or 0) / 2
    for name, ref in zip(ctx.names, ctx.inputs["targets"]):
        found = TARGETS.read(ref)
        if found.preview.size == 0:
            continue
        row_mm, col_mm = (float(v) for v in found.grid_spacing_mm)
        profiles, columns = (int(v) for v in found.grid_shape)
        extent = (0.0, columns * col_mm, 0.0, profiles * row_mm)
        stickers = np.c_[(found.pixel[:, 1] + 0.5) * col_mm, (found.pixel[:, 0] + 0.5) * row_mm]
        median_rms = f", rim fit RMS median {np.median(found.rms_mm) * 1000:.0f} um" if len(found.rms_mm) else ""
        out.append(_picture(intensity_image(found.preview, extent_mm=extent, title=f"{name}: {len(found.pixel)} stickers",
                                            stickers_mm=stickers, radius_mm=radius),
                            f"pass {name} intensity", f"{name}: {len(found.pixel)} stickers{median_rms}"))
    return out


def _graph(ctx) -> tuple[list[dict[str, str]], list[dict[str, Any]]]:
    """The registration graph: pass pairs by their common targets' residuals; per-pass rows."""
    reg = REGISTRATION.open(ctx.inputs["registration"])
    summary = REGISTRATION_SUMMARY.read(ctx.inputs["registration"])
    refine = REFINE_SUMMARY.read(ctx.inputs["refine"])
    pairs = np.asarray(reg.edge_passes[...], np.int64).reshape(-1, 2)
    residual = np.asarray(reg.residual_mm[...], np.float64)
    inlier = np.asarray(reg.inlier[...], bool)
    edges = []
    for a, b in sorted({(int(min(p)), int(max(p))) for p in pairs[inlier]}):
        sel = inlier & (pairs.min(axis=1) == a) & (pairs.max(axis=1) == b)
        edges.append((a, b, int(sel.sum()), float(np.median(residual[sel]))))
    index = {n: k for k, n in enumerate(ctx.names)}
    surface = [(index[p.a], index[p.b], float(p.rms_mm if p.rms_mm is not None else math.nan))
               for p in refine.surface_pairs if p.a in index and p.b in index]
    groups = [setup for setup, _ in ctx.manifest.passes()]
    picture = _picture(registration_graph(ctx.names, groups, edges, surface,
                                          title="Registration graph: pass pairs joined by common stickers"),
                       "registration graph", "Passes around the circle in scan order, coloured by setup; a line per "
                       "pass pair with common stickers, coloured by their median residual after the solve, wider for "
                       "more stickers; grey: surface overlaps the refinement used.")
    degree = {n: 0 for n in ctx.names}
    for a, b, *_ in edges:
        degree[ctx.names[a]] += 1
        degree[ctx.names[b]] += 1
    rows = [{"pass": n, "setup": g, "pairs": degree[n],
             "rms_um": None if summary.pass_rms_mm.get(n) is None else round(summary.pass_rms_mm[n] * 1000, 1)}
            for n, g in zip(ctx.names, groups)]
    return ([picture] if edges or surface else []), rows


def _mesh_pictures(ctx, T_view_common: np.ndarray, zone: WeldZone) -> list[dict[str, str]]:
    mesh = MESH.read(ctx.inputs["mesh"])
    vertices, triangles = simplify_surface(mesh.vertices, mesh.triangles, max_triangles=ctx.settings.mesh_triangles)
    near = zone.faces_in(vertices, triangles)  # as the FE model's WELD_ZONE_SURFACE is chosen
    v = apply(T_view_common, vertices)
    radius = zone.zones[0].radius_mm if zone else 0.0
    caption = (f"The Poisson mesh ({len(mesh.triangles):,} triangles) simplified to {len(triangles):,} for the picture; "
               f"orange: the weld zone ({radius:g} mm of the weld lines, the FE model's WELD_ZONE_SURFACE).")
    lines_view = [apply(T_view_common, np.asarray(z.points_mm, np.float64)) for z in zone.zones]
    out = [_picture(mesh_view(v, triangles, azimuth_deg=-60, elevation_deg=35, title="The mesh from above",
                              highlight=near), "mesh from above", caption),
           _picture(mesh_view(v, triangles, azimuth_deg=120, elevation_deg=-35, title="The mesh from below",
                              highlight=near), "mesh from below", caption)]
    corners = v[triangles]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    up = normal[:, 2] > 0.5 * np.linalg.norm(normal, axis=1)
    keep = near & up & (corners[:, :, 2].mean(axis=1) > np.median(v[:, 2]))  # the upper face's weld
    if keep.sum() > 10 and lines_view:
        used = np.unique(triangles[keep])
        remap = np.full(len(v), -1, np.int64)
        remap[used] = np.arange(len(used))
        d = lines_view[0][-1] - lines_view[0][0]
        along = math.degrees(math.atan2(d[1], d[0]))
        out.append(_picture(mesh_view(v[used], remap[triangles[keep]], azimuth_deg=along + 200, elevation_deg=22,
                                      title="The weld zone, close up", highlight=np.ones(int(keep.sum()), bool),
                                      height_in=3.0), "mesh weld zone",
                            "The upward faces of the weld zone alone, seen low and nearly along the weld."))
    return out


_TOE_FIGURES = (("toe_radius_mm", "toe radius", "mm"), ("flank_angle_deg", "flank angle", "deg"),
                ("undercut_depth_mm", "undercut", "mm"), ("groove_depth_mm", "groove depth", "mm"),
                ("groove_width_mm", "groove width", "mm"))
_SECTION_FIGURES = (("reinforcement_height_mm", "height", "mm"),
                    ("reinforcement_width_mm", "width", "mm"),
                    ("axial_misalignment_mm", "axial misal.", "mm"),
                    ("angular_misalignment_deg", "angular misal.", "deg"))


def _value(m: Figure | None) -> tuple[float, float]:
    if m is None or m.value is None:
        return math.nan, math.nan
    return float(m.value), math.nan if m.sigma is None else float(m.sigma)


def _limits(rule: AcceptanceRule | None, figure: str) -> tuple[float | None, float | None]:
    limits = None if rule is None else getattr(rule, figure)
    return (None, None) if limits is None else (limits.min, limits.max)


def _curve(rows: list[tuple[float, float, float, bool]]):
    arr = np.array(rows, dtype=object)
    return arr[:, 0].astype(float), arr[:, 1].astype(float), arr[:, 2].astype(float), arr[:, 3].astype(bool)


def _along_weld(geometry: WeldGeometry) -> list[dict[str, str]]:
    sections = geometry.sections
    failing = {(f.line, f.position_mm, f.figure) for f in geometry.failing}
    series = []
    treated = geometry.treatment != "as-welded"
    for figure, label, unit in _TOE_FIGURES:
        if figure.startswith("groove") and not treated:
            continue
        curves = {}
        for line in geometry.line_names():
            for side in TOE_SIDES:
                rows = [(s.position_mm, *_value(getattr(s.toes, side).figure(figure) if getattr(s.toes, side) else None),
                         (line, s.position_mm, figure) in failing) for s in sections if s.line == line]
                if not rows or all(math.isnan(r[1]) for r in rows):
                    continue
                curves[f"{line} {side} toe"] = _curve(rows)
        if curves:
            series.append(AlongWeldSeries(label, unit, curves, *_limits(geometry.acceptance, figure)))
    for figure, label, unit in _SECTION_FIGURES:
        curves = {line: _curve([(s.position_mm, *_value(s.figure(figure)), (line, s.position_mm, figure) in failing)
                                for s in sections if s.line == line]) for line in geometry.line_names()}
        series.append(AlongWeldSeries(label, unit, curves, *_limits(geometry.acceptance, figure)))
    pictures = []
    for start in range(0, len(series), 4):  # at most four panels a picture
        pictures.append(_picture(along_weld(series[start:start + 4], title="Along the weld (band: 1 sigma; dashed red: "
                                            "the acceptance limits; x: a failing section)"),
                                 "weld figures along the weld"))
    return pictures


def _chosen_sections(geometry: WeldGeometry, per_line: int) -> list[WeldSection]:
    """Per weld line, the failing sections first (most violations first), then evenly along it."""
    chosen = []
    for line in geometry.line_names():
        rows = [s for s in geometry.sections if s.line == line]
        failing = sorted((s for s in rows if s.passed is False), key=lambda s: (-len(s.violations), s.position_mm))
        uncertain = [s for s in rows if s.verdict == "uncertain"]
        picked = (failing + uncertain)[:per_line]
        rest = [s for s in rows if s not in picked]
        want = per_line - len(picked)
        if want > 0 and rest:
            picked += [rest[int(round(k))] for k in np.linspace(0, len(rest) - 1, want + 2)[1:-1]] if len(rest) > want \
                else rest
        chosen += sorted({id(s): s for s in picked}.values(), key=lambda s: s.position_mm)
    return chosen


def _fmt(m: Figure | None, unit: str, digits: int = 2) -> str:
    value, sigma = _value(m)
    if math.isnan(value):
        return "-"
    return f"{value:.{digits}f}" + (f" +- {sigma:.{digits}f}" if not math.isnan(sigma) else "") + f" {unit}"


def _findings(found: list[Finding]) -> str:
    return "; ".join(f"{v.figure} {v.value} (limit {v.limit})" for v in found)


def _section_pictures(ctx, geometry: WeldGeometry, points_specimen: np.ndarray) -> list[dict[str, str]]:
    """Cross-sections measured over the drawing's plate faces (``points_specimen``: the specimen's
    measured points in the frame the weld was measured in)."""
    s = ctx.config.weld
    lo, hi = ctx.manifest.specimen.bounds_mm() if ctx.manifest.specimen is not None else (None, None)
    out = []
    for sec in _chosen_sections(geometry, ctx.settings.sections_per_line):
        line = geometry.line(sec.line)
        c = np.asarray(sec.centre_specimen_mm, np.float64)
        n = np.asarray(line.face_normal, np.float64)
        a = np.asarray(line.across, np.float64)
        t = np.cross(n, a)
        d = points_specimen - c
        sel = (np.abs(d @ t) <= s.section_half_width_mm) & (np.abs(d @ a) <= s.reach_mm) & (np.abs(d @ n) <= s.reach_mm / 2)
        u, h = d[sel] @ a, d[sel] @ n
        marks = []
        if sec.toes.both():
            centre = (sec.toes.minus.position_u_mm + sec.toes.plus.position_u_mm) / 2
            marks = [(toe.position_u_mm - centre, f"{side} toe") for side, toe in sec.toes.sides()]
        nominal = []
        if lo is not None and abs(n[2]) > 0.5:
            z0 = hi[2] if n[2] > 0 else lo[2]
            span = np.array([-s.reach_mm, s.reach_mm])
            nominal.append((span, (z0 - c[2] - span * a[2]) / n[2], "the drawing's plate face"))
        notes = [f"height {_fmt(sec.reinforcement_height_mm, 'mm')}", f"width {_fmt(sec.reinforcement_width_mm, 'mm')}"]
        for side, toe in sec.toes.sides():
            if toe is None:
                notes.append(f"{side}: no toe fitted")
                continue
            groove = toe.groove
            notes.append(f"{side}: r {_fmt(toe.toe_radius_mm, 'mm')}, flank {_fmt(toe.flank_angle_deg, 'deg', 1)}"
                         + (f", groove {_fmt(groove.depth_mm, 'mm')} deep, {_fmt(groove.width_mm, 'mm', 1)} wide"
                            if groove else ""))
        failing = sec.passed is False
        title = f"{sec.line} at {sec.position_mm:g} mm" + (" - fails" if failing else " - uncertain"
                                                           if sec.verdict == "uncertain" else "")
        if failing:
            verdict = "FAILS: " + _findings(sec.violations)
        elif sec.verdict == "uncertain":
            verdict = "UNCERTAIN (within 1 sigma of a limit, or not measured): " + _findings(sec.uncertain)
        else:
            verdict = "within the limits" if sec.passed else (sec.note or "not judged")
        width = _value(sec.reinforcement_width_mm)[0]
        span = (width / 2 if math.isfinite(width) else s.reach_mm / 2) + 6.0
        out.append(_picture(weld_section(u, h, title=title, toes=marks, nominal=nominal, failing=failing,
                                         half_span_mm=min(span, s.reach_mm)),
                            f"weld section {sec.line} {sec.position_mm:g} mm", f"{verdict}. " + "; ".join(notes)))
    return out


def _quality_picture(ctx) -> list[dict[str, str]]:
    angles = np.asarray(ELEMENT_QUALITY.open(ctx.inputs["volume"]).min_dihedral_deg[...], np.float64)
    if not len(angles):  # no model made
        return []
    return [_picture(histogram(angles, bins=np.arange(0, 72, 2.0), title="Element quality",
                               xlabel="min dihedral angle, deg", mark=10.0),
                     "FE model element quality", f"The smallest dihedral angle of each of the {len(angles):,} tetrahedra; "
                     "dashed: 10 deg")]


def qa_report(ctx) -> dict[str, Any]:
    inputs = ctx.inputs
    report = REPORT.read(inputs["report"])
    T_common_pass = np.asarray(REFINED.open(inputs["refine"]).T_common_pass[...], np.float64)
    specimen = SPECIMEN.read(inputs["segment"])
    keep = specimen.measured.astype(bool)
    T_view_common, frame = _view_frame(ctx.manifest, T_common_pass, specimen.points[keep])
    surface = apply(T_view_common, specimen.points[keep])
    surface_normals = rotate(T_view_common, specimen.normals[keep].astype(np.float64))
    zone = model_weld_zone(ctx.manifest, T_common_pass, ctx.config)  # the FE model's WELD_ZONE_SURFACE
    lines_common = [points for points, _ in weld_lines_common(ctx.manifest, T_common_pass)]
    lines_view = [apply(T_view_common, line)[:, :2] for line in lines_common[: len(ctx.manifest.weld_lines())]]
    maps, map_figures = _maps(ctx, T_view_common, T_common_pass, surface, surface_normals, lines_view)
    graph, pass_rows = _graph(ctx)
    geometry = WELD_GEOMETRY.read(inputs["weld"])
    weld = report.weld
    weld_pictures = []
    if geometry.measured:
        weld_pictures = _section_pictures(ctx, geometry, surface) + _along_weld(geometry)
    volume = VOLUME_SUMMARY.read(inputs["volume"])
    checks = report.checks
    try:
        version = importlib.metadata.version("weldrecon")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    page = _ENV.get_template("qa_report.html.j2").render(
        sample_id=ctx.manifest.sample_id, version=version, frame=frame, audit_mark=AUDIT_MARK,
        manifest=ctx.manifest, passes=len(ctx.names), setups=len(ctx.manifest.setups),
        checks=checks, flagged=[c for c in checks if c.result != "ok"], weld=weld, volume=volume,
        method_counts=sorted(Counter(report.registration_method.values()).items()),
        weld_step=ctx.config.weld.section_step_mm,
        mesh=report.mesh, maps=maps, map_figures=map_figures, pass_images=_pass_images(ctx), graph=graph,
        pass_rows=pass_rows, mesh_pictures=_mesh_pictures(ctx, T_view_common, zone),
        weld_pictures=weld_pictures, quality=_quality_picture(ctx), deliverables=report.deliverables,
        stage_keys=report.stage_keys, config=json.dumps(report.config, indent=1, sort_keys=True),
        report_sha256=inputs["report"].outputs[REPORT.name])
    QA_REPORT.write_text(ctx.out, page)
    return {"pictures": page.count('<img '), "bytes": len(page.encode()), **map_figures}
