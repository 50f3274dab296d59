"""2-D models of a part's cross-sections pulled along their length or bent: the stress concentration
at a notch on a section's outline (a weld toe, an HFMI groove, a handbook's notch).

A section is a closed outline in its plane (mm: x along the pull, y across it, through the
part's thickness), cut straight across at both ends (the outline's smallest and largest x), with
optional holes, and the points where the elements are finest (the toes). ``mesh_sections`` fills
the outlines with 6-node triangles (gmsh in a child process, ``tasks.gmsh_sections``: the outline's
points spaced at the local element size, finest at the fine points); ``pull_sections`` solves them
all in one CalculiX run (``tasks.fe_solve``, plane strain by default, 1 mm thick): each section's
left end held along x (one of its nodes also across), its right end moved ``stretch_mm`` along x,
both ends kept straight as a test machine's grips keep them. ``bend_sections`` bends them instead,
as a 4-point bending test bends the zone between its inner rollers: each end held straight and
turned by ``end_rotation_rad`` about its own mid-thickness (along x, each end node moved in
proportion to its height over the end's mid-thickness: the left end turned one way, the right end
the other, stretching the top (+y) face), one node of the left end held across, the right end free
to move along x as a roller lets it: pure bending, no net force through the section. (Held at
both ends, a section whose weld caps or misalignment move its neutral axis off the ends'
mid-thickness would carry a force too: on the ci sample 1.7 % of the bending stress. CalculiX
takes no end free to slide yet straight, so the same section is solved twice in the run, bent with
both ends held and pulled, and the pull that takes the bent one's force off is subtracted.)
``peaks_near`` reads the largest maximum principal stress on the outline near given points, and
the reaction (a force; a moment from each end node's reaction) gives the nominal stress: a stress
concentration factor is one over the other.

A 2-D elastic body loaded only at its boundary has the same in-plane stresses in plane strain and
plane stress (Michell): the factor is the section's, whichever the caller takes; plane strain is
the default, as for a weld across a wide plate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import math

import numpy as np

from tasks.arrays import distinct
from tasks.fe_solve import (DisplacementCase, FESolution, FESolveError, FESolveTimeout, Material, max_principal,
                            solve_static)
from tasks.volume_mesh import run_gmsh_child

__all__ = ["PlaneSection", "SectionMeshSettings", "SectionMesh", "SectionSolution", "SectionMeshError",
           "mesh_sections", "pull_sections", "bend_sections", "each_solved", "peaks_near", "boundary_nodes"]


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
    """A loaded section: its mesh, the nodal stresses (n, 6: xx, yy, zz, xy, yz, zx; MPa), the
    maximum principal stress per node (n,), the force through it (N, along x, for the model's
    thickness: the right end's reaction; bent, ~0), the bending moment (N mm for the model's thickness, the
    right end's reactions about its mid-thickness, positive when they stretch the top face; NaN
    for a pulled section, whose reactions are read summed) and how far apart the two ends'
    reactions are: pulled, |left + right| / right force; bent, |left + right| / right moment, both
    ends' taken about the same point (each end's own differ by the net force times the ends'
    offset across)."""

    mesh: SectionMesh
    stress_mpa: np.ndarray
    max_principal_mpa: np.ndarray
    force_n: float
    imbalance: float
    moment_nmm: float = math.nan


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
                           too_slow=SectionMeshError(f"gmsh did not mesh the sections within {timeout_s:g} s of "
                                                     "CPU time"))
    return [SectionMesh(points, triangles) for points, triangles in value]


def boundary_nodes(triangles: np.ndarray) -> np.ndarray:
    """The nodes on the mesh's outline (and its holes'): corners and edge nodes of the edges only
    one triangle has, sorted."""
    t = np.asarray(triangles, np.int64)
    # each edge: its two corners and its edge node (6-node triangle: 3 is 0-1, 4 is 1-2, 5 is 2-0)
    edges = np.concatenate([t[:, [0, 1, 3]], t[:, [1, 2, 4]], t[:, [2, 0, 5]]])
    key = np.sort(edges[:, :2], axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    return distinct(edges[first[count == 1]])


def pull_sections(meshes: Sequence[SectionMesh], *, stretch_mm: float = 0.01, plane: str = "strain",
                  material: Material = Material(), timeout_s: float, max_nodes_per_run: int,
                  workdir: Path | None = None) -> list[SectionSolution]:
    """Each section pulled along x by ``stretch_mm`` (see the module's description), as many
    sections in one CalculiX run as ``max_nodes_per_run`` nodes hold (at least one): CalculiX
    expands each 6-node triangle into a 15-node wedge, and its memory grows by ~16 kB a node (33
    demo sections, 745,140 nodes, in one run: 11.7 GB; the time is the same either way, ~2.5 s a
    section of 22,000 nodes). ``workdir``: where CalculiX's files are kept, one folder per run."""
    return _in_runs(meshes, "pull", float(stretch_mm), plane, material, timeout_s, max_nodes_per_run, workdir)


def bend_sections(meshes: Sequence[SectionMesh], *, end_rotation_rad: float = 1e-3, plane: str = "strain",
                  material: Material = Material(), timeout_s: float, max_nodes_per_run: int,
                  workdir: Path | None = None) -> list[SectionSolution]:
    """Each section bent, its ends turned by ``end_rotation_rad`` each about their mid-thickness
    (see the module's description), the top (+y) face stretched; in runs as ``pull_sections``."""
    return _in_runs(meshes, "bend", float(end_rotation_rad), plane, material, timeout_s, max_nodes_per_run, workdir)


def each_solved(solve: Callable[..., list[SectionSolution]], meshes: Sequence[SectionMesh], *, timeout_s: float,
                max_nodes_per_run: int, **load: float) -> list[SectionSolution | FESolveError]:
    """``solve(meshes, timeout_s=, max_nodes_per_run=, **load)`` (``pull_sections``, ``bend_sections``;
    ``load`` their ``stretch_mm`` or ``end_rotation_rad``), where a section CalculiX
    refuses (seen: "nonpositive jacobian" on one provisional section) does not take the others with
    it: a run it fails is solved again one section at a time, and a section refused alone has its
    error in its place. The same solutions as ``solve`` where nothing is refused. A run that ran out
    of time (``FESolveTimeout``) is not tried again, section by section, and is raised."""
    kwargs = dict(timeout_s=timeout_s, max_nodes_per_run=max_nodes_per_run, **load)
    try:
        return list(solve(meshes, **kwargs))
    except FESolveTimeout:
        raise
    except FESolveError as together:
        if len(meshes) == 1:
            return [together]
    out: list[SectionSolution | FESolveError] = []
    for mesh in meshes:
        try:
            out += solve([mesh], **kwargs)
        except FESolveTimeout:
            raise
        except FESolveError as alone:
            out.append(alone)
    return out


def _in_runs(meshes: Sequence[SectionMesh], load: str, amount: float, plane: str, material: Material,
             timeout_s: float, max_nodes_per_run: int, workdir: Path | None) -> list[SectionSolution]:
    """The sections in as few CalculiX runs as ``max_nodes_per_run`` nodes allow (a bent section
    counts twice: it is solved twice), in order."""
    out: list[SectionSolution] = []
    start, total = 0, 0
    copies = 2 if load == "bend" else 1
    for k, m in enumerate(meshes):
        if k > start and total + copies * len(m.points) > max_nodes_per_run:
            out += _solve_together(meshes[start:k], start, load, amount, plane, material, timeout_s,
                                   None if workdir is None else Path(workdir) / f"run{len(out)}")
            start, total = k, 0
        total += copies * len(m.points)
    if start < len(meshes):
        out += _solve_together(meshes[start:], start, load, amount, plane, material, timeout_s,
                               None if workdir is None else Path(workdir) / f"run{len(out)}")
    return out


def _solve_together(meshes: Sequence[SectionMesh], first: int, load: str, amount: float, plane: str,
                    material: Material, timeout_s: float, workdir: Path | None) -> list[SectionSolution]:
    """The sections in one CalculiX run (``first``: the first one's number, for messages), pulled
    by ``amount`` mm, or bent by ``amount`` rad an end: each then twice, bent with both ends held
    (sets LEFT, RIGHT, PIVOT) and pulled by 0.01 mm (HELD, PULLED, ANCHOR), their reactions read
    node by node."""
    bend = load == "bend"
    points, triangles, sets, prescribed, offsets, ends = [], [], {}, {}, {}, []
    start = 0
    for k, m in enumerate(meshes):
        p = np.asarray(m.points, np.float64)
        x = p[:, 0]
        span = float(x.max() - x.min())
        tol = 1e-6 * max(span, 1.0)
        left, right = np.flatnonzero(x <= x.min() + tol), np.flatnonzero(x >= x.max() - tol)
        if len(left) < 2 or len(right) < 2:
            raise ValueError(f"section {first + k}: its ends are not cut straight across (nodes at its smallest / "
                             f"largest x: {len(left)} / {len(right)})")
        anchor = left[np.argmin(np.abs(p[left, 1] - np.median(p[left, 1])))]
        mid = [0.5 * (p[e, 1].min() + p[e, 1].max()) for e in (left, right)]
        ends.append((p[left, 1], p[right, 1], mid[1]))
        for copy in ("bend", "pull") if bend else ("pull",):
            if copy == "bend":  # each end turned about its mid-thickness: u_x = -+ theta (y - y_mid)
                sets.update({f"LEFT{k}": left + start, f"RIGHT{k}": right + start,
                             f"PIVOT{k}": np.array([anchor + start])})
                prescribed.update({f"LEFT{k}": {1: -amount * (p[left, 1] - mid[0])},
                                   f"RIGHT{k}": {1: amount * (p[right, 1] - mid[1])}, f"PIVOT{k}": {2: 0.0}})
            else:
                sets.update({f"HELD{k}": left + start, f"PULLED{k}": right + start,
                             f"ANCHOR{k}": np.array([anchor + start])})
                prescribed.update({f"HELD{k}": {1: 0.0}, f"PULLED{k}": {1: 0.01 if bend else amount},
                                   f"ANCHOR{k}": {2: 0.0}})
            points.append(p)
            triangles.append(np.asarray(m.triangles, np.int64) + start)
            offsets[copy, k] = (start, start + len(p))
            start += len(p)
    if not points:
        return []
    per_node = (tuple(f"{name}{k}" for k in range(len(meshes)) for name in ("LEFT", "RIGHT", "HELD", "PULLED"))
                if bend else ())
    solved: FESolution = solve_static(np.concatenate(points), np.concatenate(triangles),
                                      DisplacementCase(node_sets=sets, prescribed=prescribed,
                                                       reactions_per_node=per_node),
                                      material=material, timeout_s=timeout_s, workdir=workdir, plane=plane)
    out = []
    for k, m in enumerate(meshes):
        a, b = offsets["pull", k]
        if not bend:
            stress = solved.stress_mpa[a:b]
            force = float(solved.reaction_n[f"PULLED{k}"][0])
            held = float(solved.reaction_n[f"HELD{k}"][0])
            imbalance = abs(force + held) / abs(force) if force else float("inf")
            out.append(SectionSolution(m, stress, max_principal(stress), force, imbalance))
            continue
        # the bent section less the pull that takes its force off: its right end free along x
        r = {name: solved.node_reaction_n[f"{name}{k}"][:, 0] for name in ("LEFT", "RIGHT", "HELD", "PULLED")}
        off = r["RIGHT"].sum() / r["PULLED"].sum()
        c, d = offsets["bend", k]
        stress = solved.stress_mpa[c:d] - off * solved.stress_mpa[a:b]
        left_rx, right_rx = r["LEFT"] - off * r["HELD"], r["RIGHT"] - off * r["PULLED"]
        y_left, y_right, y_mid = ends[k]
        moment = float(right_rx @ (y_right - y_mid))
        apart = moment + float(left_rx @ (y_left - y_mid))  # the left end's about the right end's mid-thickness
        imbalance = abs(apart) / abs(moment) if moment else float("inf")
        out.append(SectionSolution(m, stress, max_principal(stress), float(right_rx.sum()), imbalance, moment))
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
