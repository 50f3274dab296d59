"""Stage ``segment`` (remove unwanted objects): keep the specimen, the fixture goes.

Two or more setups: the connected components that carry the specimen's targets (the stickers seen
in more than one setup: the part moved, the fixture did not). Components come from the occupied
cells of a grid (``tasks.segment``): memory follows the merged points, not pairs of them. Where the
first setup states the part's nominal placement, only the points inside the part's drawing box
placed there (grown by the setup's placement tolerance and 2 mm) take part: supports that touch
the part (a T-joint's blocks, under its base plate in one setup and beside its stem in the other)
are not linked to it.

One setup (the part never turned): the fixture's plane, the part's drawing where the setup puts
it, and one body of the part's size (``tasks.single_setup``); a body that is not of the part's size
is refused with its figures, never kept.

Either way, where the first setup places the part, the part kept is held against the part declared
(``declared_part``: tasks.declared_part; the report's check "part as declared").
"""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.contracts import zarr_array
from flows.stages.outputs import MERGED, REFINED, SPECIMEN
from tasks.declared_part import against_declaration
from tasks.segment import keep_specimen_components
from tasks.single_setup import (Underside, fill_underside, inside_drawing_box, keep_part_single_setup,
                                principal_extents_mm)

__all__ = ["segment"]

_ROWS = 1 << 20  # merged points per block written
_BOX_MARGIN_MM = 2.0  # the drawing box grown beyond the placement tolerance


def _first_setup_part(ctx, T_common_pass: np.ndarray) -> np.ndarray | None:
    """The part's nominal placement in the common frame (the first setup's robot frame through its
    first pass's pose), or None where the first setup states none."""
    setup = ctx.manifest.setups[0]
    if setup.T_world_specimen_nominal is None:
        return None
    first = [e.pass_id for _, e in ctx.manifest.passes()].index(setup.passes[0].pass_id)
    return np.asarray(T_common_pass[first]) @ np.asarray(setup.T_world_specimen_nominal)


def _single_setup(ctx, T_common_pass: np.ndarray, T_part: np.ndarray | None, points: np.ndarray,
                  normals) -> tuple[np.ndarray, Underside | None, dict[str, Any]]:
    """The part in a single setup's merged cloud (common frame: the setup's robot frame through its
    first pass's pose; ``T_part``: the part's nominal placement there, ``_first_setup_part``), and
    the plane closing its unseen underside (None: ``underside_fill_mm`` 0)."""
    setup = ctx.manifest.setups[0]
    first = [e.pass_id for _, e in ctx.manifest.passes()].index(setup.passes[0].pass_id)
    T_common_world = np.asarray(T_common_pass[first])
    s = ctx.settings
    result = keep_part_single_setup(points, np.asarray(normals[...]), up=T_common_world[:3, :3] @ np.asarray(s.up_world),
                                    link_mm=s.link_mm, part_bounds_mm=ctx.manifest.specimen.bounds_mm(),
                                    T_frame_part=T_part, placement_tolerance_mm=setup.placement_tolerance_mm,
                                    plane_clearance_mm=s.plane_clearance_mm, size_tolerance=s.size_tolerance,
                                    min_seen_fraction=s.min_seen_fraction)
    plane = result.plane
    up = T_common_world[:3, :3] @ np.asarray(s.up_world)
    fill = fill_underside(points[result.keep], up=up, spacing_mm=s.underside_fill_mm) if s.underside_fill_mm else None
    return result.keep, fill, {
        "method": "single setup: fixture plane, drawing box, one body of the part's size",
        "components": result.n_components, "kept_components": 1,
        "fixture_plane": None if plane is None else {"normal": [round(float(v), 6) for v in plane.normal],
                                                     "offset_mm": round(plane.offset_mm, 4),
                                                     "support": plane.support, "rms_mm": round(plane.rms_mm, 4)},
        "points_on_or_below_plane": result.below_plane, "points_outside_drawing_box": result.outside_box,
        "part_extents_mm": [round(float(v), 2) for v in result.extents_mm],
        "drawing_extents_mm": [round(float(v), 2) for v in result.expected_mm],
        "underside": None if fill is None else {
            "note": "never seen in a single setup: closed by a plane at the lowest measured height (not measured)",
            "points": int(len(fill.points_mm)), "height_mm": round(fill.height_mm, 4), "spacing_mm": fill.spacing_mm}}


