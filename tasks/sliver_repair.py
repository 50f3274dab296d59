"""Slivers out of a tetrahedral mesh by local operations, for the FE model
(``tasks.volume_mesh``).

gmsh's optimisers move and swap inside the volume; a sliver whose four nodes lie on the surface
is out of their reach. On the demo's model they were of two kinds: a flat tetrahedron spanning two
neighbouring surface triangles (the surface's edge between them flipped would not need it) and a
wedge on a surface edge of ~0.01 mm (where the reparametrised patches' curves meet). The first is
peeled off (the two surface triangles become the element's two other faces: the surface moves by
the element's thickness), the second's short edge collapsed (its two nodes merged where the
elements around them are best: the surface moves by the edge's length). Each operation is kept
only where the elements it changes are all positive and better than before (fewer outside the
limits, or as few and a better worst one), and where the mesh stays one manifold solid (the link
condition, with the outside as one more vertex).
Where neither applies, a node of the element is moved to where the elements around it are best:
one inside anywhere, one on the surface within its faces' plane where they are flat (the
T-joint's one poor element, aspect ratio 11.3 -> 7.1; Netgen's optimiser, `volume.optimize`,
leaves a node inside flat on a surface triangle, 0.69 deg on the demo).
Elements it cannot mend are left as they are and counted (``SliverRepair.left``): on the demo
one with a node inside, its fourth node at a 90 deg edge of the plate (9.0 deg, aspect ratio
13.2), where moving the nodes (a surface node along the edge: 9.0 at best), 2-3 and 3-2 flips
and merging the inner node were tried and none made it good.
Pure numpy without BLAS (no thread count changes a sum), in a fixed order: the same mesh gives
the same result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.arrays import distinct

__all__ = ["SliverRepair", "repair_boundary_slivers", "MIN_DIHEDRAL_DEG", "MAX_ASPECT_RATIO"]

# the limits FE programs accept without warnings (issue 26): the repair's aim, the stage's defaults,
# the quality summary's count and the report's check
MIN_DIHEDRAL_DEG = 10.0
MAX_ASPECT_RATIO = 10.0

_FACES = ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2))  # as tasks.volume_mesh: the face leaving out node 3, 2, 0, 1
_APEX = (3, 2, 0, 1)  # the node each face leaves out
_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


@dataclass(frozen=True)
class SliverRepair:
    points: np.ndarray  # (p, 3) float64, mm: the nodes still used, in their old order
    tetrahedra: np.ndarray  # (e, 4) int64, positively oriented
    peeled: int  # flat elements on the surface removed
    collapsed: int  # short edges collapsed
    slid: int  # nodes moved: inside, or on the surface within a flat face
    left: int  # elements still outside the limits


def _quality(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(smallest dihedral angle deg, aspect ratio circumradius / 3 inradius, signed volume mm3) of
    tetrahedra given by their corners (e, 4, 3)."""
    normals = np.stack([np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i]) for i, j, k in _FACES], axis=1)
    areas = np.linalg.norm(normals, axis=2) / 2
    unit = normals / np.maximum(2 * areas[..., None], 1e-300)
    cos = np.stack([-np.einsum("ij,ij->i", unit[:, f], unit[:, g]) for f, g in _PAIRS], axis=1)
    dihedral = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).min(axis=1)
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    volume = np.einsum("ij,ij->i", np.cross(a, b), c) / 6.0
    inradius = 3 * np.abs(volume) / np.maximum(areas.sum(axis=1), 1e-300)
    num = ((a * a).sum(1)[:, None] * np.cross(b, c) + (b * b).sum(1)[:, None] * np.cross(c, a)
           + (c * c).sum(1)[:, None] * np.cross(a, b))
    circumradius = np.linalg.norm(num, axis=1) / np.maximum(12 * np.abs(volume), 1e-300)
    return dihedral, circumradius / np.maximum(3 * inradius, 1e-300), volume


def _score(limits: tuple[float, float], dihedral: np.ndarray, aspect: np.ndarray,
           volume: np.ndarray) -> tuple[int, float]:
    """How good a set of elements is, to compare (higher is better): first how few are outside the
    ``limits`` (smallest dihedral angle, largest aspect ratio), then the worst of them, its smallest
    dihedral angle or, where lower, 100 / its aspect ratio. Counting first: a change that trades
    one bad element for several (seen: a node moved off a flat element made four) is no better."""
    if len(dihedral) == 0:
        return 0, 90.0
    if np.any(volume <= 0):
        return -len(dihedral) - 1, -1.0
    outside = int(np.count_nonzero((dihedral < limits[0]) | (aspect > limits[1])))
    return -outside, float(min(dihedral.min(), 100.0 / max(aspect.max(), 1e-9)))


