"""Stage ``export``: the mesh as binary STL (for FE software) and PLY."""

from __future__ import annotations

from typing import Any

from flows.stages.outputs import MESH, PLY, STL
from tasks.mesh import write_mesh

__all__ = ["export"]



def export(ctx) -> dict[str, Any]:
    m = MESH.read(ctx.inputs["mesh"])
    for target in (STL, PLY):
        write_mesh(ctx.out / target.name, m.vertices, m.triangles, binary=True)
    return {"stl_bytes": (ctx.out / STL.name).stat().st_size}
