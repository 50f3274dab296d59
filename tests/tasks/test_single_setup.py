"""A single setup: the part told apart from the fixture by the fixture's plane, the part's drawing
where the setup puts it, and its size (tasks/single_setup.py)."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.reconstruction import SegmentConfig
from tasks.single_setup import PartNotFound, fill_underside, find_fixture_plane, keep_part_single_setup


def _face(origin, u, v, normal, step=1.0):
    """Points on the rectangle origin + s*u + t*v (0 <= s, t <= 1), ``step`` mm apart, with ``normal``."""
    origin, u, v = (np.asarray(a, float) for a in (origin, u, v))
    s = np.arange(0, np.linalg.norm(u) + 1e-9, step) / max(np.linalg.norm(u), 1e-9)
    t = np.arange(0, np.linalg.norm(v) + 1e-9, step) / max(np.linalg.norm(v), 1e-9)
    S, T = np.meshgrid(s, t, indexing="ij")
    points = origin + S.reshape(-1, 1) * u + T.reshape(-1, 1) * v
    return points, np.repeat(np.asarray(normal, float)[None], len(points), 0)


def _box(lo, hi, faces=("top", "-x", "+x", "-y", "+y"), step=1.0):
    """The visible faces of an axis-aligned box (the bottom is on the table, unseen)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    parts = {"top": _face((x0, y0, z1), (x1 - x0, 0, 0), (0, y1 - y0, 0), (0, 0, 1), step),
             "-x": _face((x0, y0, z0), (0, y1 - y0, 0), (0, 0, z1 - z0), (-1, 0, 0), step),
             "+x": _face((x1, y0, z0), (0, y1 - y0, 0), (0, 0, z1 - z0), (1, 0, 0), step),
             "-y": _face((x0, y0, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), (0, -1, 0), step),
             "+y": _face((x0, y1, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), (0, 1, 0), step)}
    points, normals = zip(*(parts[f] for f in faces))
    return np.concatenate(points), np.concatenate(normals)


def _scene(*objects):
    points = np.concatenate([o[0] for o in objects])
    normals = np.concatenate([o[1] for o in objects])
    labels = np.concatenate([np.full(len(o[0]), k) for k, o in enumerate(objects)])
    return points, normals, labels


def _table(size=300.0, z=0.0):
    return _face((-size / 2, -size / 2, z), (size, 0, 0), (0, size, 0), (0, 0, 1), step=2.0)


# the stage's settings, as the segment stage passes them (the task function has no defaults of its own)
SETTINGS = {k: getattr(SegmentConfig(), k) for k in ("plane_clearance_mm", "size_tolerance", "min_seen_fraction")}
PART_BOUNDS = ((-80.0, -20.0, -5.0), (80.0, 20.0, 5.0))  # a 160 x 40 x 10 mm plate, specimen frame


def test_the_plate_on_blocks_is_kept_and_the_table_and_blocks_go():
    part = _box((-80, -20, 10), (80, 20, 20))
    blocks = [_box((x - 10, -10, 0), (x + 10, 10, 10), faces=("-x", "+x", "-y", "+y")) for x in (-60, 60)]
    points, normals, labels = _scene(part, _table(), *blocks)
    result = keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 1), link_mm=1.0, part_bounds_mm=PART_BOUNDS)
    assert np.array_equal(result.keep, labels == 0)
    assert result.plane is not None and abs(result.plane.offset_mm) < 1e-9 and result.plane.normal[2] > 0.999
    np.testing.assert_allclose(result.extents_mm[:2], [160, 40], atol=1e-6)


def test_a_plate_standing_on_the_table_comes_apart_from_it_at_the_plane():
    """Its walls reach down to the table: only the plane's removal separates the two."""
    part = _box((-80, -20, 0), (80, 20, 10), step=0.5)
    points, normals, labels = _scene(part, _table())
    result = keep_part_single_setup(points, normals, **{**SETTINGS, "plane_clearance_mm": 1.0}, up=(0, 0, 1),
                                    link_mm=1.0, part_bounds_mm=PART_BOUNDS)
    assert np.array_equal(result.keep, (labels == 0) & (points[:, 2] > 1.0))
    assert result.below_plane == int(np.count_nonzero((labels == 1) | (points[:, 2] <= 1.0)))


