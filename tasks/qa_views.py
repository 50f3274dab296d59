"""What the QA page shows of a run, as numbers: the frame its maps and renderings are drawn in, how
each pass is thinned and placed for the coverage maps, the maps' values and colour scales, where a
pass's stickers lie on its intensity image, the registration graph's edges and per-pass rows, and
the mesh in that frame with its weld zone and the zone's close-up.

Pure functions on arrays (mm, degrees) and the run's typed documents; the pictures are drawn by
``tasks.report_figures``, the page by ``flows.stages.qa_report``. The weld's sections and figures
along the weld are ``tasks.weld_views``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from schemas.stage_documents import SurfacePair
from tasks.arrays import distinct
from tasks.cells import grid_thinning_steps
from tasks.coverage import FaceGrid
from tasks.frames import apply, invert, make_pose, rotate
from tasks.report_figures import ViewedFace
from tasks.weld_zone import WeldZone

__all__ = ["principal_axes_frame", "SurfaceView", "surface_view", "plan_view_lines", "thinning_steps", "PassInView",
           "pass_in_view", "CoverageMaps", "coverage_maps", "StickerMarks", "sticker_marks", "PairEdge",
           "OverlapEdge", "registration_edges", "overlap_edges", "PassRow", "pass_rows", "CloseUp", "MeshInView",
           "mesh_in_view"]


def _points(name: str, values, columns: int = 3) -> np.ndarray:
    """``values`` as an (n, columns) array (its dtype kept), or a ValueError naming ``name``."""
    p = np.asarray(values)
    if p.ndim != 2 or p.shape[1] != columns:
        raise ValueError(f"{name} must be (n, {columns}); got shape {p.shape}")
    return p


def _pose(name: str, T) -> np.ndarray:
    T = np.asarray(T)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) pose; got shape {T.shape}")
    return T


# --- the frame the page is drawn in ---
def principal_axes_frame(points_mm: np.ndarray) -> np.ndarray:
    """(4, 4) pose, the points' frame -> their principal axes: origin at the centroid, x the
    largest spread, z the least; each axis's sign such that the points' third moment along it is
    not negative, then z flipped where needed to make the frame right-handed. ``points_mm``:
    (n >= 3, 3), mm (its dtype is kept for the arithmetic)."""
    p = _points("points_mm", points_mm)
    if len(p) < 3 or not np.isfinite(p).all():
        raise ValueError(f"principal_axes_frame needs at least 3 finite points; got {len(p)} "
                         f"({int((~np.isfinite(p).all(axis=1)).sum())} not finite)")
    centre = p.mean(axis=0)
    d = p - centre
    _, vectors = np.linalg.eigh(d.T @ d)
    axes = vectors[:, ::-1].T.copy()  # largest spread first: x, y, z
    for k in range(3):
        if np.mean((d @ axes[k]) ** 3) < 0:
            axes[k] = -axes[k]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return make_pose(axes, -axes @ centre)


@dataclass(frozen=True)
class SurfaceView:
    """The part's measured surface in the page's view frame: ``T_view_common`` (4, 4) common ->
    view; ``points_mm`` (m, 3) float64, mm; ``normals`` (m, 3) float64, unit; ``placed``: the view
    frame is the specimen frame (else the points' principal axes)."""

    T_view_common: np.ndarray
    points_mm: np.ndarray
    normals: np.ndarray
    placed: bool


def surface_view(points_mm: np.ndarray, normals: np.ndarray, measured: np.ndarray, *,
                 T_common_specimen: np.ndarray | None) -> SurfaceView:
    """The measured points (``measured`` (n,) truthy) of the segmented specimen (``points_mm``,
    ``normals``: (n, 3), common frame) in the frame the page is drawn in: the specimen frame where
    it is placed (``T_common_specimen``, specimen -> common), else the measured points' principal
    axes (``principal_axes_frame``)."""
    points, normals = _points("points_mm", points_mm), _points("normals", normals)
    keep = np.asarray(measured).astype(bool)
    if keep.shape != (len(points),) or len(normals) != len(points):
        raise ValueError(f"points_mm {points.shape}, normals {normals.shape} and measured {keep.shape} "
                         f"must describe the same n points")
    if T_common_specimen is not None:
        T = invert(_pose("T_common_specimen", T_common_specimen))
    else:
        T = principal_axes_frame(points[keep])
    return SurfaceView(T, apply(T, points[keep]), rotate(T, normals[keep].astype(np.float64)),
                       T_common_specimen is not None)


def plan_view_lines(lines_mm: Sequence[np.ndarray], T_view_common: np.ndarray) -> list[np.ndarray]:
    """Each line (k, 3) of ``lines_mm`` (common frame, mm) seen from above in the view frame: its
    (k, 2) x, y, mm."""
    T = _pose("T_view_common", T_view_common)
    return [apply(T, _points("a line", line))[:, :2] for line in lines_mm]


# --- the coverage maps ---
def thinning_steps(shape: tuple[int, ...], *, cell_mm: float, points_per_pass: int,
                   grid_pitch_mm: Sequence[float] | None = None) -> tuple[int, ...]:
    """How a pass is thinned for the maps, as a step per axis of its stored points (``shape``):
    a grid pass ((profiles, columns, 3), ``grid_pitch_mm``: its spacing between profiles and
    between columns, mm) every k-th profile and column, k as large as keeps its points at most a
    third of a cell (``cell_mm``) apart, about nine to a cell, enough for a cell's mean; an
    imported scan ((n, 3), no pitch) evenly to about ``points_per_pass`` points."""
    if cell_mm <= 0 or points_per_pass < 1:
        raise ValueError(f"cell_mm must be positive and points_per_pass at least 1; got {cell_mm}, {points_per_pass}")
    if grid_pitch_mm is not None:
        if len(shape) != 3 or len(grid_pitch_mm) != 2 or min(grid_pitch_mm) <= 0:
            raise ValueError(f"a grid pass is (profiles, columns, 3) with two positive pitches; got shape {shape}, "
                             f"grid_pitch_mm {tuple(grid_pitch_mm)}")
        return grid_thinning_steps(cell_mm, grid_pitch_mm)
    return (max(1, shape[0] // points_per_pass),)


@dataclass(frozen=True)
class PassInView:
    """One pass's (thinned) points in the view frame: ``points_mm``, ``normals`` (n, 3) float64;
    ``sweep_mm`` (2, 2) x, y of the sensor at the sweep's start and end (None: not known) and
    ``face`` the face it looked at ("top" or "bottom", by its normals; None with no sweep)."""

    points_mm: np.ndarray
    normals: np.ndarray
    sweep_mm: np.ndarray | None
    face: str | None


def pass_in_view(points_mm: np.ndarray, normals: np.ndarray, sensor_origins_mm: np.ndarray, *,
                 T_view_common: np.ndarray, T_common_pass: np.ndarray) -> PassInView:
    """A pass's points and normals ((..., 3), its own frame, NaN where not measured; a grid pass's
    (profiles, columns, 3) are flattened) and its sensor's positions (``sensor_origins_mm`` (p, 3),
    one per profile) in the view frame, through its pose ``T_common_pass`` and ``T_view_common``."""
    T = _pose("T_view_common", T_view_common) @ _pose("T_common_pass", T_common_pass)
    points = apply(T, np.asarray(points_mm, np.float64).reshape(-1, 3))
    normals = rotate(T, np.asarray(normals, np.float64).reshape(-1, 3))
    if len(normals) != len(points):
        raise ValueError(f"{len(points)} points but {len(normals)} normals")
    origins = _points("sensor_origins_mm", np.asarray(sensor_origins_mm, np.float64))
    if len(origins) >= 2 and np.isfinite(origins[[0, -1]]).all():
        ends = apply(T, origins[[0, -1]])
        face = "top" if np.nanmean(normals[:, 2]) >= 0 else "bottom"  # normals face the sensor
        return PassInView(points, normals, ends[:, :2], face)
    return PassInView(points, normals, None, None)


@dataclass(frozen=True)
class CoverageMaps:
    """The two maps of the part's faces: ``coverage`` (passes per cell, NaN where none) and
    ``spread`` (the passes' disagreement, um), one ``ViewedFace`` per face; ``most_passes`` the
    coverage's colour scale top (at least 1); ``spread_top_um`` the disagreement's (its 99th
    percentile, at least 1 um)."""

    coverage: list[ViewedFace]
    spread: list[ViewedFace]
    most_passes: int
    spread_top_um: float


def coverage_maps(grids: Sequence[FaceGrid]) -> CoverageMaps:
    """The coverage and disagreement maps of the faces (``tasks.coverage.FaceAccumulator.faces``)."""
    if not grids:
        raise ValueError("coverage_maps needs at least one face")
    coverage = [ViewedFace(f"{g.name} face: passes that measured each {g.cell_mm:g} mm cell",
                           np.where(g.passes > 0, g.passes, np.nan).astype(float), g.origin_mm, g.cell_mm)
                for g in grids]
    spread = [ViewedFace(f"{g.name} face", g.spread_mm * 1000, g.origin_mm, g.cell_mm) for g in grids]
    most = max(int(max(g.passes.max() for g in grids)), 1)
    values = np.concatenate([g.spread_mm[np.isfinite(g.spread_mm)] for g in grids])
    top = float(np.percentile(values, 99) * 1000) if len(values) else 1.0
    return CoverageMaps(coverage, spread, most, max(top, 1.0))


# --- the passes' intensity images ---
@dataclass(frozen=True)
class StickerMarks:
    """A pass's intensity image in mm: ``extent_mm`` (line from, to, sweep from, to); the stickers'
    centres ``centres_mm`` (k, 2) (along the line, along the sweep); ``median_rms_um`` their rim
    fits' median RMS (None: no sticker)."""

    extent_mm: tuple[float, float, float, float]
    centres_mm: np.ndarray
    median_rms_um: float | None


def sticker_marks(pixel: np.ndarray, rms_mm: np.ndarray, *, grid_spacing_mm: Sequence[float],
                  grid_shape: Sequence[int]) -> StickerMarks:
    """Where the stickers found at ``pixel`` ((k, 2) (profile, column) of each circle's centre;
    ``rms_mm`` (k,) their rim fits' RMS) lie on a pass's image of ``grid_shape`` (profiles,
    columns) points ``grid_spacing_mm`` (between profiles, between columns) apart."""
    pixel = _points("pixel", pixel, columns=2)
    if len(rms_mm) != len(pixel) or len(grid_spacing_mm) != 2 or len(grid_shape) != 2:
        raise ValueError(f"pixel (k, 2) and rms_mm (k,) must agree and the grid be two numbers each; got "
                         f"{pixel.shape}, {np.shape(rms_mm)}, grid_spacing_mm {tuple(grid_spacing_mm)}, "
                         f"grid_shape {tuple(grid_shape)}")
    row_mm, col_mm = (float(v) for v in grid_spacing_mm)
    profiles, columns = (int(v) for v in grid_shape)
    extent = (0.0, columns * col_mm, 0.0, profiles * row_mm)
    centres = np.c_[(pixel[:, 1] + 0.5) * col_mm, (pixel[:, 0] + 0.5) * row_mm]
    return StickerMarks(extent, centres, float(np.median(rms_mm) * 1000) if len(rms_mm) else None)


# --- the registration graph ---
class PairEdge(NamedTuple):
    """Two passes (indices, ``a`` < ``b``) joined by ``targets`` inlier target pairs whose median
    residual after the solve is ``median_residual_mm``."""

    a: int
    b: int
    targets: int
    median_residual_mm: float


class OverlapEdge(NamedTuple):
    """Two passes (indices) whose overlapping surfaces the refinement used, their ``rms_mm`` (NaN: none)."""

    a: int
    b: int
    rms_mm: float


def registration_edges(edge_passes: np.ndarray, residual_mm: np.ndarray, inlier: np.ndarray) -> list[PairEdge]:
    """The pass pairs of the registration graph (``edge_passes`` (e, 2) pass indices of each target
    pair, ``residual_mm`` (e,) its residual, ``inlier`` (e,) whether the solve kept it): one edge
    per pass pair with an inlier, ordered by (a, b)."""
    pairs = np.asarray(edge_passes, np.int64).reshape(-1, 2)
    residual = np.asarray(residual_mm, np.float64)
    inlier = np.asarray(inlier, bool)
    if residual.shape != (len(pairs),) or inlier.shape != (len(pairs),):
        raise ValueError(f"edge_passes (e, 2), residual_mm (e,) and inlier (e,) must agree; got {pairs.shape}, "
                         f"{residual.shape}, {inlier.shape}")
    edges = []
    for a, b in sorted({(int(min(p)), int(max(p))) for p in pairs[inlier]}):
        sel = inlier & (pairs.min(axis=1) == a) & (pairs.max(axis=1) == b)
        edges.append(PairEdge(a, b, int(sel.sum()), float(np.median(residual[sel]))))
    return edges


def overlap_edges(names: Sequence[str], pairs: Sequence[SurfacePair]) -> list[OverlapEdge]:
    """The surface overlaps the refinement used (``pairs``, by pass name) as edges between the
    passes' indices in ``names``; pairs of a pass not in ``names`` are left out."""
    index = {n: k for k, n in enumerate(names)}
    return [OverlapEdge(index[p.a], index[p.b], float(p.rms_mm if p.rms_mm is not None else math.nan))
            for p in pairs if p.a in index and p.b in index]


@dataclass(frozen=True)
class PassRow:
    """One pass in the registration table: its setup, the passes it registered with, its RMS (um, None: none)."""

    pass_id: str
    setup: str
    pairs: int
    rms_um: float | None


def pass_rows(names: Sequence[str], setups: Sequence[str], edges: Sequence[PairEdge],
              pass_rms_mm: Mapping[str, float | None]) -> list[PassRow]:
    """Per pass (``names``, in order, with their ``setups``): how many graph ``edges`` it has and its
    RMS after the solve (``pass_rms_mm`` by name, mm; shown in um to 0.1)."""
    if len(setups) != len(names):
        raise ValueError(f"{len(names)} passes but {len(setups)} setups")
    degree = {n: 0 for n in names}
    for a, b, *_ in edges:
        degree[names[a]] += 1
        degree[names[b]] += 1
    return [PassRow(n, g, degree[n], None if pass_rms_mm.get(n) is None else round(pass_rms_mm[n] * 1000, 1))
            for n, g in zip(names, setups)]


# --- the mesh ---
@dataclass(frozen=True)
class CloseUp:
    """The weld zone's upward faces alone: ``vertices_mm`` (u, 3), ``triangles`` (k, 3) int64 into
    them, ``in_zone`` (k,) bool (all True), seen from ``azimuth_deg``."""

    vertices_mm: np.ndarray
    triangles: np.ndarray
    in_zone: np.ndarray
    azimuth_deg: float


@dataclass(frozen=True)
class MeshInView:
    """A mesh in the view frame: ``vertices_mm`` (v, 3) float64; ``in_zone`` (t,) bool, its faces in
    the weld zone; ``zone_radius_mm`` the zone's radius (0: no zone); ``close_up`` the weld zone's
    close-up (None: too little of it faces up)."""

    vertices_mm: np.ndarray
    in_zone: np.ndarray
    zone_radius_mm: float
    close_up: CloseUp | None


def mesh_in_view(vertices_mm: np.ndarray, triangles: np.ndarray, *, zone: WeldZone, T_view_common: np.ndarray,
                 min_close_up_faces: int = 10, azimuth_offset_deg: float = 200.0) -> MeshInView:
    """The mesh (``vertices_mm`` (v, 3), common frame; ``triangles`` (t, 3)) in the view frame,
    its faces in ``zone`` (common frame: as the FE model's WELD_ZONE_SURFACE is chosen) marked,
    and the close-up of the upper face's weld: the zone's faces that face up (normal within 60 deg
    of +z) above the mesh's median height, if more than ``min_close_up_faces``, seen low and nearly
    along the first weld line (its direction's azimuth plus ``azimuth_offset_deg``)."""
    vertices, triangles = _points("vertices_mm", vertices_mm), _points("triangles", triangles)
    T_view_common = _pose("T_view_common", T_view_common)
    near = zone.faces_in(vertices, triangles)
    v = apply(T_view_common, vertices)
    radius = zone.zones[0].radius_mm if zone else 0.0
    lines_view = [apply(T_view_common, np.asarray(z.points_mm, np.float64)) for z in zone.zones]
    corners = v[triangles]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    up = normal[:, 2] > 0.5 * np.linalg.norm(normal, axis=1)
    keep = near & up & (corners[:, :, 2].mean(axis=1) > np.median(v[:, 2]))  # the upper face's weld
    close_up = None
    if keep.sum() > min_close_up_faces and lines_view:
        used = distinct(triangles[keep])
        remap = np.full(len(v), -1, np.int64)
        remap[used] = np.arange(len(used))
        d = lines_view[0][-1] - lines_view[0][0]
        along = math.degrees(math.atan2(d[1], d[0]))
        close_up = CloseUp(v[used], remap[triangles[keep]], np.ones(int(keep.sum()), bool), along + azimuth_offset_deg)
    return MeshInView(v, near, radius, close_up)
