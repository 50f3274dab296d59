"""The part measured against the part declared (tasks.declared_part), on parts of known size made
of points on their faces: a 200 x 60 x 20 mm plate, the same plate with a 10 x 60 mm stem standing
50 mm on it (a T-joint), a fixture block beside them."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.declared_part import against_declaration

SPACING = 0.5


def _box_faces(lo, hi, spacing=SPACING) -> np.ndarray:
    """Points on the six faces of the box [lo, hi], ``spacing`` apart."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    out = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        gu = np.arange(lo[u], hi[u] + 1e-9, spacing)
        gv = np.arange(lo[v], hi[v] + 1e-9, spacing)
        U, V = np.meshgrid(gu, gv, indexing="ij")
        for level in (lo[axis], hi[axis]):
            face = np.empty((U.size, 3))
            face[:, axis], face[:, u], face[:, v] = level, U.ravel(), V.ravel()
            out.append(face)
    return np.concatenate(out)


PLATE = ((-100.0, -30.0, -10.0), (100.0, 30.0, 10.0))
STEM = ((-5.0, -30.0, 10.0), (5.0, 30.0, 60.0))
FIXTURE = _box_faces((130.0, -30.0, -40.0), (170.0, 30.0, 0.0))  # beside the part, not touching it


def _check(part: np.ndarray, bounds, *, flat: bool, thickness=None, placed=np.eye(4), grow=8.0):
    """The part placed by ``placed`` among the fixture; the kept part: what lies in the grown box."""
    merged = np.concatenate([part, FIXTURE]) @ placed[:3, :3].T + placed[:3, 3]
    lo, hi = (np.asarray(b) for b in bounds)
    local = (merged - placed[:3, 3]) @ placed[:3, :3]
    keep = np.all((local >= lo - grow) & (local <= hi + grow), axis=1)
    return against_declaration(merged[keep], merged, T_frame_part=placed, part_bounds_mm=bounds, grow_mm=grow,
                               link_mm=1.5, flat=flat, declared_thickness_mm=thickness)


def _turned(deg: float, shift) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = shift
    return T


def test_the_part_declared_agrees_with_its_thickness_measured():
    found = _check(_box_faces(*PLATE), PLATE, flat=True, thickness=20.0, placed=_turned(30, (5, -3, 100)))
    assert found["agrees"] and found["findings"] == []
    assert found["thickness_mm"] == pytest.approx(20.0, abs=0.1)
    assert found["measured_mm"] == [[-100.0, 100.0], [-30.0, 30.0], [-10.0, 10.0]]


def test_a_t_joint_declared_as_a_plate_is_measured_past_the_box():
    """What issue 28 found: a T-joint declared as a plate of its base's size reconstructed with
    every check ok (the box cut the stem off)."""
    t_joint = np.concatenate([_box_faces(*PLATE), _box_faces(*STEM)])
    found = _check(t_joint, PLATE, flat=True, thickness=20.0)
    assert not found["agrees"]
    [cut] = found["cut_faces"]
    assert cut["axis"] == "z" and cut["side"] == "+" and cut["reaches_mm"] == pytest.approx(60.0)
    assert found["measured_mm"][2] == [-10.0, 60.0]
    assert found["findings"] == ["the part goes on past its declared box at +z: it reaches z = 60.0 mm, the declared "
                                 "part -10 .. 10 mm (grown by 8.0 mm for the placement): measured 70.0 mm along z, "
                                 "declared 20 mm"]


def test_a_plate_declared_as_a_t_joint_is_shorter_than_declared():
    t_joint_bounds = ((-100.0, -30.0, -10.0), (100.0, 30.0, 60.0))
    found = _check(_box_faces(*PLATE), t_joint_bounds, flat=False)
    assert found["findings"] == ["the part measured is 20.0 mm along z, the declared part 70 mm: the scans cover less "
                                 "of it than declared, or the part is not the one declared"]
    assert found["cut_faces"] == [] and found["thickness_mm"] is None


@pytest.mark.parametrize("declared, says", [(12.0, "declared 12 mm thick"), (30.0, "declared 30 mm thick")])
def test_a_plate_of_another_thickness_is_named(declared, says):
    """20 mm measured: declared 12 mm (the grown box still holds it: no cut) or 30 mm (within the
    5 mm an extent may fall short)."""
    h = declared / 2
    found = _check(_box_faces(*PLATE), ((-100.0, -30.0, -h), (100.0, 30.0, h)), flat=True, thickness=declared,
                   grow=8.0)
    assert found["findings"] == [f"the part measured is 20.0 mm thick (between its faces), {says}"]


def test_a_weld_cap_and_a_finer_weld_zone_do_not_thicken_the_plate():
    """A cap 3 mm high and 12 mm wide across the top face, its zone sampled 5 times as densely as
    the faces (the merge keeps the weld zone at full resolution)."""
    plate = _box_faces(*PLATE)
    x, y = np.meshgrid(np.arange(-6, 6, SPACING / 5), np.arange(-30, 30, SPACING / 5), indexing="ij")
    cap = np.column_stack([x.ravel(), y.ravel(), 10 + 3 * (1 - (x.ravel() / 6) ** 2)])
    found = _check(np.concatenate([plate, cap]), PLATE, flat=True, thickness=20.0)
    assert found["agrees"], found["findings"]
    assert found["thickness_mm"] == pytest.approx(20.0, abs=0.1)