def test_the_plane_is_found_when_tilted_and_the_up_direction_is_rough():
    tilt = np.radians(3.0)
    R = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    table = _table()
    part = _box((-80, -20, 10), (80, 20, 20))
    points, normals, _ = _scene(part, table)
    plane = find_fixture_plane(points @ R.T + [0, 0, -7.0], normals @ R.T, up=(0, 0.05, 1))
    np.testing.assert_allclose(plane.normal, R[:, 2], atol=1e-9)  # the table's own normal, not the rough up
    assert plane.support == len(table[0]) and plane.rms_mm < 1e-9
    assert plane.offset_mm == pytest.approx(-7.0 * R[2, 2], abs=1e-9)


def test_rails_beside_the_part_are_cut_by_the_placed_drawing_box():
    """The part lies on two rails that run past its ends: they touch it, the table plane does not
    separate them, the drawing box placed where the setup says does."""
    part = _box((-80, -20, 20), (80, 20, 30))
    rails = [_box((-150, y - 3, 0), (150, y + 3, 20)) for y in (-12, 12)]
    points, normals, labels = _scene(part, _table(), *rails)
    T_frame_part = np.eye(4)
    T_frame_part[:3, 3] = [0.5, -0.3, 25.0]  # nominal, half a millimetre off the truth
    without = pytest.raises(PartNotFound, match=r"is 2\d\d\.\d x 40\.0 mm .* the part's drawing 160\.0 x 40\.0 mm")
    with without:
        keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 1), link_mm=1.0, part_bounds_mm=PART_BOUNDS)
    result = keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 1), link_mm=1.0, part_bounds_mm=PART_BOUNDS,
                                    T_frame_part=T_frame_part, placement_tolerance_mm=1.0, box_margin_mm=1.0)
    assert result.keep[labels == 0].all()
    # what is kept of the rails lies within the grown box under the part: at most the 2 mm under it
    rail_kept = points[result.keep & (labels >= 2)]
    assert len(rail_kept) == 0 or (rail_kept[:, 2] >= 20 - 2.5).all()
    assert result.outside_box > 0


def test_a_body_not_of_the_parts_size_is_refused_with_the_figures():
    part = _box((-80, -20, 10), (80, 20, 20))
    points, normals, _ = _scene(part, _table())
    with pytest.raises(PartNotFound, match=r"160\.0 x 40\.0 mm along its two longest axes, the part's drawing "
                                           r"300\.0 x 40\.0 mm"):
        keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 1), link_mm=1.0,
                               part_bounds_mm=((-150, -20, -5), (150, 20, 5)))


def test_an_up_direction_given_upside_down_finds_no_plane_and_refuses():
    """``up`` set the wrong way (the robot's base frame taken upside down): no point faces it, no
    plane is removed, and the largest body is the table with the part on it: refused, not kept."""
    part = _box((-80, -20, 0), (80, 20, 10))
    points, normals, _ = _scene(part, _table())
    with pytest.raises(PartNotFound, match=r"plane none found.* is [34]\d\d\.\d x [234]\d\d\.\d mm"):
        keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, -1), link_mm=2.5, part_bounds_mm=PART_BOUNDS)


def test_bad_arguments_are_named():
    points, normals, _ = _scene(_box((-80, -20, 10), (80, 20, 20)))
    with pytest.raises(ValueError, match=r"up must be a finite non-zero 3-vector"):
        keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 0), link_mm=1.0, part_bounds_mm=PART_BOUNDS)
    with pytest.raises(ValueError, match=r"part_bounds_mm must be \(min corner, max corner\)"):
        keep_part_single_setup(points, normals, **SETTINGS, up=(0, 0, 1), link_mm=1.0, part_bounds_mm=((0, 0, 0), (1, 1, 0)))
    with pytest.raises(ValueError, match=r"normals must have the points' shape"):
        find_fixture_plane(points, normals[:5], up=(0, 0, 1))