class _Mesh:
    """The tetrahedra (rows set to -1 when removed) with node -> element lookup, updated in place."""

    def __init__(self, points: np.ndarray, tets: np.ndarray, limits: tuple[float, float]):
        self.points = points
        self.limits = limits  # smallest dihedral angle, largest aspect ratio
        self.tets = tets
        self.ball: dict[int, set[int]] = {}
        order = np.argsort(tets.ravel(), kind="stable")
        nodes = tets.ravel()[order]
        starts = np.searchsorted(nodes, np.arange(len(points) + 1))
        self._order, self._starts = order // 4, starts
        self.moved: set[int] = set()  # nodes whose elements changed shape

    def elements_at(self, node: int) -> set[int]:
        if node not in self.ball:
            found = self._order[self._starts[node]:self._starts[node + 1]]
            self.ball[node] = {int(e) for e in found if self.tets[e, 0] >= 0}
        return self.ball[node]

    def remove(self, element: int) -> None:
        for n in self.tets[element]:
            self.elements_at(int(n)).discard(element)
        self.tets[element] = -1

    def replace(self, element: int, old: int, new: int) -> None:
        row = self.tets[element]
        self.elements_at(old).discard(element)
        row[row == old] = new
        self.elements_at(new).add(element)

    def boundary_faces_at(self, node: int) -> list[tuple[int, ...]]:
        """The faces (sorted node triples) at ``node`` that one element alone has."""
        count: dict[tuple[int, ...], int] = {}
        for e in self.elements_at(node):
            for face in _FACES:
                key = tuple(sorted(int(self.tets[e, k]) for k in face))
                if node in key:
                    count[key] = count.get(key, 0) + 1
        return [k for k, c in count.items() if c == 1]


_FLAT_DEG = 3.0  # a surface node's faces within this of one plane: it may slide in that plane
_OFF_SURFACE_MM = 0.01  # ... by no more than this off any of its faces' planes


