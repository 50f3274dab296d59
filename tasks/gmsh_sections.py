"""gmsh's side of the 2-D section models (``tasks.section_model``): quadratic triangles filling
plane outlines, made in a child process of its own.

``tasks.section_model`` runs this file by its path (``python .../gmsh_sections.py``), as
``tasks.volume_mesh`` runs ``gmsh_volume.py``: the child loads numpy and gmsh and nothing else of
weldrecon; the arguments come pickled on stdin, the result (``("ok", [(points, triangles), ...])``
or ``("error", message)``) goes pickled to stdout after ``RESULT``.

Each outline is cut at its corners (and wherever it turns sharply) into pieces, each a smooth
curve through its points (gmsh's Catmull-Rom spline): a notch drawn as a polyline would put a
small re-entrant corner at every vertex, where the stress grows as the elements shrink. The
element size is a field: ``fine_size_mm`` within ``fine_reach_mm`` of the ``fine`` points, growing
by ``growth`` per mm up to ``size_mm``. gmsh's Frontal-Delaunay (Mesh.Algorithm 6) meshes the
inside, then the triangles are made quadratic (6-node, the edge nodes on the curves).
"""

from __future__ import annotations

import pickle
import sys

import numpy as np

__all__ = ["RESULT", "GmshFailed", "gmsh_sections", "split_at_corners"]

RESULT = b"\n--weldrecon-gmsh-result--\n"  # gmsh_volume.RESULT, which the parent reads (run by path, it imports neither)


class GmshFailed(Exception):
    """gmsh could not mesh an outline (its message)."""


def split_at_corners(loop: np.ndarray, corners, *, kink_deg: float = 20.0) -> list[np.ndarray]:
    """The closed polyline ``loop`` (k, 2) cut into open pieces at its ``corners`` (indices into
    ``loop``: e.g. where a cut meets the surface) and at every point where it turns by more than
    ``kink_deg``; each piece runs from one such point to the next, both included."""
    loop = np.asarray(loop, np.float64)
    k = len(loop)
    d_in, d_out = loop - np.roll(loop, 1, axis=0), np.roll(loop, -1, axis=0) - loop
    cos = np.einsum("ij,ij->i", d_in, d_out) / np.maximum(np.hypot(*d_in.T) * np.hypot(*d_out.T), 1e-300)
    kinks = np.flatnonzero(cos < np.cos(np.radians(kink_deg)))
    cuts = np.unique(np.r_[np.asarray(corners, np.int64) % k, kinks]) if len(corners) or len(kinks) else np.array([0])
    if len(cuts) == 1:
        cuts = np.array([cuts[0], (cuts[0] + k // 2) % k])
    return [loop[np.arange(a, b + (k if b <= a else 0) + 1) % k] for a, b in zip(cuts, np.roll(cuts, -1))]


def _one(gmsh, n: int, section: dict):
    gmsh.model.add(f"section{n}")
    loops = []
    for loop, corners in [(section["outline"], section["corners"]), *[(h, []) for h in section["holes"]]]:
        pieces = split_at_corners(loop, corners)
        ends = [gmsh.model.geo.addPoint(float(x), float(y), 0.0) for x, y in (p[0] for p in pieces)]
        curves = []
        for i, piece in enumerate(pieces):
            first, last = ends[i], ends[(i + 1) % len(ends)]
            if len(piece) == 2:
                curves.append(gmsh.model.geo.addLine(first, last))
            else:  # a smooth curve through the piece's points (Catmull-Rom): no kink for the stress to see
                inner = [gmsh.model.geo.addPoint(float(x), float(y), 0.0) for x, y in piece[1:-1]]
                curves.append(gmsh.model.geo.addSpline([first, *inner, last]))
        loops.append(gmsh.model.geo.addCurveLoop(curves))
    gmsh.model.geo.addPlaneSurface(loops)
    gmsh.model.geo.synchronize()
    fine = np.asarray(section["fine"], np.float64)
    if len(fine):
        tags = [gmsh.model.geo.addPoint(float(x), float(y), 0.0) for x, y in fine]
        gmsh.model.geo.synchronize()
        distance = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(distance, "PointsList", tags)
        ramp = gmsh.model.mesh.field.add("Threshold")
        reach, lo, hi = section["fine_reach_mm"], section["fine_size_mm"], section["size_mm"]
        for name, value in (("InField", distance), ("SizeMin", lo), ("SizeMax", hi), ("DistMin", reach),
                            ("DistMax", reach + max(hi - lo, 0.0) / section["growth"])):
            gmsh.model.mesh.field.setNumber(ramp, name, value)
        gmsh.model.mesh.field.setAsBackgroundMesh(ramp)
    gmsh.option.setNumber("Mesh.MeshSizeMax", section["size_mm"])
    gmsh.model.mesh.generate(2)
    gmsh.model.mesh.setOrder(2)
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    _, element_nodes = gmsh.model.mesh.getElementsByType(9)  # 6-node triangles
    if len(element_nodes) == 0:
        raise GmshFailed(f"outline {n}: gmsh made no triangles")
    index = np.zeros(int(node_tags.max()) + 1, np.int64)
    index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
    points = np.asarray(coords, np.float64).reshape(-1, 3)[:, :2]
    triangles = index[np.asarray(element_nodes, np.int64)].reshape(-1, 6)
    # only the nodes the triangles use (gmsh also gives a node for every point the splines were
    # drawn through), numbered in gmsh's order
    used = np.unique(triangles)
    renumber = np.full(len(points), -1, np.int64)
    renumber[used] = np.arange(len(used))
    return points[used], renumber[triangles]


def gmsh_sections(sections: list[dict], *, seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each section's nodes (n, 2) and 6-node triangles (e, 6; gmsh's order: corners, then the edge
    nodes of 0-1, 1-2, 2-0, which is Abaqus's CPE6/CPS6 order), counter-clockwise."""
    import gmsh

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    out = []
    try:
        for name, value in (("General.Terminal", 0), ("General.NumThreads", 1), ("Mesh.RandomSeed", seed),
                            ("Mesh.MeshSizeExtendFromBoundary", 1), ("Mesh.MeshSizeFromPoints", 0),
                            ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.Algorithm", 6), ("Mesh.ElementOrder", 1),
                            ("Mesh.SecondOrderLinear", 0)):
            gmsh.option.setNumber(name, value)
        for n, section in enumerate(sections):
            points, triangles = _one(gmsh, n, section)
            corners = points[triangles[:, :3]]
            e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
            flip = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
            triangles[flip] = triangles[flip][:, [0, 2, 1, 5, 4, 3]]
            out.append((points, triangles))
            gmsh.model.remove()
    except GmshFailed:
        raise
    except Exception as exc:  # gmsh raises a bare Exception with its last error
        raise GmshFailed(f"gmsh could not mesh a section: {exc}") from exc
    finally:
        gmsh.finalize()
    return out


def main() -> None:
    """The child's side: the arguments pickled on stdin, the result (or the error) on stdout."""
    sections, settings = pickle.loads(sys.stdin.buffer.read())
    try:
        result = ("ok", gmsh_sections(sections, **settings))
    except GmshFailed as exc:
        result = ("error", str(exc))
    sys.stdout.buffer.write(RESULT + pickle.dumps(result))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