def test_the_unseen_underside_is_closed_by_a_plane_over_the_outline():
    """A T-shaped outline (a plate and a stem seen from above, say): the plane fills the outline at
    the lowest point's height, its normals down, one point per cell, nothing outside."""
    plate = _box((-80, -20, 10), (80, 20, 20))
    stem = _box((-5, 20, 10), (5, 60, 20), faces=("top", "-x", "+x", "+y"))
    points = np.concatenate([plate[0], stem[0]])
    fill = fill_underside(points, up=(0, 0, 1), spacing_mm=1.0)
    assert fill.height_mm == 10.0 and np.all(fill.points_mm[:, 2] == 10.0)
    np.testing.assert_array_equal(fill.normals, np.repeat([[0.0, 0.0, -1.0]], len(fill.points_mm), 0))
    area = 160 * 40 + 10 * 40
    assert abs(len(fill.points_mm) - area) < 0.05 * area  # the outline's cells, within its rim
    x, y = fill.points_mm[:, 0], fill.points_mm[:, 1]
    in_plate = (np.abs(x) <= 81) & (np.abs(y) <= 21)
    in_stem = (np.abs(x) <= 6) & (y >= 19) & (y <= 61)
    assert np.all(in_plate | in_stem)
    with pytest.raises(ValueError, match="spacing_mm must be positive"):
        fill_underside(points, up=(0, 0, 1), spacing_mm=0.0)


def test_two_setups_matched_wrongly_make_a_body_larger_than_the_part_and_are_refused():
    """The segment's evidence that the setups are one body: two copies of a 160 x 40 mm plate side
    by side (the second setup's stickers matched to the wrong ones) are 160 x 85 mm: refused with
    both sizes; the plate alone, or part of it, passes."""
    from types import SimpleNamespace

    from flows.stages.segment import _one_body_of_the_parts_size
    from schemas.manifest import PlateSpecimen
    from schemas.reconstruction import SegmentConfig

    ctx = SimpleNamespace(manifest=SimpleNamespace(specimen=PlateSpecimen(kind="plate", length_mm=160, width_mm=40,
                                                                           thickness_mm=10)),
                          settings=SegmentConfig())
    plate = _box((-80, -20, 0), (80, 20, 10))[0]
    figures = _one_body_of_the_parts_size(ctx, plate)
    assert figures["drawing_extents_mm"] == [160.0, 40.0, 10.0]
    np.testing.assert_allclose(figures["part_extents_mm"][:2], [160, 40], atol=1e-6)
    _one_body_of_the_parts_size(ctx, plate[plate[:, 0] < 0])  # half of it scanned: not refused
    twice = np.concatenate([plate, plate + [0, 45, 0]])
    with pytest.raises(ValueError, match=r"the part kept is 160\.0 x 85\.0 mm along its two longest axes, its drawing "
                                         r"160\.0 x 40\.0 mm .*not registered as one body"):
        _one_body_of_the_parts_size(ctx, twice)


def test_inside_drawing_box_places_and_grows_the_box():
    from tasks.single_setup import inside_drawing_box

    T = np.eye(4)
    T[:3, 3] = (100.0, 0.0, 50.0)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # turned over
    box = ((-10.0, -5.0, -2.0), (10.0, 5.0, 2.0))
    points = np.array([[100.0, 0.0, 50.0], [110.5, 0.0, 50.0], [100.0, 0.0, 47.5], [100.0, 0.0, 52.5]])
    inside = inside_drawing_box(points, T_frame_part=T, part_bounds_mm=box, grow_lo_mm=np.zeros(3),
                                grow_hi_mm=(1.0, 0.0, 1.0))
    # x grown by 1 beyond the max; z = 47.5 is local +2.5 (turned over): grown by 1 beyond the max
    assert inside.tolist() == [True, True, True, False]
    with pytest.raises(ValueError, match=r"T_frame_part must be a finite \(4, 4\) pose"):
        inside_drawing_box(points, T_frame_part=np.eye(3), part_bounds_mm=box, grow_lo_mm=0, grow_hi_mm=0)