def _boundary_nodes(tets: np.ndarray) -> np.ndarray:
    """The nodes of the faces one element alone has."""
    faces = np.sort(tets[:, np.asarray(_FACES)].reshape(-1, 3), axis=1)
    base = int(tets.max()) + 1
    if base ** 3 >= 2 ** 63:  # no one int64 key a face
        unique, counts = np.unique(faces, axis=0, return_counts=True)
        return distinct(unique[counts == 1])
    keys = (faces[:, 0] * base + faces[:, 1]) * base + faces[:, 2]
    unique, counts = np.unique(keys, return_counts=True)
    once = unique[counts == 1]
    return np.unique(np.stack([once // (base * base), once // base % base, once % base], axis=1))


_OUTSIDE = -2  # the vertex standing for the outside, joined to every boundary face


def _link(mesh: _Mesh, node: int) -> tuple[set, set, set]:
    """The link of ``node`` in the mesh closed by the outside vertex: its vertices, edges, triangles."""
    triangles = set()
    for e in mesh.elements_at(node):
        triangles.add(tuple(sorted(int(n) for n in mesh.tets[e] if n != node)))
    for face in mesh.boundary_faces_at(node):
        triangles.add(tuple(sorted([n for n in face if n != node] + [_OUTSIDE])))
    edges = {tuple(sorted(pair)) for t in triangles for pair in ((t[0], t[1]), (t[0], t[2]), (t[1], t[2]))}
    vertices = {n for t in triangles for n in t}
    return vertices, edges, triangles


def _collapse_keeps_topology(mesh: _Mesh, a: int, b: int) -> bool:
    """The link condition for collapsing edge (a, b): Lk(a) and Lk(b) meet exactly in Lk(ab)."""
    va, ea, ta = _link(mesh, a)
    vb, eb, tb = _link(mesh, b)
    shared_ab = set()
    for e in mesh.elements_at(a) & mesh.elements_at(b):
        shared_ab.add(tuple(sorted(int(n) for n in mesh.tets[e] if n not in (a, b))))
    boundary_ab = [f for f in mesh.boundary_faces_at(a) if b in f]
    for face in boundary_ab:
        shared_ab.add(tuple(sorted([n for n in face if n not in (a, b)] + [_OUTSIDE])))
    link_vertices = {n for edge in shared_ab for n in edge}
    return (ta & tb) == set() and (ea & eb) == shared_ab and (va - {b}) & (vb - {a}) == link_vertices


def _try_collapse(mesh: _Mesh, a: int, b: int, before: tuple[int, float]) -> bool:
    """Merge b and a at a's place, b's or the midpoint, whichever leaves the changed elements best,
    if better than ``before`` and the link condition holds."""
    if not _collapse_keeps_topology(mesh, a, b):
        return False
    gone = mesh.elements_at(a) & mesh.elements_at(b)
    changed = sorted((mesh.elements_at(a) | mesh.elements_at(b)) - gone)
    rows = mesh.tets[changed].copy()
    rows[rows == b] = a
    best, place = before, None
    for where in (mesh.points[a], mesh.points[b], (mesh.points[a] + mesh.points[b]) / 2):
        corners = mesh.points[rows]
        corners[rows == a] = where
        score = _score(mesh.limits, *_quality(corners))
        if score > best:
            best, place = score, where
    if place is None:
        return False
    for e in sorted(gone):
        mesh.remove(e)
    for e in changed:
        if b in mesh.tets[e]:
            mesh.replace(e, b, a)
    mesh.points[a] = place
    mesh.moved.add(a)
    return True


def _try_move(mesh: _Mesh, element: int, on_boundary: np.ndarray) -> bool:
    """Move a node of ``element`` to where the elements around it are best (a pattern search: steps
    from a fifth of its edges' median length, halved down to 1/1000 of it), if better than they
    are: a node inside anywhere, a surface node within the plane of its surface faces where they
    lie within ``_FLAT_DEG`` of one plane, off none of their planes by more than ``_OFF_SURFACE_MM``."""
    for node in (int(n) for n in mesh.tets[element]):
        if on_boundary[node]:
            faces = np.asarray(mesh.boundary_faces_at(node))
            if len(faces) == 0:
                continue
            p = mesh.points[faces]
            normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            normals /= np.linalg.norm(normals, axis=1)[:, None]
            if np.degrees(np.arccos(np.clip(np.abs((normals * normals[0]).sum(axis=1)), 0, 1))).max() > _FLAT_DEG:
                continue
            ref = normals[0]
            u = np.cross(ref, [1.0, 0, 0] if abs(ref[0]) < 0.9 else [0, 1.0, 0])
            u /= np.linalg.norm(u)
            directions = [u, np.cross(ref, u), -u, -np.cross(ref, u)]
        else:  # inside: anywhere
            normals = np.zeros((1, 3))
            directions = list(np.vstack([np.eye(3), -np.eye(3)]))
        start = mesh.points[node].copy()

        def within(here, step, direction, normals=normals, start=start):
            where = here + step * direction
            return None if np.abs((normals * (where - start)).sum(axis=1)).max() > _OFF_SURFACE_MM else where

        if _pattern_search(mesh, node, directions, within):
            return True
    return False


def _pattern_search(mesh: _Mesh, node: int, directions, place, accept=None) -> bool:
    """Move ``node`` to where the elements around it are best, if better than they are: a pattern
    search, steps from a fifth of its edges' median length in each of ``directions``, halved down
    to 1/1000 of it (200 tries at most). ``place(here, step, direction)``: where a step leads
    (None: nowhere it may go); ``accept(where)``: whether a better place is kept (None: always).
    True: the node moved."""
    ball = sorted(mesh.elements_at(node))
    rows = mesh.tets[ball]
    corners = mesh.points[rows]
    start = mesh.points[node].copy()
    here, best = start, _score(mesh.limits, *_quality(corners))
    step = 0.2 * float(np.median(np.linalg.norm(mesh.points[rows[rows != node]] - start, axis=1)))
    smallest, tries = step / 1000, 0
    while step > smallest and tries < 200:  # each try a step's length in every direction
        tries += 1
        moved = False
        for direction in directions:
            where = place(here, step, direction)
            if where is None:
                continue
            corners[rows == node] = where
            score = _score(mesh.limits, *_quality(corners))
            if score > best and (accept is None or accept(where)):
                best, candidate, moved = score, where, True
        if moved:
            here = candidate
        else:
            step /= 2
    if here is start:
        return False
    mesh.points[node] = here
    mesh.moved.add(node)
    return True


def _closest_points(q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The point of each triangle (k, 3, 3) closest to ``q`` (3,): (k, 3) (Ericson, Real-Time
    Collision Detection, 5.1.5: the face, an edge or a corner, by where q projects)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac = b - a, c - a
    d1, d2 = np.einsum("ij,ij->i", ab, q - a), np.einsum("ij,ij->i", ac, q - a)
    d3, d4 = np.einsum("ij,ij->i", ab, q - b), np.einsum("ij,ij->i", ac, q - b)
    d5, d6 = np.einsum("ij,ij->i", ab, q - c), np.einsum("ij,ij->i", ac, q - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        total = va + vb + vc
        out = a + ab * (vb / total)[:, None] + ac * (vc / total)[:, None]  # inside the face
        # the regions, the one Ericson tests first last (it wins)
        bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        regions = (((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * bc[:, None]),
                   ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6))[:, None]),
                   ((d6 >= 0) & (d5 <= d6), c),
                   ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3))[:, None]),
                   ((d3 >= 0) & (d4 <= d3), b),
                   ((d1 <= 0) & (d2 <= 0), a))
    for mask, point in regions:
        out[mask] = point[mask]
    return out