def _one_body_of_the_parts_size(ctx, kept: np.ndarray) -> dict[str, Any]:
    """Evidence that the setups were registered as one body: what is kept is no larger than the
    part's drawing along its two longest axes (setups matched wrongly put two copies of the part
    side by side, or turned; a fixture kept adds its size). Smaller is not refused: a sample may
    scan part of the part."""
    extents = principal_extents_mm(kept)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in ctx.manifest.specimen.bounds_mm())
    drawing = np.sort(hi - lo)[::-1]
    limit = 1 + ctx.settings.size_tolerance
    if np.any(extents[:2] > limit * drawing[:2]):
        raise ValueError(f"the part kept is {extents[0]:.1f} x {extents[1]:.1f} mm along its two longest axes, its "
                         f"drawing {drawing[0]:.1f} x {drawing[1]:.1f} mm (segment.size_tolerance {limit - 1:g}): larger "
                         "than the part, so the setups are not registered as one body (or the fixture is kept); "
                         "check the stickers both setups see (report: registration) and the specimen's dimensions")
    return {"part_extents_mm": [round(float(v), 2) for v in extents],
            "drawing_extents_mm": [round(float(v), 2) for v in drawing]}


def _declared_part(ctx, points: np.ndarray, keep: np.ndarray, T_part: np.ndarray | None) -> dict[str, Any] | None:
    """The part kept held against the part declared (tasks.declared_part), in the frame the first
    setup places it in; None where no setup states a placement."""
    if T_part is None or not keep.any():
        return None
    specimen = ctx.manifest.specimen
    return against_declaration(points[keep], points, T_frame_part=T_part, part_bounds_mm=specimen.bounds_mm(),
                               grow_mm=ctx.manifest.setups[0].placement_tolerance_mm + _BOX_MARGIN_MM,
                               link_mm=ctx.settings.link_mm, flat=specimen.kind in ("plate", "dog-bone"),
                               declared_thickness_mm=getattr(specimen, "thickness_mm", None))


def segment(ctx) -> dict[str, Any]:
    reg = REFINED.open(ctx.inputs["refine"])
    anchors = reg.track_positions_mm[reg.specimen_track.astype(bool)]
    points = zarr_array(ctx.inputs["merge"], MERGED, "points")
    normals = zarr_array(ctx.inputs["merge"], MERGED, "normals")
    fine = zarr_array(ctx.inputs["merge"], MERGED, "fine")
    all_points = np.asarray(points[...])  # labelling needs every point; normals and zones are read by block
    fill = None
    T_part = None if ctx.manifest.surfaces else _first_setup_part(ctx, reg.T_common_pass)
    if ctx.manifest.surfaces:  # imported scans: no fixture, no stickers to tell the part by
        keep = np.ones(len(all_points), bool)
        metrics = {"method": "surfaces sample (imported scans): every merged point kept, no fixture to remove",
                   "components": None, "kept_components": None}
    elif len(anchors):
        boxed = np.ones(len(all_points), bool)
        if T_part is not None:
            grow = np.full(3, ctx.manifest.setups[0].placement_tolerance_mm + _BOX_MARGIN_MM)
            boxed = inside_drawing_box(all_points, T_frame_part=T_part, part_bounds_mm=ctx.manifest.specimen.bounds_mm(),
                                       grow_lo_mm=grow, grow_hi_mm=grow)
        rows = np.flatnonzero(boxed)
        result = keep_specimen_components(all_points[rows], link_mm=ctx.settings.link_mm, target_points_mm=anchors)
        keep = np.zeros(len(all_points), bool)
        keep[rows[result.keep]] = True
        metrics = {"method": "components holding the targets seen in more than one setup",
                   "points_outside_drawing_box": int(len(all_points) - len(rows)),
                   "components": int(result.n_components), "kept_components": int(len(result.kept_labels)),
                   **_one_body_of_the_parts_size(ctx, all_points[keep]),
                   "declared_part": _declared_part(ctx, all_points, keep, T_part)}
    elif len(ctx.manifest.setups) == 1:
        keep, fill, metrics = _single_setup(ctx, reg.T_common_pass, T_part, all_points, normals)
        metrics["declared_part"] = _declared_part(ctx, all_points, keep, T_part)
    else:
        raise ValueError(f"no target was seen in more than one of the {len(ctx.manifest.setups)} setups: the "
                         "specimen cannot be told from the fixture (the part's stickers are those seen in two "
                         "setups; is a side seen from both?)")
    out = SPECIMEN.writer(ctx.out, chunk_rows=1 << 18)
    kept = no_normal = 0
    for start in range(0, len(keep), _ROWS):
        rows = slice(start, start + _ROWS)
        p, q = all_points[rows], np.asarray(normals[rows])
        take = keep[rows] & np.isfinite(q).all(axis=1)  # a cell whose normals cancelled has none: left out
        no_normal += int(np.count_nonzero(keep[rows]) - np.count_nonzero(take))
        out.append("points", p[take])
        out.append("normals", q[take])
        out.append("fine", np.asarray(fine[rows])[take])
        out.append("measured", np.ones(int(take.sum()), bool))
        kept += int(take.sum())
    if fill is not None:
        out.append("points", fill.points_mm)
        out.append("normals", fill.normals.astype(np.float32))
        out.append("fine", np.zeros(len(fill.points_mm), bool))
        out.append("measured", np.zeros(len(fill.points_mm), bool))
    out.close()
    return {"points_in": int(len(keep)), "points_out": kept, "without_normal": no_normal, **metrics}
