"""2-D models of a part's cross-sections pulled along their length: the stress concentration at a
notch on a section's outline (a weld toe, an HFMI groove, a handbook's notch).

A section is a closed outline in its plane (mm: x along the pull, y across it, through the
part's thickness), cut straight across at both ends (the outline's smallest and largest x), with
optional holes, and the points where the elements are finest (the toes). ``mesh_sections`` fills
the outlines with 6-node triangles (gmsh in a child process, ``tasks.gmsh_sections``: the outline's
points spaced at the local element size, finest at the fine points); ``pull_sections`` solves them
all in one CalculiX run (``tasks.fe_solve``, plane strain by default, 1 mm thick): each section's
left end held along x (one of its nodes also across), its right end moved ``stretch_mm`` along x,
both ends kept straight as a test machine's grips keep them. ``peaks_near`` reads the largest
maximum principal stress on the outline near given points, and the reaction gives the nominal
stress: a stress concentration factor is one over the other.

A 2-D elastic body loaded only at its boundary has the same in-plane stresses in plane strain and
plane stress (Michell): the factor is the section's, whichever the caller takes; plane strain is
the default, as for a weld across a wide plate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tasks.fe_solve import DisplacementCase, FESolution, Material, max_principal, solve_static
from tasks.volume_mesh import run_gmsh_child

__all__ = ["PlaneSection", "SectionMeshSettings", "SectionMesh", "SectionSolution", "SectionMeshError",
           "mesh_sections", "pull_sections", "peaks_near", "boundary_nodes"]


class SectionMeshError(RuntimeError):
    """gmsh could not mesh a section, or took too long."""


@dataclass(frozen=True)
class PlaneSection:
    """One cross-section: ``outline_mm`` (k, 2) a closed polyline (not repeating its first point),
    x along the pull, cut straight across at its smallest and largest x; ``corners`` indices of
    outline points kept as they are (where a cut meets the surface); ``holes_mm`` closed polylines
    inside it; ``fine_mm`` (m, 2) where the elements are finest; ``fine_size_mm`` their size there
    when this section needs its own (None: the settings')."""

    outline_mm: np.ndarray
    fine_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    corners: tuple[int, ...] = ()
    holes_mm: tuple[np.ndarray, ...] = ()
    fine_size_mm: float | None = None


@dataclass(frozen=True)
class SectionMeshSettings:
    """Element sizes (mm): ``fine_size_mm`` within ``fine_reach_mm`` of a fine point, growing by
    ``growth`` per mm up to ``size_mm``."""

    fine_size_mm: float
    fine_reach_mm: float
    size_mm: float
    growth: float


@dataclass(frozen=True)
class SectionMesh:
    """A section's nodes (n, 2) and 6-node triangles (e, 6), counter-clockwise."""

    points: np.ndarray
    triangles: np.ndarray


@dataclass(frozen=True)
class SectionSolution:
    """A pulled section: its mesh, the nodal stresses (n, 6: xx, yy, zz, xy, yz, zx; MPa), the
    maximum principal stress per node (n,), the force through it (N, along x, for the model's
    thickness) and how far apart the two ends' reactions are (|held + pulled| / pulled)."""

    mesh: SectionMesh
    stress_mpa: np.ndarray
    max_principal_mpa: np.ndarray
    force_n: float
    imbalance: float


def mesh_sections(sections: Sequence[PlaneSection], settings: SectionMeshSettings, *,
                  timeout_s: float) -> list[SectionMesh]:
    """The sections' meshes (``tasks.gmsh_sections`` in one child process, one thread); a section's
    own ``fine_size_mm`` takes the place of the settings'."""
    payload = [{"outline": np.asarray(s.outline_mm, np.float64), "corners": list(s.corners),
                "holes": [np.asarray(h, np.float64) for h in s.holes_mm],
                "fine": np.asarray(s.fine_mm, np.float64).reshape(-1, 2),
                "fine_size_mm": settings.fine_size_mm if s.fine_size_mm is None else float(s.fine_size_mm),
                "fine_reach_mm": settings.fine_reach_mm, "size_mm": settings.size_mm, "growth": settings.growth}
               for s in sections]
    for k, s in enumerate(payload):
        if s["outline"].ndim != 2 or s["outline"].shape[1] != 2 or len(s["outline"]) < 3:
            raise ValueError(f"section {k}: outline_mm must be (k >= 3, 2), got {s['outline'].shape}")
    value = run_gmsh_child("gmsh_sections.py", (payload, {}), timeout_s=timeout_s, failed=SectionMeshError,
                           too_slow=SectionMeshError(f"gmsh did not mesh the sections within {timeout_s:g} s"))
    return [SectionMesh(points, triangles) for points, triangles in value]


def boundary_nodes(triangles: np.ndarray) -> np.ndarray:
    """The nodes on the mesh's outline (and its holes'): corners and edge nodes of the edges only
    one triangle has, sorted."""
    t = np.asarray(triangles, np.int64)
    # each edge: its two corners and its edge node (6-node triangle: 3 is 0-1, 4 is 1-2, 5 is 2-0)
    edges = np.concatenate([t[:, [0, 1, 3]], t[:, [1, 2, 4]], t[:, [2, 0, 5]]])
    key = np.sort(edges[:, :2], axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    return np.unique(edges[first[count == 1]])


def pull_sections(meshes: Sequence[SectionMesh], *, stretch_mm: float = 0.01, plane: str = "strain",
                  material: Material = Material(), timeout_s: float, max_nodes_per_run: int,
                  workdir: Path | None = None) -> list[SectionSolution]:
    """Each section pulled along x by ``stretch_mm`` (see the module's description), as many
    sections in one CalculiX run as ``max_nodes_per_run`` nodes hold (at least one): CalculiX
    expands each 6-node triangle into a 15-node wedge, and its memory grows by ~16 kB a node (33
    demo sections, 745,140 nodes, in one run: 11.7 GB; the time is the same either way, ~2.5 s a
    section of 22,000 nodes). ``workdir``: where CalculiX's files are kept, one folder per run."""
    out: list[SectionSolution] = []
    start, total = 0, 0
    for k, m in enumerate(meshes):
        if k > start and total + len(m.points) > max_nodes_per_run:
            out += _pull_together(meshes[start:k], start, stretch_mm, plane, material, timeout_s,
                                  None if workdir is None else Path(workdir) / f"run{len(out)}")
            start, total = k, 0
        total += len(m.points)
    if start < len(meshes):
        out += _pull_together(meshes[start:], start, stretch_mm, plane, material, timeout_s,
                              None if workdir is None else Path(workdir) / f"run{len(out)}")
    return out


def _pull_together(meshes: Sequence[SectionMesh], first: int, stretch_mm: float, plane: str, material: Material,
                   timeout_s: float, workdir: Path | None) -> list[SectionSolution]:
    """The sections in one CalculiX run (``first``: the first one's number, for messages)."""
    points, triangles, sets, prescribed, offsets = [], [], {}, {}, []
    start = 0
    for k, m in enumerate(meshes):
        p = np.asarray(m.points, np.float64)
        x = p[:, 0]
        span = float(x.max() - x.min())
        tol = 1e-6 * max(span, 1.0)
        held, pulled = np.flatnonzero(x <= x.min() + tol), np.flatnonzero(x >= x.max() - tol)
        if len(held) < 2 or len(pulled) < 2:
            raise ValueError(f"section {first + k}: its ends are not cut straight across (nodes at its smallest / "
                             f"largest x: {len(held)} / {len(pulled)})")
        anchor = held[np.argmin(np.abs(p[held, 1] - np.median(p[held, 1])))]
        sets.update({f"HELD{k}": held + start, f"PULLED{k}": pulled + start, f"ANCHOR{k}": np.array([anchor + start])})
        prescribed.update({f"HELD{k}": {1: 0.0}, f"PULLED{k}": {1: float(stretch_mm)}, f"ANCHOR{k}": {2: 0.0}})
        points.append(p)
        triangles.append(np.asarray(m.triangles, np.int64) + start)
        offsets.append((start, start + len(p)))
        start += len(p)
    if not points:
        return []
    solved: FESolution = solve_static(np.concatenate(points), np.concatenate(triangles),
                                      DisplacementCase(node_sets=sets, prescribed=prescribed), material=material,
                                      timeout_s=timeout_s, workdir=workdir, plane=plane)
    out = []
    for k, (m, (a, b)) in enumerate(zip(meshes, offsets)):
        stress = solved.stress_mpa[a:b]
        pulled_force = float(solved.reaction_n[f"PULLED{k}"][0])
        held_force = float(solved.reaction_n[f"HELD{k}"][0])
        imbalance = abs(pulled_force + held_force) / abs(pulled_force) if pulled_force else float("inf")
        out.append(SectionSolution(m, stress, max_principal(stress), pulled_force, imbalance))
    return out


def peaks_near(solution: SectionSolution, where_mm: np.ndarray, reach_mm: float) -> list[tuple[float, np.ndarray]]:
    """For each point of ``where_mm`` (m, 2): the largest maximum principal stress (MPa) of the
    outline's nodes within ``reach_mm`` of it, and where that node is ((2,), mm); (NaN, its own
    position) where no outline node is within reach."""
    nodes = boundary_nodes(solution.mesh.triangles)
    p = solution.mesh.points[nodes]
    s = solution.max_principal_mpa[nodes]
    out = []
    for w in np.asarray(where_mm, np.float64).reshape(-1, 2):
        near = np.flatnonzero(np.hypot(*(p - w).T) <= reach_mm)
        near = near[np.isfinite(s[near])]
        if len(near) == 0:
            out.append((float("nan"), w.copy()))
            continue
        k = near[np.argmax(s[near])]
        out.append((float(s[k]), p[k].copy()))
    return out
