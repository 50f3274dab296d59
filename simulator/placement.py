"""Putting the specimen on the fixture by hand: nominal pose plus a random offset and yaw; the
plate comes to rest on the two support blocks (the down-facing surface touches both)."""

from __future__ import annotations

import numpy as np

from schemas.manifest import PositionerTurn
from schemas.simulation import FixtureConfig, PlacementConfig, SimulationConfig
from simulator.specimen import Specimen
from tasks.frames import apply, make_pose, rotation_deg, translation, turn_about_axis

__all__ = ["place_on_fixture", "nominal_placement", "placement_tolerance_mm", "positioner_turn", "turned_setup",
           "resting_plate_mm", "FLIP"]

FLIP = make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
"""Turned over by hand: 180 degrees about the specimen's length axis."""


def _contact_heights(vertices: np.ndarray, fixture: FixtureConfig) -> np.ndarray:
    bx, by, _ = fixture.block_size_mm
    out = []
    for cx in fixture.block_centres_x_mm:
        inside = (np.abs(vertices[:, 0] - cx) <= bx / 2) & (np.abs(vertices[:, 1]) <= by / 2)
        if not inside.any():
            raise ValueError(f"the specimen does not rest on the support block at x = {cx} mm")
        out.append(vertices[inside, 2].min())
    return np.array(out)


def nominal_placement(fixture: FixtureConfig, thickness_mm: float, *, flipped: bool) -> np.ndarray:
    """T_world_specimen as the fixture is drawn: centred on the blocks, flat on them."""
    return translation([0.0, 0.0, fixture.block_size_mm[2] + thickness_mm / 2]) @ (FLIP if flipped else np.eye(4))


def placement_tolerance_mm(placement: PlacementConfig, half_width_mm: float, weld_centre_x_mm: float = 0.0) -> float:
    """How far a point of the weld line (specimen x = ``weld_centre_x_mm``, |y| <= ``half_width_mm``)
    can stray along the specimen's x from where the nominal placement puts it: the hand's offset and
    yaw (``place_on_fixture``), plus 0.5 mm for settling on the blocks."""
    yaw = np.radians(placement.yaw_deg)
    return float(placement.translation_mm + half_width_mm * np.sin(yaw)
                 + abs(weld_centre_x_mm) * (1 - np.cos(yaw)) + 0.5)


def place_on_fixture(specimen: Specimen, fixture: FixtureConfig, placement: PlacementConfig,
                     rng: np.random.Generator, *, flipped: bool) -> np.ndarray:
    """T_world_specimen for one setup."""
    dx, dy = rng.uniform(-placement.translation_mm, placement.translation_mm, 2)
    yaw = rng.uniform(-placement.yaw_deg, placement.yaw_deg)
    T = translation([dx, dy, 0.0]) @ rotation_deg("z", yaw) @ (FLIP if flipped else np.eye(4))
    vertices = specimen.mesh.vertices
    x1, x2 = fixture.block_centres_x_mm
    for _ in range(3):  # settle: level the two contacts, then lower onto the blocks
        z1, z2 = _contact_heights(apply(T, vertices), fixture)
        pitch = np.degrees(np.arctan2(z2 - z1, x2 - x1))
        centre = np.array([(x1 + x2) / 2, 0.0, 0.0])
        T = translation(centre) @ rotation_deg("y", pitch) @ translation(-centre) @ T
    z = _contact_heights(apply(T, vertices), fixture).min()
    return translation([0.0, 0.0, fixture.block_size_mm[2] - z]) @ T


def resting_plate_mm(config: SimulationConfig) -> tuple[float, float]:
    """(thickness, half width) of the plate that rests on the support blocks: a dog-bone's
    (its grips' width), a T-joint's or a cruciform's base plate."""
    tj = config.tjoint
    if tj is None:
        return config.specimen.thickness_mm, config.specimen.grip_width_mm / 2
    return tj.base_thickness_mm, tj.base_width_mm / 2


def positioner_turn(config: SimulationConfig, *, from_setup: str) -> PositionerTurn:
    """The positioner's turn as calibrated (the manifest's): its axis by default along the part's
    length through its mid-plane at the nominal placement."""
    pc = config.positioner
    thickness, _ = resting_plate_mm(config)
    point = pc.axis_point_mm if pc.axis_point_mm is not None else (0.0, 0.0, config.fixture.block_size_mm[2] + thickness / 2)
    return PositionerTurn(from_setup=from_setup, axis_point_mm=tuple(float(v) for v in point),
                          axis_direction=tuple(float(v) for v in pc.axis_direction), angle_deg=pc.angle_deg,
                          tolerance_mm=pc.tolerance_mm)


def turned_setup(config: SimulationConfig, *, from_setup: str) -> tuple[PositionerTurn, np.ndarray, str]:
    """A setup the positioner turned from ``from_setup`` (at its nominal placement), as a
    manifest says it: the calibrated turn, T_world_specimen_nominal, the description."""
    turn = positioner_turn(config, from_setup=from_setup)
    nominal = turn_about_axis(turn.axis_point_mm, turn.axis_direction, turn.angle_deg) @ \
        nominal_placement(config.fixture, resting_plate_mm(config)[0], flipped=False)
    return turn, nominal, f"turned {turn.angle_deg:g} deg by the positioner, still clamped"
