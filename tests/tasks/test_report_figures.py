"""The QA report's computations and pictures on known inputs: the coverage and the disagreement
of overlapping passes, the pass preview, and pictures that are the same bytes for the same numbers."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from flows.stages.targets import preview_image
from tasks.coverage import FaceAccumulator
from tasks.report_figures import ViewedFace, face_map, mesh_view, weld_section


def _plate(x0: float, x1: float, z: float, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(0, 10, step))
    points = np.c_[x.ravel(), y.ravel(), np.full(x.size, z)]
    return points, np.tile([0.0, 0.0, 1.0], (len(points), 1))


def test_coverage_counts_passes_and_the_spread_is_their_offset():
    surface, normals = _plate(0, 20, 0.0)
    faces = FaceAccumulator(surface, normals, lo_mm=(0, 0), hi_mm=(20, 10), cell_mm=1.0)
    faces.add(*_plate(0, 12, 0.0))        # pass A: on the surface
    faces.add(*_plate(8, 20, 0.05))       # pass B: 50 um above it
    down, down_normals = _plate(0, 20, 0.0)
    faces.add(down, -down_normals)        # pass C: the other face (normals down)
    top, bottom = faces.faces()
    assert top.name == "top" and bottom.name == "bottom"
    assert top.passes[:, :8].max() == 1 and (top.passes[:, 8:12] == 2).all() and top.passes[:, 12:].max() == 1
    assert np.allclose(top.spread_mm[:, 8:12], 0.05, atol=1e-9)
    assert np.isnan(top.spread_mm[:, :8]).all() and np.isnan(top.spread_mm[:, 12:]).all()
    assert (bottom.passes == 1).all() and np.isnan(bottom.spread_mm).all()


def test_coverage_ignores_points_off_the_surface_and_nans():
    surface, normals = _plate(0, 10, 0.0)
    faces = FaceAccumulator(surface, normals, lo_mm=(0, 0), hi_mm=(10, 10), cell_mm=1.0, max_distance_mm=1.0)
    far, far_normals = _plate(0, 10, 5.0)  # a fixture 5 mm above: not the part
    far[::7] = np.nan
    faces.add(far, far_normals)
    assert faces.faces()[0].passes.max() == 0
    with pytest.raises(ValueError, match="cell_mm must be positive"):
        FaceAccumulator(surface, normals, lo_mm=(0, 0), hi_mm=(1, 1), cell_mm=0)


def test_preview_image_averages_blocks_to_at_most_the_rows_asked():
    image = np.arange(1300 * 50, dtype=np.int64).reshape(1300, 50) % 251
    small = preview_image(image.astype(np.uint8), max_rows=640)
    assert small.dtype == np.uint8 and small.shape == (434, 17)  # blocks of 3 x 3
    assert abs(float(small[:-1, :-1].mean()) - float(image[:1299, :48].mean())) < 0.6
    same = preview_image(np.full((10, 4), 7, np.uint8), max_rows=640)
    assert same.shape == (10, 4) and (same == 7).all()


def test_pictures_are_png_and_the_same_bytes_for_the_same_numbers():
    values = np.arange(12, dtype=float).reshape(3, 4)
    face = ViewedFace("top", values, (0.0, 0.0), 1.0)
    first = face_map([face], title="t", unit="passes", discrete=True, vmax=11)
    assert first[:8] == b"\x89PNG\r\n\x1a\n" and first == face_map([face], title="t", unit="passes", discrete=True, vmax=11)
    assert first != face_map([ViewedFace("top", values + 1, (0.0, 0.0), 1.0)], title="t", unit="passes",
                             discrete=True, vmax=11)
    u = np.linspace(-10, 10, 200)
    section = weld_section(u, np.maximum(0, 2 - (u / 5) ** 2), title="s", toes=[(-5.0, "minus toe")], nominal=[],
                           failing=False, half_span_mm=12)
    assert Image.open(io.BytesIO(section)).size == (370, 200)


def test_mesh_view_draws_the_faces_toward_the_viewer_in_the_highlight_colour():
    # a unit cube, outward counter-clockwise triangles, seen from straight above
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    t = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                  [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    top = np.zeros(12, bool)
    top[[2, 3]] = True
    picture = Image.open(io.BytesIO(mesh_view(v, t, azimuth_deg=0, elevation_deg=90, title="", highlight=top,
                                              width_in=2, height_in=2))).convert("RGB")
    centre = np.asarray(picture)[100, 100].astype(int)
    assert centre[0] > centre[2]  # orange (the highlighted top), not the grey-blue of the rest
    inverted = Image.open(io.BytesIO(mesh_view(v, t[:, ::-1], azimuth_deg=0, elevation_deg=90, title="",
                                               highlight=top, width_in=2, height_in=2))).convert("RGB")
    assert np.asarray(inverted)[100, 100].astype(int)[2] >= np.asarray(inverted)[100, 100].astype(int)[0]


def test_circles_added_at_once_give_add_patchs_limits_and_picture():
    """tasks.report_figures._add_circles (the stickers on a pass's picture) against add_patch one
    by one: the same data limits (circles reaching past the image included) and the same PNG."""
    from matplotlib.patches import Ellipse

    from tasks.report_figures import _add_circles, _figure, png

    rng = np.random.default_rng(2)
    centres = np.r_[rng.uniform(0, 40, (12, 2)), [[-1.0, 20.0], [41.5, 3.0]]]  # two past the edges
    image = rng.random((8, 8))
    pictures, limits = [], []
    for at_once in (False, True):
        fig = _figure(5.6, 1.9, margins=(0.5, 0.45, 0.1, 0.25))
        ax = fig.add_subplot()
        ax.imshow(image, extent=(0, 40, 0, 40), aspect="auto")
        circles = [Ellipse(tuple(c), 5.0, 5.0, fill=False, color="tab:red", lw=0.8) for c in centres]
        if at_once:
            _add_circles(ax, circles)
        else:
            for circle in circles:
                ax.add_patch(circle)
        limits.append(ax.dataLim.get_points().copy())
        pictures.append(png(fig))
    assert np.array_equal(limits[0], limits[1]) and limits[0][0, 0] < -3  # grown by the circles past the edge
    assert pictures[0] == pictures[1]