class _Surface:
    """The boundary as it was when first needed: its triangles' corners and, per node, its faces."""

    def __init__(self, points: np.ndarray, tets: np.ndarray):
        faces = np.sort(tets[:, np.asarray(_FACES)].reshape(-1, 3), axis=1)
        unique, counts = np.unique(faces, axis=0, return_counts=True)
        self.faces = unique[counts == 1]
        self.corners = points[self.faces].copy()
        self.points = points.copy()
        flat = self.faces.ravel()
        self._order = np.argsort(flat, kind="stable") // 3
        self._starts = np.searchsorted(flat[np.argsort(flat, kind="stable")], np.arange(len(points) + 1))

    def around(self, node: int) -> np.ndarray:
        """The faces (numbers) at ``node`` and at its neighbours on the surface."""
        own = self._order[self._starts[node]:self._starts[node + 1]]
        near = distinct(self.faces[own])
        return distinct(np.concatenate([self._order[self._starts[n]:self._starts[n + 1]] for n in near]))

    def distance(self, q: np.ndarray, faces: np.ndarray) -> tuple[float, np.ndarray]:
        """How far ``q`` is from the given faces, and the closest point on them."""
        closest = _closest_points(q, self.corners[faces])
        d = np.linalg.norm(closest - q, axis=1)
        k = int(np.argmin(d))
        return float(d[k]), closest[k]


def _try_slide(mesh: _Mesh, element: int, surface: _Surface) -> bool:
    """Move a surface node of ``element`` over the surface as it was (where its faces are not
    flat: a rounded edge or corner of the part) to where the elements around it are best: a pattern
    search of steps along the axes, each put back onto the surface, the node's faces then within
    ``_OFF_SURFACE_MM`` of it at their centres and edges' middles. The paper preset's last slivers:
    elements of three surface nodes at a plate's rounded 90 deg edge and one inside, which no place
    of the inner node mended (a node 0.15-0.85 mm along the edge did)."""
    for node in (int(n) for n in mesh.tets[element]):
        if surface._starts[node] == surface._starts[node + 1]:
            continue  # not on the surface as it was
        patch = surface.around(node)

        def onto(here, step, direction, patch=patch):
            _, where = surface.distance(here + step * direction, patch)
            return None if np.array_equal(where, here) else where

        if _pattern_search(mesh, node, np.vstack([np.eye(3), -np.eye(3)]), onto,
                           lambda where, node=node, patch=patch: _faces_on(mesh, node, where, surface, patch)):
            return True
    return False


def _faces_on(mesh: _Mesh, node: int, where: np.ndarray, surface: _Surface, patch: np.ndarray) -> bool:
    """Whether ``node``'s surface faces, it at ``where``, stay within ``_OFF_SURFACE_MM`` of the
    surface as it was (their centres and their edges' middles), and the node's place as it was
    within as much of them (a node on a sharp edge or corner stays on it)."""
    faces = []
    for face in mesh.boundary_faces_at(node):
        p = mesh.points[list(face)].copy()
        p[list(face).index(node)] = where
        faces.append(p)
        for q in (p.mean(axis=0), (p[0] + p[1]) / 2, (p[1] + p[2]) / 2, (p[2] + p[0]) / 2):
            if surface.distance(q, patch)[0] > _OFF_SURFACE_MM:
                return False
    was = surface.points[node]
    return bool(faces) and float(np.linalg.norm(_closest_points(was, np.array(faces)) - was, axis=1).min()) <= _OFF_SURFACE_MM


