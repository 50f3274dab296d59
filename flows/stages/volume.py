"""Stage ``volume``: the FE model. gmsh fills the Poisson surface with tetrahedra graded toward the
weld lines (where the setups' nominal placements and the refined poses put them) and, finer, toward
the weld toes the weld stage measured, from the
surface simplified to ``volume.max_surface_triangles`` (quadric edge collapse; a part with no weld
lines to as many triangles of edge ``volume.size_mm`` as cover it: its elements are no finer), checked to be
one positively oriented solid of the surface's volume, written as Abaqus ``.inp`` and VTU (quadratic
tetrahedra, C3D10, by default: ``volume.element_order``) with
the element quality figures (``tasks.volume_mesh``) and the simplified surface (``surface.zarr``, which
the QA page draws). An open surface (a scan that left the part
unclosed), one gmsh cannot fill, or a fill that is not one solid of the surface's volume makes no
model: ``volume.json`` says why, the report flags it, the model files are left out and the run
publishes the rest (the STL is the deliverable a fatigue model cannot do without)."""

from __future__ import annotations

from typing import Any

import numpy as np

from data_catalog.volume_meshes import WELD_ZONE_NODES, WELD_ZONE_SURFACE, write_abaqus, write_vtu
from flows.stages.outputs import (ELEMENT_QUALITY, MESH, MODEL_SURFACE, REFINED, VOLUME_INP, VOLUME_SUMMARY, VOLUME_VTU,
                                  WELD_TOES, ElementQualityArrays, Mesh)
from flows.stages.placement import model_weld_zone
from schemas.stage_documents import FEModelSummary, SolidChecks, VolumeSets
from tasks.arrays import distinct
from tasks.mesh import mesh_report, simplify_surface
from tasks.volume_mesh import (VolumeMeshError, element_face_nodes, element_quality, quadratic_tetrahedra,
                               quality_summary, solid_checks, tetrahedralize)

__all__ = ["volume"]


