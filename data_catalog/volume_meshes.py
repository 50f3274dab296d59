"""FE volume meshes on disk, written by meshio: Abaqus input and VTU.

Abaqus ``.inp`` (C3D10 or C3D4 tetrahedra, mm): element set ``ALL``; the weld zone's boundary as node set
``WELD_ZONE_NODES`` and as the element-face surface ``WELD_ZONE_SURFACE`` (built from one element
set per face number, ``WELD_ZONE_S1`` ... ``WELD_ZONE_S4``), for sub-modelling. VTU (binary,
zlib) with per-element data for ParaView. Node and element numbers follow the arrays' order.
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

__all__ = ["write_abaqus", "write_vtu", "WELD_ZONE_NODES", "WELD_ZONE_SURFACE"]

WELD_ZONE_NODES = "WELD_ZONE_NODES"
WELD_ZONE_SURFACE = "WELD_ZONE_SURFACE"


# meshio's cell type and the Abaqus element written, by nodes per element (meshio's own name for
# its "tetra10" is the hybrid C3D10MH: the element type is written as named here)
_TETRA = {4: ("tetra", "C3D4"), 10: ("tetra10", "C3D10")}


def _tetra_cells(tetrahedra: np.ndarray) -> tuple[str, str]:
    tetrahedra = np.asarray(tetrahedra)
    if tetrahedra.ndim != 2 or tetrahedra.shape[1] not in _TETRA:
        raise ValueError(f"tetrahedra must be (e, 4) C3D4 or (e, 10) C3D10 node numbers, got shape {tetrahedra.shape}")
    return _TETRA[tetrahedra.shape[1]]


def write_abaqus(path: Path, points: np.ndarray, tetrahedra: np.ndarray, *, zone_faces: dict[int, np.ndarray],
                 zone_nodes: np.ndarray) -> None:
    """``points`` (p, 3) mm, ``tetrahedra`` (e, 4) C3D4 or (e, 10) C3D10 (Abaqus node order),
    positively oriented; ``zone_faces`` Abaqus face number (1-4) -> the 0-based elements whose face
    of that number lies on the weld zone's boundary; ``zone_nodes`` the 0-based nodes of those faces
    (a C3D10 face's edge nodes too)."""
    cell_type, element_type = _tetra_cells(tetrahedra)
    cell_sets = {"ALL": [np.arange(len(tetrahedra))]}
    cell_sets.update({f"WELD_ZONE_S{n}": [np.asarray(zone_faces[n])] for n in sorted(zone_faces)})
    out = meshio.Mesh(points, [(cell_type, tetrahedra)], cell_sets=cell_sets,
                      point_sets={WELD_ZONE_NODES: np.asarray(zone_nodes)} if len(zone_nodes) else {})
    out.cells[0].type = element_type  # written as it is (translate_cell_names off)
    meshio.abaqus.write(str(path), out, float_fmt=".9e", translate_cell_names=False)
    if zone_faces:
        with open(path, "a", encoding="ascii") as f:
            f.write(f"*SURFACE, TYPE=ELEMENT, NAME={WELD_ZONE_SURFACE}\n")
            f.writelines(f"WELD_ZONE_S{n}, S{n}\n" for n in sorted(zone_faces))


def write_vtu(path: Path, points: np.ndarray, tetrahedra: np.ndarray, cell_data: dict[str, np.ndarray]) -> None:
    """VTU (binary, zlib) of the tetrahedra ((e, 4), or (e, 10) quadratic: VTK's order is Abaqus's)
    with one array per element in ``cell_data``."""
    cell_type, _ = _tetra_cells(tetrahedra)
    out = meshio.Mesh(points, [(cell_type, tetrahedra)], cell_data={k: [np.asarray(v)] for k, v in cell_data.items()})
    meshio.vtu.write(str(path), out, binary=True, compression="zlib")


def write_section_vtu(path: Path, frames, solutions) -> None:
    """VTU (binary, zlib) of 2-D section models placed in 3-D: each section's 6-node triangles at
    ``origin + x * across + y * up`` (``frames``: one (origin, across, up) per solution, (3,) each);
    per node its stresses (``stress_mpa``, xx yy zz xy yz zx in the section's own axes: x across,
    y up) and ``max_principal_mpa``; per triangle the section's number."""
    points, cells, stress, principal, section = [], [], [], [], []
    start = 0
    for k, ((origin, across, up), sol) in enumerate(zip(frames, solutions)):
        p = np.asarray(sol.mesh.points, np.float64)
        points.append(np.asarray(origin) + p[:, :1] * np.asarray(across) + p[:, 1:2] * np.asarray(up))
        cells.append(np.asarray(sol.mesh.triangles, np.int64) + start)
        stress.append(np.asarray(sol.stress_mpa, np.float32))
        principal.append(np.asarray(sol.max_principal_mpa, np.float32))
        section.append(np.full(len(sol.mesh.triangles), k, np.int32))
        start += len(p)
    out = meshio.Mesh(np.concatenate(points), [("triangle6", np.concatenate(cells))],
                      point_data={"stress_mpa": np.concatenate(stress), "max_principal_mpa": np.concatenate(principal)},
                      cell_data={"section": [np.concatenate(section)]})
    meshio.vtu.write(str(path), out, binary=True, compression="zlib")
