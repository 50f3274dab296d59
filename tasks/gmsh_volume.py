"""gmsh's side of the FE model (tasks.volume_mesh): the nodes and tetrahedra of a closed surface's
volume, made in a child process of its own.

``tasks.volume_mesh`` runs this file by its path (``python .../gmsh_volume.py``), so that the child
loads numpy and gmsh and nothing else of weldrecon: the arguments come pickled on stdin, the
result (``("ok", (node_tags, coords, element_nodes))`` or ``("error", message)``) goes pickled to
stdout after ``RESULT``. It imports nothing from the package for that reason.
"""

from __future__ import annotations

import pickle
import sys

import numpy as np

__all__ = ["RESULT", "GmshFailed", "gmsh_volume"]

RESULT = b"\n--weldrecon-gmsh-result--\n"


class GmshFailed(Exception):
    """gmsh could not mesh the volume (its message)."""


def _ramp(gmsh, points: np.ndarray, size_min: float, reach: float, size_max: float, growth: float) -> int:
    """A gmsh size field: ``size_min`` within ``reach`` of ``points`` (n, 3), then growing by
    ``growth`` per mm up to ``size_max`` (a Distance field into a Threshold)."""
    tags = [gmsh.model.geo.addPoint(*map(float, p)) for p in points]
    gmsh.model.geo.synchronize()
    distance = gmsh.model.mesh.field.add("Distance")
    gmsh.model.mesh.field.setNumbers(distance, "PointsList", tags)
    ramp = gmsh.model.mesh.field.add("Threshold")
    for name, value in (("InField", distance), ("SizeMin", size_min), ("SizeMax", size_max), ("DistMin", reach),
                        ("DistMax", reach + max(size_max - size_min, 0.0) / growth)):
        gmsh.model.mesh.field.setNumber(ramp, name, value)
    return ramp


# gmsh's 3-D algorithm: HXT (Marot, Pellerin & Remacle 2019), one thread, and gmsh's optimizer on
# the elements of a quality (gamma) under _OPTIMIZE_BELOW. On the ci sample's surface (53,296
# triangles): 6.2 s against 23.0 s for Delaunay with Netgen's optimizer (the algorithm before),
# smallest dihedral worst 16.7 deg (the same), 1st percentile 27.6 deg (31.7), aspect ratio worst 3.9,
# no element under 10 deg. gmsh's default threshold, 0.3: 13.8 deg worst, 20.0 deg 1st percentile;
# 0.6: 18.9 / 31.5 deg but 126 s. Netgen's optimizer after HXT (volume.optimize): 20.0 deg worst
# in 15.4 s (at threshold 0.3).
_HXT = 10
# the reparametrised patches at most this many triangles each: the paper preset's surface
# (150,000 triangles, genus 0) made a patch gmsh could not flatten at its default ("Wrong topology
# of boundary mesh for parametrization": the surface's own triangles were kept, 273 slivers); at
# 20,000 it cut 70 patches and flattened every one
_OPTIMIZE_BELOW = 0.45
_PATCH_TRIANGLES = 20_000


def gmsh_volume(vertices, triangles, weld, *, remesh: bool, size_mm, weld_size_mm, weld_zone_mm, growth,
                feature_angle_deg, optimize, seed, toes=None, toe_size_mm=None, toe_zone_mm=0.0):
    """gmsh's nodes and tetrahedra: the surface remeshed on its reparametrised patches (``remesh``)
    or kept as it is, the inside meshed."""
    import gmsh

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        for name, value in (("General.Terminal", 0), ("General.NumThreads", 1), ("Mesh.RandomSeed", seed),
                            ("Mesh.MeshSizeExtendFromBoundary", 1), ("Mesh.MeshSizeFromPoints", 0),
                            ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.MeshSizeMax", size_mm),
                            ("Mesh.Algorithm", 6), ("Mesh.Algorithm3D", _HXT), ("Mesh.Optimize", 1),
                            ("Mesh.OptimizeThreshold", _OPTIMIZE_BELOW), ("Mesh.OptimizeNetgen", 0),
                            ("Mesh.ReparamMaxTriangles", _PATCH_TRIANGLES)):
            gmsh.option.setNumber(name, value)
        gmsh.model.add("part")
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(vertices) + 1), vertices.ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).ravel())
        if remesh:
            gmsh.model.mesh.classifySurfaces(np.radians(feature_angle_deg), True, True, np.pi)
            gmsh.model.mesh.createGeometry()
        # remeshed: the reparametrised patches; else the discrete surface, its triangles kept
        patches = [tag for _, tag in gmsh.model.getEntities(2)]
        gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop(patches)])
        if weld is not None and len(weld):
            # the size field, in gmsh: weld_size_mm within weld_zone_mm of the weld's points, then
            # growing linearly by `growth` per mm up to size_mm
            ramp = _ramp(gmsh, weld, weld_size_mm, weld_zone_mm, size_mm, growth)
            field = ramp
            if toes is not None and len(toes):  # finer at the toes, the smaller of the two sizes wins
                # growing at the same rate up to the largest size (a Threshold is SizeMax beyond
                # DistMax: capped at the weld's size it would cap the whole part there)
                field = gmsh.model.mesh.field.add("Min")
                gmsh.model.mesh.field.setNumbers(field, "FieldsList", [
                    ramp, _ramp(gmsh, toes, toe_size_mm, toe_zone_mm, size_mm, growth)])
            sized = field
            if remesh:  # on the surface only: inside, sizes grow from the surface's
                field = gmsh.model.mesh.field.add("Restrict")
                gmsh.model.mesh.field.setNumber(field, "InField", sized)
                gmsh.model.mesh.field.setNumbers(field, "SurfacesList", patches)
            gmsh.model.mesh.field.setAsBackgroundMesh(field)
        gmsh.model.geo.synchronize()
        gmsh.model.mesh.generate(3)
        if optimize:  # (Mesh.OptimizeNetgen is not applied after HXT: asked for here)
            gmsh.model.mesh.optimize("Netgen")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, element_nodes = gmsh.model.mesh.getElementsByType(4)
    except Exception as exc:  # gmsh raises a bare Exception with its last error
        raise GmshFailed(f"gmsh could not mesh the surface's volume: {exc}") from exc
    finally:
        gmsh.finalize()
    return np.asarray(node_tags), np.asarray(coords), np.asarray(element_nodes)


def main() -> None:
    """The child's side: the arguments pickled on stdin, the result (or the error) on stdout."""
    vertices, triangles, weld, settings = pickle.loads(sys.stdin.buffer.read())
    try:
        result = ("ok", gmsh_volume(vertices, triangles, weld, **settings))
    except GmshFailed as exc:
        result = ("error", str(exc))
    sys.stdout.buffer.write(RESULT + pickle.dumps(result))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
