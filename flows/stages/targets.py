"""Stage ``targets`` (per pass): the pass's sticker targets, 3-D centres in the coarse world frame.

The pass is streamed in blocks of profiles (``pass_blocks``), never held whole, three times: for its
point spacing (``GridSpacing``), for the image the circles are searched in (``HoughImage``, which
needs the spacing's pixel size; the one thing held whole, small), and, with a halo of a window's
half height, to refine each circle in the block whose own profiles hold its centre. The result is
the same bytes whatever the block size (``tests/flows/test_targets_blocks.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from data_catalog.passes import PassReader
from flows.stages.outputs import PassTargets, TARGETS
from flows.stages.passes import open_entry, pass_blocks
from schemas.manifest import ScanEntry
from tasks.targets import (GridSpacing, HoughImage, SearchGrid, TargetDetection, TargetRefinement, find_circles,
                           refine_target, search_grid)

__all__ = ["targets"]

# Profiles per block; None: ``pass_blocks``'s default (about a million points). Tests set small
# ones: the results do not depend on it.
BLOCK_ROWS: int | None = None


def _blocks(ctx, reader: PassReader, halo_rows: int = 0):
    return pass_blocks(ctx.sample_dir, ctx.manifest, ctx.entry, halo_rows=halo_rows, rows=BLOCK_ROWS, reader=reader)


def _search_grid(ctx, reader: PassReader) -> SearchGrid | None:
    spacing = GridSpacing(reader.n_profiles)
    for block in _blocks(ctx, reader, halo_rows=1):  # a sampled profile's partner: the next one
        spacing.add(block.points[block.core.start:], start=block.core_start, stop=block.core_stop)
    return search_grid((reader.n_profiles, reader.n_columns), spacing.spacing_mm(),
                       sticker_diameter_mm=ctx.manifest.sticker_diameter_mm)


def _hough_image(ctx, reader: PassReader, grid: SearchGrid) -> np.ndarray:
    image = HoughImage(grid)
    for block in _blocks(ctx, reader):
        image.add(block.data.intensity)
    return image.image()


def _refine(ctx, reader: PassReader, grid: SearchGrid, circles: np.ndarray) -> list[TargetRefinement]:
    """Each circle refined in its window, in the circles' order."""
    s = ctx.settings
    positions = [grid.grid_position(c) for c in circles]
    if not positions:
        return []
    refined: list[TargetRefinement | None] = [None] * len(positions)
    for block in _blocks(ctx, reader, halo_rows=grid.half_rows):
        for i, (row, col) in enumerate(positions):
            if not block.core_start <= grid.centre_row(row) < block.core_stop:
                continue
            rows, cols = grid.window(row, col)
            assert block.start <= rows.start and rows.stop <= block.stop, "a window reaches past its block's halo"
            local = slice(rows.start - block.start, rows.stop - block.start)
            refined[i] = refine_target(block.data.intensity[local, cols], block.points[local, cols],
                                       block.T_world_sensor[local, :3, 3], pixel=(row, col), grid=grid,
                                       max_rms_mm=s.max_rms_mm, min_rim_coverage=s.min_rim_coverage,
                                       radius_tolerance=s.radius_tolerance, rim_edge=s.rim_edge)
    assert all(r is not None for r in refined), "a circle's centre fell in no block"
    return refined  # type: ignore[return-value]


PREVIEW_ROWS = 640  # the report's picture of the pass: the searched image, area-averaged to at most this many rows


def preview_image(image: np.ndarray, max_rows: int = PREVIEW_ROWS) -> np.ndarray:
    """``image`` (uint8) averaged over square blocks of f x f pixels, f the least whole number that
    brings it to ``max_rows`` rows or fewer (the last partial blocks averaged over what they hold)."""
    rows, cols = image.shape
    f = max(1, -(-rows // max_rows))
    if f == 1:
        return image.copy()
    out_r, out_c = -(-rows // f), -(-cols // f)
    total = np.zeros((out_r, out_c))
    count = np.zeros((out_r, out_c))
    r, c = np.arange(rows) // f, np.arange(cols) // f
    np.add.at(total, (r[:, None], c[None, :]), image.astype(np.float64))
    np.add.at(count, (r[:, None], c[None, :]), 1.0)
    return np.rint(total / count).astype(np.uint8)


def _detect(ctx) -> tuple[TargetDetection, np.ndarray, tuple[float, float], tuple[int, int]]:
    """The targets, the preview of the searched image, the grid's spacing and shape."""
    reader = open_entry(ctx.sample_dir, ctx.entry)
    grid = _search_grid(ctx, reader)
    shape = (reader.n_profiles, reader.n_columns)
    if grid is None:
        return (TargetDetection.from_refinements([], pixel_mm=float("nan")), np.zeros((0, 0), np.uint8),
                (float("nan"), float("nan")), shape)
    image = _hough_image(ctx, reader, grid)
    circles = find_circles(image, radius_px=grid.radius_px)
    return (TargetDetection.from_refinements(_refine(ctx, reader, grid, circles), pixel_mm=grid.pixel_mm),
            preview_image(image), grid.spacing_mm, shape)


def targets(ctx) -> dict[str, Any]:
    if isinstance(ctx.entry, ScanEntry):  # a sample registered on its surfaces: no stickers to look for
        empty = np.zeros((0, 3))
        TARGETS.write(ctx.out, PassTargets(centres=empty, normals=empty, rms_mm=np.zeros(0), rim_coverage=np.zeros(0),
                                           edge_height_mm=np.zeros(0), edge_height_sigma_mm=np.zeros(0),
                                           centre_per_height=empty, pixel=np.zeros((0, 2)),
                                           preview=np.zeros((0, 0), np.uint8),
                                           grid_spacing_mm=np.full(2, np.nan), grid_shape=np.zeros(2, np.int64)))
        return {"targets": 0, "skipped": "an imported scan (registration: surfaces): no sticker targets sought"}
    found, preview, spacing, shape = _detect(ctx)
    if not found.targets:
        raise ValueError(f"pass {ctx.entry.pass_id}: no sticker targets found ({found.n_circles} circle candidates, "
                         f"rejected {found.rejected}); the pass cannot be registered")
    t = found.targets
    TARGETS.write(ctx.out, PassTargets(centres=np.array([x.centre_mm for x in t]), normals=np.array([x.normal for x in t]),
                                       rms_mm=np.array([x.rms_mm for x in t]),
                                       rim_coverage=np.array([x.rim_coverage for x in t]),
                                       edge_height_mm=np.array([x.edge_height_mm for x in t]),
                                       edge_height_sigma_mm=np.array([x.edge_height_sigma_mm for x in t]),
                                       centre_per_height=np.array([x.centre_per_height for x in t]),
                                       pixel=np.array([x.pixel for x in t], dtype=np.float64), preview=preview,
                                       grid_spacing_mm=np.array(spacing, np.float64),
                                       grid_shape=np.array(shape, np.int64)))
    return {"targets": len(t), "circles": found.n_circles, "rejected": found.rejected,
            "median_rms_mm": float(np.median([x.rms_mm for x in t])),
            "median_edge_height_mm": float(np.median([x.edge_height_mm for x in t]))}
