"""The robot program (scan plan) and the robot's real motion.

A pass is a linear sweep. The robot reports (and the manifest records) the nominal motion; the
real sensor pose differs by a per-pass rigid error E (absolute accuracy) and a speed ripple:
``T_world_sensor_true(t) = E @ T_nominal(s(t))`` with ``s(t) = v t + ripple``. The logged flange
poses follow the real path parameter s(t) (the encoders see it) but not E.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from schemas.manifest import NominalMotion, PassEntry
from schemas.simulation import RobotConfig, ScanPlanConfig, SpecimenConfig
from tasks.frames import frame_from_axes, invert, make_pose

__all__ = ["PlannedPass", "plan_passes", "PassMotion", "draw_motion", "pass_entry"]


@dataclass(frozen=True)
class PlannedPass:
    pass_id: str
    setup: str
    direction: str  # "along-length" | "along-width"
    T_world_sensor_start: np.ndarray  # nominal pose of the first profile
    travel_world: np.ndarray  # unit vector
    length_mm: float
    speed_mm_s: float
    profile_rate_hz: float

    @property
    def n_profiles(self) -> int:
        return int(round(self.length_mm / self.speed_mm_s * self.profile_rate_hz)) + 1

    @property
    def duration_s(self) -> float:
        return self.length_mm / self.speed_mm_s

    def nominal_sensor_poses(self, s_mm: np.ndarray) -> np.ndarray:
        """Nominal sensor poses (n, 4, 4) at path positions s (mm from the start)."""
        T = np.repeat(self.T_world_sensor_start[None], len(s_mm), axis=0)
        T[:, :3, 3] += s_mm[:, None] * self.travel_world[None, :]
        return T


def pass_entry(p: PlannedPass, robot: RobotConfig, content_sha256: str | None = None) -> PassEntry:
    """The pass as the sample manifest lists it: its nominal flange motion, the store's name."""
    T_sensor_flange = invert(np.asarray(robot.T_flange_sensor))
    motion = NominalMotion(
        T_world_flange_start=(p.T_world_sensor_start @ T_sensor_flange).tolist(),
        direction_world=tuple(float(v) for v in p.travel_world), speed_mm_s=p.speed_mm_s,
        profile_rate_hz=p.profile_rate_hz, length_mm=p.length_mm)
    return PassEntry(pass_id=p.pass_id, file=f"passes/{p.pass_id}.zarr", direction=p.direction,
                     n_profiles=p.n_profiles, duration_s=p.duration_s, nominal_motion=motion,
                     has_profile_poses=robot.log_profile_poses, content_sha256=content_sha256)


def _sensor_frame(travel: np.ndarray, view: np.ndarray, aim: np.ndarray, standoff: float) -> np.ndarray:
    """Sensor pose whose z looks along ``view`` at ``aim`` from ``standoff``; y as close to the
    travel direction as the view allows (an inclined sensor still travels straight)."""
    z = view / np.linalg.norm(view)
    y = travel - (travel @ z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return frame_from_axes(x, y, z, aim - standoff * z)


def plan_passes(plan: ScanPlanConfig, specimen: SpecimenConfig, robot: RobotConfig, *,
                z_top_mm: float, standoff_mm: float, setups: tuple[str, ...] = ("top", "bottom")) -> list[PlannedPass]:
    """The robot program for each setup, in the cell's (world) frame, relative to the nominal
    specimen placement (centred at the origin in x and y, top face at ``z_top_mm``)."""
    rate = robot.profile_rate_hz()
    length = specimen.length_mm + 2 * plan.margin_mm
    width = specimen.grip_width_mm + 2 * plan.margin_mm
    half_w = specimen.grip_width_mm / 2
    t = specimen.thickness_mm
    along_x = np.array([1.0, 0.0, 0.0])
    along_y = np.array([0.0, 1.0, 0.0])
    passes: list[PlannedPass] = []

    def add(setup: str, kind: str, T_start: np.ndarray, travel: np.ndarray, travel_len: float) -> None:
        tag = "L" if kind == "along-length" else "W"
        count = sum(1 for p in passes if p.setup == setup and p.direction == kind) + 1
        passes.append(PlannedPass(f"{setup}-{tag}{count:02d}", setup, kind, T_start, travel, travel_len,
                                  robot.speed_mm_s, rate))

    for setup in setups:
        for k, y_off in enumerate(plan.vertical_offsets_mm):
            tilt = np.radians(plan.inclination_deg) * (1 if k % 2 == 0 else -1)
            aim = np.array([-length / 2, y_off, z_top_mm])
            view = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])
            add(setup, "along-length", _sensor_frame(along_x, view, aim, standoff_mm), along_x, length)
        for side in (-1.0, 1.0):
            for roll in plan.side_rolls_deg:
                b = np.radians(roll)
                view = np.array([0.0, -side * np.sin(b), -np.cos(b)])
                aim = np.array([-length / 2, side * half_w, z_top_mm - 0.5 * t * np.sin(b)])
                add(setup, "along-length", _sensor_frame(along_x, view, aim, standoff_mm), along_x, length)
        for wp in plan.width_passes:
            g = np.radians(wp.pitch_deg)
            view = np.array([np.sin(g), 0.0, -np.cos(g)])
            aim = np.array([wp.x_mm, -width / 2, z_top_mm])
            add(setup, "along-width", _sensor_frame(along_y, view, aim, standoff_mm), along_y, width)
    return passes


@dataclass(frozen=True)
class PassMotion:
    """What really happened during one pass."""

    timestamp_s: np.ndarray  # (n,)
    T_world_sensor_true: np.ndarray  # (n, 4, 4)
    T_world_flange_logged: np.ndarray  # (n, 4, 4)
    T_error: np.ndarray  # (4, 4): the pass's rigid robot error E


def draw_motion(planned: PlannedPass, robot: RobotConfig, rng: np.random.Generator) -> PassMotion:
    n = planned.n_profiles
    t = np.arange(n) / planned.profile_rate_hz
    v = planned.speed_mm_s
    phase = rng.uniform(0, 2 * np.pi)
    omega = 2 * np.pi * robot.speed_ripple_hz
    amplitude = robot.speed_ripple_fraction * v / omega
    s = v * t + amplitude * (np.sin(omega * t + phase) - np.sin(phase))
    rot = Rotation.from_rotvec(np.radians(rng.normal(0, robot.pose_error_rotation_deg, 3))).as_matrix()
    T_error = make_pose(rot, rng.normal(0, robot.pose_error_translation_mm, 3))
    T_nominal = planned.nominal_sensor_poses(s)
    T_true = T_error[None] @ T_nominal
    T_flange_sensor = np.asarray(robot.T_flange_sensor)
    logged = T_nominal @ invert(T_flange_sensor)[None]
    logged[:, :3, 3] += rng.normal(0, robot.encoder_noise_mm, (n, 3))
    return PassMotion(timestamp_s=t, T_world_sensor_true=T_true, T_world_flange_logged=logged, T_error=T_error)