def volume(ctx) -> dict[str, Any]:
    s = ctx.settings
    surface = MESH.read(ctx.inputs["mesh"])
    closed = mesh_report(surface.vertices, surface.triangles)
    if not (closed.watertight and closed.consistently_oriented):
        MODEL_SURFACE.write(ctx.out, Mesh(vertices=np.zeros((0, 3)), triangles=np.zeros((0, 3), np.int64)))  # none
        return _not_made(ctx, f"the surface mesh is not closed ({closed.n_boundary_edges} boundary edges, "
                              f"{closed.n_non_manifold_edges} non-manifold edges): no solid to fill")
    # the weld zone (placement.model_weld_zone, the weld frame's lines; the QA page colours the same):
    # elements graded toward its lines, its boundary faces the named set
    zone = model_weld_zone(ctx.manifest, REFINED.open(ctx.inputs["refine"]).T_common_pass, ctx.config)
    lines = [np.asarray(z.points_mm, np.float64) for z in zone.zones]
    toes = WELD_TOES.read(ctx.inputs["weld"]).polylines()  # where the weld stage measured the toes
    budget = s.max_surface_triangles
    if not lines and not toes:  # no weld: elements of size_mm everywhere, the surface no finer
        # as many equilateral triangles of edge size_mm as cover the surface's area
        budget = max(1000, min(budget, int(np.ceil(closed.surface_area_mm2 / (np.sqrt(3) / 4 * s.size_mm ** 2)))))
    vertices, triangles = simplify_surface(surface.vertices, surface.triangles, max_triangles=budget)
    MODEL_SURFACE.write(ctx.out, Mesh(vertices=vertices, triangles=triangles))  # the QA page draws it
    try:
        solid = tetrahedralize(vertices, triangles, weld_lines_mm=lines, size_mm=s.size_mm,
                               weld_size_mm=s.weld_size_mm, weld_zone_mm=s.weld_zone_mm, growth=s.growth,
                               feature_angle_deg=s.feature_angle_deg, optimize=s.optimize, toe_lines_mm=toes,
                               toe_size_mm=s.toe_size_mm, toe_zone_mm=s.toe_zone_mm, timeout_s=s.timeout_s,
                               keep_surface_after_timeout=s.keep_surface_after_timeout)
    except VolumeMeshError as exc:
        return _not_made(ctx, str(exc))
    checks = solid_checks(solid, closed.volume_mm3)
    difference = checks.volume_difference  # None: a surface of no volume (refused as off)
    problems = [what for what, bad in (
        (f"{checks.components} separate solids, expected one", checks.components != 1),
        (f"{checks.negative_or_flat} tetrahedra with no positive volume", checks.negative_or_flat > 0),
        (f"{checks.open_boundary_edges} boundary edges not shared by two boundary faces",
         checks.open_boundary_edges > 0),
        (f"volume {checks.volume_mm3:.1f} mm3 differs from the surface's {checks.surface_volume_mm3:.1f} mm3 "
         f"by {100 * abs(difference or 0):.2f} %, over volume.max_volume_difference "
         f"{100 * s.max_volume_difference:.2f} %", difference is None or abs(difference) > s.max_volume_difference),
    ) if bad]
    if problems:
        return _not_made(ctx, "the volume mesh is not one valid solid: " + "; ".join(problems))
    min_dihedral, aspect = element_quality(solid.points, solid.tetrahedra)  # of the corners, either order
    zone_faces = solid.weld_zone_faces()
    points, elements = solid.points, solid.tetrahedra
    if s.element_order == 2:  # C3D10: the same elements with a node at each edge's midpoint
        points, elements = quadratic_tetrahedra(solid.points, solid.tetrahedra)
    zone = solid.weld_zone_face
    zone_nodes = distinct(element_face_nodes(elements, solid.boundary_element[zone], solid.boundary_face[zone]))
    write_abaqus(ctx.out / VOLUME_INP.name, points, elements, zone_faces=zone_faces, zone_nodes=zone_nodes)
    in_zone = np.zeros(len(solid.tetrahedra), np.uint8)
    in_zone[np.concatenate(list(zone_faces.values()) or [np.zeros(0, np.int64)])] = 1
    write_vtu(ctx.out / VOLUME_VTU.name, points, elements,
              {"min_dihedral_deg": min_dihedral.astype(np.float32), "aspect_ratio": aspect.astype(np.float32),
               "weld_zone_boundary": in_zone})
    ELEMENT_QUALITY.write(ctx.out, ElementQualityArrays(min_dihedral_deg=min_dihedral.astype(np.float32),
                                                        aspect_ratio=aspect.astype(np.float32)))
    solid_figures = SolidChecks(**{k: (round(v, 6) if isinstance(v, float) else v) for k, v in checks.model_dump().items()})
    summary = FEModelSummary(
        made=True, surface_triangles=int(len(surface.triangles)), meshed_triangles=int(len(triangles)),
        surface_remeshed=solid.surface_remeshed,
        surface_kept_because=solid.surface_kept_because, element_type="C3D10" if s.element_order == 2 else "C3D4",
        model_nodes=int(len(points)), slivers_peeled=solid.slivers_peeled,
        short_edges_collapsed=solid.short_edges_collapsed, nodes_moved=solid.nodes_moved, solid=solid_figures,
        quality=quality_summary(min_dihedral, aspect), weld_lines=len(lines), toe_lines=len(toes),
        toe_points=int(sum(len(t) for t in toes)),
        sets=VolumeSets(elements="ALL", weld_zone_nodes=WELD_ZONE_NODES, weld_zone_surface=WELD_ZONE_SURFACE))
    VOLUME_SUMMARY.write(ctx.out, summary)
    return {"made": True, "tetrahedra": solid_figures.tetrahedra, "nodes": solid_figures.nodes,
            "volume_difference": solid_figures.volume_difference, "weld_zone_faces": solid_figures.weld_zone_faces,
            "min_dihedral_deg": summary.quality.min_dihedral_deg.worst,
            "aspect_ratio_worst": summary.quality.aspect_ratio.worst}


def _not_made(ctx, why: str) -> dict[str, Any]:
    """No FE model: why, in volume.json (the report's check and the terminal say it); the model
    files left out (the surface simplified for it, ``surface.zarr``, written by the caller), the run
    goes on and publishes the rest."""
    VOLUME_SUMMARY.write(ctx.out, FEModelSummary(made=False, why=why))
    ELEMENT_QUALITY.write(ctx.out, ElementQualityArrays(min_dihedral_deg=np.zeros(0, np.float32),
                                                        aspect_ratio=np.zeros(0, np.float32)))
    return {"made": False, "why": why}
