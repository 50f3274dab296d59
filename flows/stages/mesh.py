"""Stage ``mesh``: MeshLab's screened Poisson surface on the specimen's merged points and their
normals (fitted per pass on the organized grid, in stage ``denoise``, and merged per cell)."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.outputs import MESH, Mesh, SPECIMEN
from tasks.mesh import flagged_vertices, screened_poisson

__all__ = ["mesh"]


def mesh(ctx) -> dict[str, Any]:
    s = ctx.settings
    cloud = SPECIMEN.read(ctx.inputs["segment"])
    surface = screened_poisson(cloud.points, cloud.normals.astype(np.float64), depth=s.poisson_depth,
                               samples_per_node=s.samples_per_node, point_weight=s.point_weight,
                               scale=s.poisson_scale)
    MESH.write(ctx.out, Mesh(vertices=surface.vertices, triangles=surface.triangles))
    r = surface.report
    # the vertex budget by zone: a vertex belongs to the zone of the merged point nearest to it
    fine_vertices = int(np.count_nonzero(flagged_vertices(surface.vertices, cloud.points, cloud.fine)))
    return {"points": int(len(cloud.points)), "fine_points": int(np.count_nonzero(cloud.fine)),
            "vertices_fine_zone": fine_vertices, "vertices_coarse_zone": int(len(surface.vertices) - fine_vertices), "vertices": r.n_vertices, "triangles": r.n_triangles,
            "watertight": r.watertight, "consistently_oriented": r.consistently_oriented,
            "boundary_edges": r.n_boundary_edges, "non_manifold_edges": r.n_non_manifold_edges,
            "volume_mm3": r.volume_mm3, "surface_area_mm2": r.surface_area_mm2, "note": surface.note}
