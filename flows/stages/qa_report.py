"""Stage ``qa_report``: the sample's QA report, one self-contained HTML file (``report.html``) that
opens offline: every picture is inside it (PNG, base64), no script, no link out.

What it shows, in the order a person checks a sample: the verdicts (checks, weld, FE model); the
scan plan over the passes' coverage of each face; each pass's intensity image with the stickers
found on it; the registration graph with its residuals; how far overlapping passes disagree, as a
colour map on the faces; renderings of the mesh, the weld zone coloured; the weld's cross-sections
measured over the drawing's plates and its figures along the weld with the acceptance limits; the
FE model's element quality; the provenance (settings, inputs, code, every stage's key).

The numbers behind each picture are ``tasks.qa_views`` (the view frame, the passes on the coverage maps,
the stickers, the registration graph, the mesh and its weld zone), ``tasks.coverage`` and
``tasks.weld_views`` (the sections drawn, the figures along the weld); the pictures are
``tasks.report_figures``, drawn on worker processes (``tasks.drawing``) while this body reads the
rest of its inputs. This body reads the inputs, calls those, renders the template, writes the page.

The file is a function of the stages' outputs and records (same inputs, same bytes): the other
stages' settings it shows or draws with (the weld's section step, width and reach, the FE model's
weld zone) are read from the run's recorded settings (``report.json``), not from this stage's
config. The audit trail's state belongs to the moment of publication, not to the stage: the stage
leaves a marked place (``AUDIT_MARK``) that ``flows.stages.report.publish`` fills with the trail's
verification.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import math
from collections import Counter
from concurrent.futures import Future
from typing import Any

import numpy as np
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

from flows.stages.contracts import zarr_array
from flows.stages.qa_audit import AUDIT_MARK
from flows.stages.outputs import (CLOUD, ELEMENT_QUALITY, HOT_SECTION, MESH, MODEL_SURFACE, PREVIEW, QA_REPORT,
                                  REFINE_SUMMARY, REFINED, REGISTRATION, REGISTRATION_SUMMARY, REPORT, SPECIMEN,
                                  STRESS_SUMMARY, TARGETS, VOLUME_SUMMARY, WELD_GEOMETRY)
from flows.stages.placement import model_weld_zone, weld_frame, weld_lines_common
from schemas.reconstruction import ReconstructionConfig, WeldGeometryConfig
from schemas.weld_document import Figure, FilletWeldSection, Finding, WeldGeometry
from tasks.drawing import Drawing
from tasks.coverage import CoverageFigures, FaceAccumulator, coverage_figures
from tasks.mesh import simplify_surface
from tasks.qa_views import (PassRow, SurfaceView, coverage_maps, mesh_in_view, overlap_edges, pass_in_view, pass_rows,
                            plan_view_lines, registration_edges, sticker_marks, surface_view, thinning_steps)
from tasks.report_figures import (along_weld, face_map, histogram, intensity_image, mesh_view, registration_graph,
                                  stress_along_toes, stress_field, weld_section)
from tasks.report_figures import toe_closeups as closeup_picture
from tasks.weld_views import (along_weld_series, chosen_sections, figure_value, near_sections, section_cut,
                              toe_closeups)
from tasks.weld_zone import WeldZone

__all__ = ["qa_report", "TEMPLATES", "section_pictures", "along_weld_pictures", "steps_on_copy"]

TEMPLATES = Environment(loader=PackageLoader("flows", "templates"), autoescape=select_autoescape(["html", "j2"]),
                   undefined=StrictUndefined, keep_trailing_newline=True, trim_blocks=True, lstrip_blocks=True)


PICTURE_WORKERS = 2  # processes drawing the page's pictures while it reads its inputs (tasks.drawing)


def _maps(ctx, draw: Drawing, view: SurfaceView, T_common_pass: np.ndarray,
          lines_view: list[np.ndarray]) -> tuple[list[dict[str, str]], CoverageFigures]:
    """The scan plan over the coverage, and the passes' disagreement, on the part's two faces."""
    s = ctx.settings
    faces = FaceAccumulator.around(view.points_mm, view.normals, cell_mm=s.cell_mm)
    paths: dict[str, list[tuple[str, np.ndarray]]] = {"top": [], "bottom": []}
    entries = [e for _, e in ctx.manifest.passes()]
    for k, (name, ref) in enumerate(zip(ctx.names, ctx.inputs["denoise"])):
        points, normals = _thinned(ctx, ref, entries[k])
        seen = pass_in_view(points, normals, zarr_array(ref, CLOUD, "sensor_origins")[...],
                            T_view_common=view.T_view_common, T_common_pass=T_common_pass[k])
        faces.add(seen.points_mm, seen.normals)
        if seen.sweep_mm is not None:
            paths[seen.face].append((name, seen.sweep_mm))
    grids = faces.faces()
    maps = coverage_maps(grids)
    pictures = [draw.picture(face_map, maps.coverage, title="Scan plan and coverage", unit="passes", cmap="viridis",
                             discrete=True, vmax=maps.most_passes, paths=[paths[g.name] for g in grids], lines=lines_view,
                             alt="scan plan and coverage", caption="Arrows: each pass's sweep, start to end, over the "
                             "number of passes that measured each cell; dashed: the weld lines."),
                draw.picture(face_map, maps.spread, title="Disagreement of overlapping passes", unit="um", cmap="magma",
                             vmax=maps.spread_top_um, lines=lines_view, alt="disagreement of overlapping passes",
                             caption="Where two or more passes measured a cell: the largest minus the smallest of their "
                             "mean distances to the merged surface (colour scale to the 99th percentile).")]
    return pictures, coverage_figures(grids)


def steps_on_copy(steps, copy_steps) -> tuple[slice, ...] | None:
    """The slices of a thinned copy (every ``copy_steps`` of the whole) that give every ``steps``
    of the whole; None where a step is not a multiple of the copy's, or there is no copy (0)."""
    if min(copy_steps) < 1 or any(n % c for n, c in zip(steps, copy_steps)):
        return None
    return tuple(slice(None, None, n // c) for n, c in zip(steps, copy_steps))


def _thinned(ctx, ref, entry) -> tuple[np.ndarray, np.ndarray]:
    """A pass's points and normals thinned for the maps (``tasks.qa_views.thinning_steps``): from
    the denoise stage's thinned copy where the page's steps are multiples of the copy's (the same
    values; the paper preset: 0.27 M points of 12.9 M read a pass), else from the whole pass."""
    s = ctx.settings
    stored_points = zarr_array(ref, CLOUD, "points")
    grid = len(stored_points.shape) == 3 and ctx.manifest.scanner is not None
    steps = thinning_steps(stored_points.shape, cell_mm=s.cell_mm, points_per_pass=s.points_per_pass,
                           grid_pitch_mm=ctx.manifest.grid_pitch_mm(entry) if grid else None)
    if PREVIEW.name in ref.outputs and grid:
        step = steps_on_copy(steps, [int(n) for n in zarr_array(ref, PREVIEW, "steps")[...]])
        if step is not None:
            return zarr_array(ref, PREVIEW, "points")[step], zarr_array(ref, PREVIEW, "normals")[step]
    step = tuple(slice(None, None, n) for n in steps)
    return stored_points[step], zarr_array(ref, CLOUD, "normals")[step]


def _pass_images(ctx, draw: Drawing) -> list[dict[str, str]]:
    """Each pass's searched intensity image with the stickers found on it."""
    out = []
    radius = (ctx.manifest.sticker_diameter_mm or 0) / 2
    for name, ref in zip(ctx.names, ctx.inputs["targets"]):
        found = TARGETS.read(ref)
        if found.preview.size == 0:
            continue
        marks = sticker_marks(found.pixel, found.rms_mm, grid_spacing_mm=found.grid_spacing_mm,
                              grid_shape=found.grid_shape)
        median_rms = f", rim fit RMS median {marks.median_rms_um:.0f} um" if marks.median_rms_um is not None else ""
        out.append(draw.picture(intensity_image, found.preview, extent_mm=marks.extent_mm,
                                title=f"{name}: {len(found.pixel)} stickers", stickers_mm=marks.centres_mm,
                                radius_mm=radius, alt=f"pass {name} intensity",
                                caption=f"{name}: {len(found.pixel)} stickers{median_rms}"))
    return out


def _graph(ctx, draw: Drawing) -> tuple[list[dict[str, str]], list[PassRow]]:
    """The registration graph: pass pairs by their common targets' residuals; per-pass rows."""
    reg = REGISTRATION.open(ctx.inputs["registration"])
    summary = REGISTRATION_SUMMARY.read(ctx.inputs["registration"])
    refine = REFINE_SUMMARY.read(ctx.inputs["refine"])
    edges = registration_edges(reg.edge_passes[...], reg.residual_mm[...], reg.inlier[...])
    surface = overlap_edges(ctx.names, refine.surface_pairs)
    groups = [setup for setup, _ in ctx.manifest.passes()]
    rows = pass_rows(ctx.names, groups, edges, summary.pass_rms_mm)
    if not (edges or surface):
        return [], rows
    picture = draw.picture(registration_graph, ctx.names, groups, edges, surface,
                           title="Registration graph: pass pairs joined by common stickers", alt="registration graph",
                           caption="Passes around the circle in scan order, coloured by setup; a line per pass pair "
                           "with common stickers, coloured by their median residual after the solve, wider for more "
                           "stickers; grey: surface overlaps the refinement used.")
    return [picture], rows


def _drawn_mesh(ctx, draw: Drawing) -> Future:
    """The surface the mesh pictures show, simplified to the page's triangles on ``draw``'s pool
    (seconds of MeshLab beside the coverage maps): the FE model's surface, simplified already;
    the Poisson mesh where there is none (an open surface)."""
    simplified = MODEL_SURFACE.read(ctx.inputs["volume"])
    drawn = simplified if len(simplified.triangles) else MESH.read(ctx.inputs["mesh"])
    return draw.submit(simplify_surface, drawn.vertices, drawn.triangles, max_triangles=ctx.settings.mesh_triangles)


def _mesh_pictures(ctx, draw: Drawing, drawn: Future, T_view_common: np.ndarray, zone: WeldZone) -> list[dict[str, str]]:
    poisson_triangles = MESH.open(ctx.inputs["mesh"]).triangles.shape[0]
    vertices, triangles = drawn.result()
    seen = mesh_in_view(vertices, triangles, zone=zone, T_view_common=T_view_common)  # the zone as the FE model's
    caption = (f"The Poisson mesh ({poisson_triangles:,} triangles) simplified to {len(triangles):,} for the picture; "
               f"orange: the weld zone ({seen.zone_radius_mm:g} mm of the weld lines, the FE model's WELD_ZONE_SURFACE).")
    out = [draw.picture(mesh_view, seen.vertices_mm, triangles, azimuth_deg=-60, elevation_deg=35,
                        title="The mesh from above", highlight=seen.in_zone, alt="mesh from above", caption=caption),
           draw.picture(mesh_view, seen.vertices_mm, triangles, azimuth_deg=120, elevation_deg=-35,
                        title="The mesh from below", highlight=seen.in_zone, alt="mesh from below", caption=caption)]
    close = seen.close_up
    if close is not None:
        out.append(draw.picture(mesh_view, close.vertices_mm, close.triangles, azimuth_deg=close.azimuth_deg,
                                elevation_deg=22, title="The weld zone, close up", highlight=close.in_zone, height_in=3.0,
                                alt="mesh weld zone",
                                caption="The upward faces of the weld zone alone, seen low and nearly along the weld."))
    return out


def along_weld_pictures(geometry: WeldGeometry, *, error_bars: bool = False,
                        draw: Drawing | None = None) -> list[dict[str, str]]:
    """The weld's figures along it (``tasks.weld_views.along_weld_series``), four panels a
    picture; each 1-sigma a band, or an error bar at each section (``error_bars``). ``draw``: where
    the pictures are drawn (None: here, at once)."""
    draw = draw or Drawing()
    series = along_weld_series(geometry)
    sigma = "bars" if error_bars else "band"
    pictures = []
    for start in range(0, len(series), 4):  # at most four panels a picture
        pictures.append(draw.picture(along_weld, series[start:start + 4], title=f"Along the weld ({sigma}: 1 sigma; "
                                     "dashed red: the acceptance limits; x: a failing section)", error_bars=error_bars,
                                     alt="weld figures along the weld"))
    return pictures


def _fmt(m: Figure | None, unit: str, digits: int = 2) -> str:
    value, sigma = figure_value(m)
    if math.isnan(value):
        return "-"
    return f"{value:.{digits}f}" + (f" +- {sigma:.{digits}f}" if not math.isnan(sigma) else "") + f" {unit}"


def _findings(found: list[Finding]) -> str:
    return "; ".join(f"{v.figure} {v.value} (limit {v.limit})" for v in found)


def _section_pictures(ctx, draw: Drawing, geometry: WeldGeometry, points_specimen: np.ndarray,
                      weld: WeldGeometryConfig) -> list[dict[str, str]]:
    """Cross-sections measured over the drawing's plate faces (``points_specimen``: the specimen's
    measured points in the frame the weld was measured in; ``weld``: the settings it was measured with)."""
    bounds = ctx.manifest.specimen.bounds_mm() if ctx.manifest.specimen is not None else None
    return section_pictures(geometry, points_specimen, per_line=ctx.settings.sections_per_line,
                            half_width_mm=weld.section_half_width_mm, reach_mm=weld.reach_mm, bounds_mm=bounds, draw=draw)


def section_pictures(geometry: WeldGeometry, points_mm: np.ndarray, *, per_line: int, half_width_mm: float,
                     reach_mm: float, bounds_mm=None, draw: Drawing | None = None) -> list[dict[str, str]]:
    """Up to ``per_line`` sections per weld line (``tasks.weld_views.chosen_sections``), each its
    measured points (``points_mm`` (n, 3): the frame the weld was measured in, read within
    ``half_width_mm`` along the weld and ``reach_mm`` across it) with its toes, its figures and
    verdict in the caption, over the drawing's plate face (``bounds_mm``; None: no drawing), and
    its toes close up. ``draw``: where the pictures are drawn (None: here, at once)."""
    draw = draw or Drawing()
    out = []
    chosen = chosen_sections(geometry, per_line)
    near: dict[int, np.ndarray] = {}  # each section's neighbourhood of the points, a line's sections at once
    for name in dict.fromkeys(sec.line for sec in chosen):
        ks = [k for k, sec in enumerate(chosen) if sec.line == name]
        near.update(zip(ks, near_sections(points_mm, [chosen[k] for k in ks], geometry.line(name),
                                          half_width_mm=half_width_mm, reach_mm=reach_mm)))
    for k, sec in enumerate(chosen):
        cut = section_cut(near[k], sec, geometry.line(sec.line), half_width_mm=half_width_mm,
                          reach_mm=reach_mm, bounds_mm=bounds_mm)
        if isinstance(sec, FilletWeldSection):
            notes = [f"legs {_fmt(sec.leg_base_mm, 'mm')} on the base, {_fmt(sec.leg_stem_mm, 'mm')} on the stem",
                     f"throat {_fmt(sec.throat_mm, 'mm')}", f"convexity {_fmt(sec.convexity_mm, 'mm')}"]
        else:
            notes = [f"height {_fmt(sec.reinforcement_height_mm, 'mm')}",
                     f"width {_fmt(sec.reinforcement_width_mm, 'mm')}"]
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
        out.append(draw.picture(weld_section, cut.u_mm, cut.h_mm, title=title, toes=cut.toes, nominal=cut.plate,
                                failing=failing, half_span_mm=cut.half_span_mm, toe_points=cut.toe_points,
                                alt=f"weld section {sec.line} {sec.position_mm:g} mm",
                                caption=f"{verdict}. " + "; ".join(notes)))
        closeups = toe_closeups(near[k], sec, geometry.line(sec.line), half_width_mm=half_width_mm)
        if closeups:
            out.append(draw.picture(closeup_picture, closeups,
                                    title=f"{sec.line} at {sec.position_mm:g} mm: the toes close, height exaggerated",
                                    alt=f"toe close-up {sec.line} {sec.position_mm:g} mm",
                                    caption="Each toe's measured points and the fitted toe (its rounding of the measured "
                                    "radius and its flank at the measured angle), the height drawn taller than true "
                                    "scale."))
    return out


def _quality_picture(ctx, draw: Drawing) -> list[dict[str, str]]:
    angles = np.asarray(ELEMENT_QUALITY.open(ctx.inputs["volume"]).min_dihedral_deg[...], np.float64)
    if not len(angles):  # no model made
        return []
    return [draw.picture(histogram, angles, bins=np.arange(0, 72, 2.0), title="Element quality",
                         xlabel="min dihedral angle, deg", mark=10.0, alt="FE model element quality",
                         caption=f"The smallest dihedral angle of each of the {len(angles):,} tetrahedra; dashed: 10 deg")]


def _along_toes(rows) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, position mm, value) rows -> per label, sorted by label: (label, positions, values) in
    the rows' order; None values left out."""
    found: dict[str, list[tuple[float, float]]] = {}
    for label, position, value in rows:
        if value is not None:
            found.setdefault(label, []).append((position, value))
    return [(label, np.array([p for p, _ in r]), np.array([v for _, v in r])) for label, r in sorted(found.items())]


def _stress_pictures(ctx, draw: Drawing, geometry: WeldGeometry) -> list[dict[str, str]]:
    """The stress concentration along every toe beside the measured toe radius, and the stress map
    of the hot spot's section (the stress stage's stress.json and hot_section.zarr)."""
    stress = STRESS_SUMMARY.read(ctx.inputs["stress"])
    if not stress.made or stress.hot_spot is None:
        return []
    factors = _along_toes((f"{t.line} {t.side}", sec.position_mm, t.factor) for sec in stress.sections for t in sec.toes)
    notch = _along_toes((f"{t.line} {t.side}", sec.position_mm, t.notch_factor)
                        for sec in stress.sections for t in sec.toes)
    drawn = {f"{t.line} {t.side}": t.factor for t in stress.drawn.toes if t.factor is not None} \
        if stress.drawn is not None and stress.drawn.made else {}
    radii = _along_toes((f"{sec.line} {side}", sec.position_mm, toe.toe_radius_mm.value)
                        for sec in geometry.sections for side, toe in sec.toes.sides() if toe is not None)
    hot = stress.hot_spot
    pictures = [draw.picture(stress_along_toes, factors, radii, hot=(hot.position_mm, hot.factor), notch=notch,
                             drawn=drawn, alt="stress concentration along the toes",
                             caption=(f"{len(stress.sections)} sections, each a 2-D plane-strain model of the measured "
                                      f"part pulled across the weld (CalculiX); factor: the highest maximum principal "
                                      f"stress within reach of the toe over the force per area of the toe's plate"
                                      + (f"; dashed: the toes rounded to r = {stress.notch_radius_mm:g} mm (IIW notch "
                                         f"stress)" if notch else "")
                                      + ("; dotted: the drawn weld, toes rounded likewise" if drawn else "")))]
    section = HOT_SECTION.read(ctx.inputs["stress"])
    if len(section.triangles):
        pictures.append(draw.picture(
            stress_field, section.points_mm, section.triangles, section.factor, toe=section.toe_mm,
            title=f"Hot spot: {hot.line} weld, {hot.side} toe, {hot.position_mm:g} mm along it, factor {hot.factor:.2f}",
            alt="stress map of the hot spot's section",
            caption="The section's maximum principal stress over the nominal stress, around the hot toe (+)"))
    return pictures


def qa_report(ctx) -> dict[str, Any]:
    with Drawing(PICTURE_WORKERS) as draw:  # the pictures drawn beside what follows, filled in at the block's end
        page_arguments = _page(ctx, draw)
    page = TEMPLATES.get_template("qa_report.html.j2").render(**page_arguments)
    QA_REPORT.write_text(ctx.out, page)
    return {"pictures": page.count('<img '), "bytes": len(page.encode()),
            **dataclasses.asdict(page_arguments["map_figures"])}


def _page(ctx, draw: Drawing) -> dict[str, Any]:
    """The template's arguments, the pictures asked of ``draw``: those whose inputs are quick to
    read first, so that they are drawn while the coverage maps are summed."""
    inputs = ctx.inputs
    report = REPORT.read(inputs["report"])
    # the other stages' settings as the run recorded them (report.json), so the page is a function of its inputs
    recorded = ReconstructionConfig.model_validate(report.config)
    T_common_pass = np.asarray(REFINED.open(inputs["refine"]).T_common_pass[...], np.float64)
    drawn_mesh = _drawn_mesh(ctx, draw)
    pass_images = _pass_images(ctx, draw)
    graph, pass_rows = _graph(ctx, draw)
    geometry = WELD_GEOMETRY.read(inputs["weld"])
    stress_pictures = _stress_pictures(ctx, draw, geometry) if geometry.measured else []
    quality = _quality_picture(ctx, draw)
    specimen = SPECIMEN.read(inputs["segment"])
    view = surface_view(specimen.points, specimen.normals, specimen.measured,
                        T_common_specimen=weld_frame(ctx.manifest, T_common_pass))
    frame = "the specimen frame (the drawing's)" if view.placed else "the points' principal axes (no nominal placement)"
    zone = model_weld_zone(ctx.manifest, T_common_pass, recorded)  # the FE model's WELD_ZONE_SURFACE
    weld_pictures = []
    if geometry.measured:
        weld_pictures = (_section_pictures(ctx, draw, geometry, view.points_mm, recorded.weld)
                         + along_weld_pictures(geometry, draw=draw))
    lines_common = [points for points, _ in weld_lines_common(ctx.manifest, T_common_pass)]
    lines_view = plan_view_lines(lines_common[: len(ctx.manifest.weld_lines())], view.T_view_common)
    maps, map_figures = _maps(ctx, draw, view, T_common_pass, lines_view)
    mesh_pictures = _mesh_pictures(ctx, draw, drawn_mesh, view.T_view_common, zone)
    volume = VOLUME_SUMMARY.read(inputs["volume"])
    checks = report.checks
    try:
        version = importlib.metadata.version("weldrecon")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return dict(
        sample_id=ctx.manifest.sample_id, version=version, frame=frame, audit_mark=AUDIT_MARK,
        manifest=ctx.manifest, passes=len(ctx.names), setups=len(ctx.manifest.setups),
        checks=checks, flagged=[c for c in checks if c.result != "ok"], weld=report.weld, volume=volume,
        method_counts=sorted(Counter(report.registration_method.values()).items()),
        weld_step=recorded.weld.section_step_mm,
        mesh=report.mesh, maps=maps, map_figures=map_figures, pass_images=pass_images, graph=graph,
        pass_rows=pass_rows, mesh_pictures=mesh_pictures,
        weld_pictures=weld_pictures, quality=quality, deliverables=report.deliverables,
        stress=report.stress, stress_pictures=stress_pictures,
        stage_keys=report.stage_keys, config=json.dumps(report.config, indent=1, sort_keys=True),
        report_sha256=inputs["report"].outputs[REPORT.name])