def _try_peel(mesh: _Mesh, element: int) -> bool:
    """Remove an element two of whose faces are on the boundary, when the edge its other two faces
    share is not on the boundary already (the surface stays manifold); or three, when the node they
    share is in no other element."""
    row = [int(n) for n in mesh.tets[element]]
    on_boundary = []
    for face in _FACES:
        key = tuple(sorted(row[k] for k in face))
        others = mesh.elements_at(key[0]) & mesh.elements_at(key[1]) & mesh.elements_at(key[2])
        on_boundary.append(len(others) == 1)
    if sum(on_boundary) == 3:  # the node the three share goes with it, if no other element has it
        apex = _APEX[on_boundary.index(False)]
        if len(mesh.elements_at(row[apex])) != 1:
            return False
        mesh.remove(element)
        return True
    if sum(on_boundary) != 2:
        return False
    inner = [tuple(row[k] for k in face) for face, b in zip(_FACES, on_boundary) if not b]
    c, d = sorted(set(inner[0]) & set(inner[1]))
    if any(c in f and d in f for f in mesh.boundary_faces_at(c)):
        return False
    mesh.remove(element)
    return True


def repair_boundary_slivers(points: np.ndarray, tetrahedra: np.ndarray, *, min_dihedral_deg: float = MIN_DIHEDRAL_DEG,
                            max_aspect_ratio: float = MAX_ASPECT_RATIO, short_edge: float = 0.2,
                            rounds: int = 4) -> SliverRepair:
    """The elements of smallest dihedral angle under ``min_dihedral_deg`` or aspect ratio over
    ``max_aspect_ratio`` repaired, worst first, by collapsing their shortest edge where it is shorter
    than ``short_edge`` times their longest, else by peeling them off the surface (module
    description). ``points`` (p, 3) mm, ``tetrahedra`` (e, 4) positively oriented; returns the
    repaired mesh with the nodes no element uses left out, and how many of each operation."""
    points = np.array(points, np.float64)
    tets = np.array(tetrahedra, np.int64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (p, 3) mm, got shape {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or (len(tets) and (tets.min() < 0 or tets.max() >= len(points))):
        raise ValueError(f"tetrahedra must be (e, 4) numbers of the {len(points)} points, got shape {tets.shape}")
    peeled = collapsed = slid = 0
    on_boundary = surface = None
    dihedral, aspect, _ = _quality(points[tets])
    for round_ in range(rounds + 1):  # each round ends where the next one's figures are the mesh's
        bad = np.flatnonzero((dihedral < min_dihedral_deg) | (aspect > max_aspect_ratio))
        if len(bad) == 0 or round_ == rounds:
            break
        mesh = _Mesh(points, tets, (min_dihedral_deg, max_aspect_ratio))
        done = 0
        for e in bad[np.lexsort((bad, dihedral[bad]))]:  # worst first, ties by number
            if mesh.tets[e, 0] < 0:
                continue
            row = mesh.tets[e]
            p = points[row]
            lengths = np.array([np.linalg.norm(p[i] - p[j]) for i, j in _PAIRS])
            i, j = _PAIRS[int(np.argmin(lengths))]
            ball = sorted(mesh.elements_at(int(row[i])) | mesh.elements_at(int(row[j])))
            before = _score(mesh.limits, *_quality(points[mesh.tets[ball]]))
            if lengths.min() < short_edge * lengths.max() and _try_collapse(mesh, int(row[i]), int(row[j]), before):
                collapsed += 1
                done += 1
            elif _try_peel(mesh, int(e)):
                peeled += 1
                done += 1
            else:
                if on_boundary is None:  # the surface's nodes: peeling and collapsing only take some away
                    on_boundary = np.zeros(len(points), bool)
                    on_boundary[_boundary_nodes(tets)] = True
                if surface is None:
                    surface = _Surface(points, tets)
                if _try_move(mesh, int(e), on_boundary) or _try_slide(mesh, int(e), surface):
                    slid += 1
                    done += 1
        if done == 0:
            break
        # the figures again where a node was merged or moved (peeling changes no element's shape)
        alive = mesh.tets[:, 0] >= 0
        tets, dihedral, aspect = mesh.tets[alive], dihedral[alive], aspect[alive]
        changed = np.flatnonzero(np.isin(tets, np.fromiter(mesh.moved, np.int64, len(mesh.moved))).any(axis=1))
        dihedral[changed], aspect[changed], _ = _quality(points[tets[changed]])
    if peeled + collapsed + slid == 0:  # nothing changed: the same arrays back
        return SliverRepair(points=points, tetrahedra=tets, peeled=0, collapsed=0, slid=0, left=len(bad))
    used = distinct(tets)
    renumber = np.full(len(points), -1, np.int64)
    renumber[used] = np.arange(len(used))
    return SliverRepair(points=points[used], tetrahedra=renumber[tets], peeled=peeled, collapsed=collapsed, slid=slid,
                        left=len(bad))
