"""Where each planned pass will measure the weld, before it is scanned: its nominal sweep against
the drawn part.

A robot pass (``schemas.manifest.PassEntry``) is a straight sweep of the line scanner: the laser
fans out in the sensor's x-z plane from the emitter (``ScannerSettings``), and the plane moves
along ``nominal_motion.direction_world`` for ``length_mm``. A point of a weld line (the manifest's
drawn lines, put in the cell by its setup's ``T_world_specimen_nominal``) is predicted measured by
the pass when

- the laser plane crosses it during the sweep;
- it lies inside the fan (``points_per_profile`` columns ``x_spacing_mm`` apart at
  ``reference_distance_mm``) and within the depth range ``z_range_mm``;
- the emitter and the camera both see it: neither sight line passes through the drawn part
  (dog-bone and plate: their bounding box; T-joint and cruciform: the base and stem plates as
  boxes; a drawing: its mesh).

It is a prediction from the drawing: weld beads, the fixture and the robot's real path are not in
it. What it is for: a scan followed as it comes in says what the next pass will add, and a plan
can be checked for weld lines no pass reaches.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_opening

from schemas.manifest import (UNITS_TO_MM, CruciformSpecimen, DogBoneSpecimen, DrawingSpecimen, PassEntry, SampleManifest,
                              TJointSpecimen)

__all__ = ["LineCoverage", "PlanCoverage", "plan_coverage", "part_mesh", "intervals", "dog_bone_half_width"]

_SIGHT_EPS_MM = 0.05  # a sight line starts this far off the surface point (toward its eye)


@dataclass(frozen=True)
class LineCoverage:
    """One weld line sampled every ``step_mm`` of its length: ``along_mm`` (k,) the samples'
    positions along it from its first point, ``seen`` (passes, k) whether each pass will measure
    each sample, ``on_part`` (k,) whether the sample lies on the drawn part (a dog-bone's lines
    run past its narrower waist)."""

    name: str
    along_mm: np.ndarray
    seen: np.ndarray
    on_part: np.ndarray

    def reached(self) -> list[tuple[float, float]]:
        """The stretches some pass of the plan reaches, (from, to) mm along the line."""
        return intervals(self.along_mm, self.seen.any(axis=0))


@dataclass(frozen=True)
class PlanCoverage:
    """The plan's predicted weld coverage: ``pass_ids`` in manifest order, one ``LineCoverage``
    per weld line; ``predicted`` False where it cannot be said (a setup with no nominal placement,
    imported scans): ``reason`` says why."""

    pass_ids: list[str]
    lines: list[LineCoverage]
    predicted: bool = True
    reason: str = ""

    def adds(self, index: int, landed: set[int]) -> list[tuple[str, list[tuple[float, float]], list[tuple[float, float]]]]:
        """What pass ``index`` will measure, per weld line it reaches: (line, its stretches, the
        stretches no pass in ``landed`` measured), stretches as (from, to) mm along the line."""
        out = []
        for line in self.lines:
            mine = line.seen[index]
            if not mine.any():
                continue
            before = line.seen[sorted(landed)].any(axis=0) if landed else np.zeros_like(mine)
            out.append((line.name, intervals(line.along_mm, mine), intervals(line.along_mm, mine & ~before)))
        return out

    def unreached(self) -> list[tuple[str, list[tuple[float, float]]]]:
        """The stretches of each weld line that no pass of the plan reaches."""
        return [(line.name, stretches) for line in self.lines
                if (stretches := intervals(line.along_mm, line.on_part & ~line.seen.any(axis=0)))]


def intervals(along_mm: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """The runs of ``mask`` as (first, last) positions of ``along_mm``."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return []
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(along_mm[a]), float(along_mm[b])) for a, b in zip(starts, ends)]


def dog_bone_half_width(x_mm, *, gauge_length_mm: float, gauge_width_mm: float, grip_width_mm: float,
                        transition_radius_mm: float) -> np.ndarray:
    """A dog-bone's half width at ``x_mm`` along its length (its centre at 0): the gauge width
    within the gauge length, then arcs of ``transition_radius_mm`` out to the grip width."""
    ax = np.abs(np.asarray(x_mm, dtype=float))
    g, r = gauge_length_mm / 2, transition_radius_mm
    d = ax - g
    arc = gauge_width_mm / 2 + r - np.sqrt(np.maximum(r * r - np.clip(d, 0, r) ** 2, 0.0))
    return np.where(ax <= g, gauge_width_mm / 2, np.minimum(arc, grip_width_mm / 2))


def _on_the_part(spec, points_mm: np.ndarray) -> np.ndarray:
    """Which points of a weld line lie on the drawn part: a dog-bone's lines run across its grip
    width (``schemas.manifest.dog_bone_weld_lines``), wider than the part at the weld."""
    if not isinstance(spec, DogBoneSpecimen):
        return np.ones(len(points_mm), bool)
    half = dog_bone_half_width(points_mm[:, 0], gauge_length_mm=spec.gauge_length_mm, gauge_width_mm=spec.gauge_width_mm,
                               grip_width_mm=spec.grip_width_mm, transition_radius_mm=spec.transition_radius_mm)
    return np.abs(points_mm[:, 1]) <= half


def _box(lo, hi):
    import open3d as o3d

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    box = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    box.translate(lo)
    return np.asarray(box.vertices), np.asarray(box.triangles)


def part_mesh(manifest: SampleManifest, sample_dir: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The drawn part as triangles in its specimen frame, mm: (vertices (n, 3), triangles (m, 3)).
    A drawing is read from ``sample_dir``; the other kinds are built of boxes."""
    spec = manifest.specimen
    if isinstance(spec, DrawingSpecimen):
        import open3d as o3d

        if sample_dir is None:
            raise ValueError("a drawing specimen's mesh is read from its sample folder: sample_dir is needed")
        mesh = o3d.io.read_triangle_mesh(str(Path(sample_dir) / spec.file))
        return np.asarray(mesh.vertices) * UNITS_TO_MM[spec.units], np.asarray(mesh.triangles)
    if isinstance(spec, (TJointSpecimen, CruciformSpecimen)):
        x, y, z = spec.base_length_mm / 2, spec.base_width_mm / 2, spec.base_thickness_mm / 2
        sx, st = spec.stem_x_mm, spec.stem_thickness_mm / 2
        boxes = [((-x, -y, -z), (x, y, z)), ((sx - st, -y, z), (sx + st, y, z + spec.stem_height_mm))]
        if isinstance(spec, CruciformSpecimen):
            boxes.append(((sx - st, -y, -z - spec.stem_height_mm), (sx + st, y, -z)))
    else:
        boxes = [spec.bounds_mm()]
    parts = [_box(lo, hi) for lo, hi in boxes]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return np.concatenate([v for v, _ in parts]), np.concatenate([t + o for (_, t), o in zip(parts, offsets)])


def _resampled(points_mm: np.ndarray, step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A polyline sampled every ``step_mm`` of its length (its last point included): (positions
    along it, points)."""
    seg = np.linalg.norm(np.diff(points_mm, axis=0), axis=1)
    at = np.r_[0.0, np.cumsum(seg)]
    along = np.r_[np.arange(0.0, at[-1], step_mm), at[-1]]
    return along, np.column_stack([np.interp(along, at, points_mm[:, k]) for k in range(3)])


def _pass_sees(entry: PassEntry, scanner, points_world: np.ndarray, scene) -> np.ndarray:
    """Which of ``points_world`` (n, 3) the pass will measure (see the module's description)."""
    import open3d as o3d

    motion = entry.nominal_motion
    T = np.asarray(motion.T_world_flange_start, np.float64) @ np.asarray(scanner.T_flange_sensor, np.float64)
    R, origin = T[:3, :3], T[:3, 3]
    d = np.asarray(motion.direction_world, np.float64)
    normal = R[:, 1]  # the laser plane is the sensor's x-z plane
    rate = float(d @ normal)
    seen = np.zeros(len(points_world), bool)
    if abs(rate) < 1e-6:  # a sweep within its own laser plane crosses nothing
        return seen
    s = (points_world - origin) @ normal / rate  # how far along the sweep the plane crosses each point
    q = (points_world - origin - s[:, None] * d) @ R  # in the sensor frame at that moment (y ~ 0)
    near, far = scanner.z_range_mm
    half_tan = (scanner.points_per_profile - 1) / 2 * scanner.x_spacing_mm / scanner.reference_distance_mm
    inside = ((s >= 0) & (s <= motion.length_mm) & (q[:, 2] >= near) & (q[:, 2] <= far)
              & (np.abs(q[:, 0]) <= half_tan * q[:, 2]))
    if not inside.any():
        return seen
    idx = np.flatnonzero(inside)
    p = points_world[idx]
    emitter = origin + s[idx, None] * d
    camera = emitter + R @ np.asarray(scanner.camera_offset_mm, np.float64)
    clear = np.ones(len(idx), bool)
    for eye in (emitter, camera):
        ray = eye - p
        length = np.linalg.norm(ray, axis=1)
        direction = ray / length[:, None]
        rays = np.c_[p + _SIGHT_EPS_MM * direction, direction].astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        clear &= ~(hit < length - _SIGHT_EPS_MM)
    seen[idx] = clear
    return seen


def plan_coverage(manifest: SampleManifest, sample_dir: Path | None = None, *, step_mm: float = 1.0) -> PlanCoverage:
    """Each robot pass's predicted measurement of each weld line (``PlanCoverage``), from the
    manifest alone (a drawing specimen's mesh from ``sample_dir``)."""
    import open3d as o3d

    passes = manifest.passes()
    ids = [entry.pass_id for _, entry in passes]
    lines = manifest.weld_lines()
    if not lines or manifest.specimen is None:
        return PlanCoverage(ids, [], predicted=False, reason="the manifest draws no weld line on a part")
    if manifest.surfaces or any(not isinstance(entry, PassEntry) for _, entry in passes):
        return PlanCoverage(ids, [], predicted=False, reason="imported scans carry no planned sweep")
    unplaced = [s.name for s in manifest.setups if s.T_world_specimen_nominal is None]
    if unplaced:
        return PlanCoverage(ids, [], predicted=False,
                            reason=f"setup {unplaced[0]} gives no T_world_specimen_nominal: where the part lies is unknown")
    vertices, triangles = part_mesh(manifest, sample_dir)
    sampled = [_resampled(np.asarray(line.points_mm, np.float64), step_mm) for line in lines]
    on_part = [_on_the_part(manifest.specimen, points) for _, points in sampled]
    seen = [np.zeros((len(passes), len(along)), bool) for along, _ in sampled]
    placements = {s.name: np.asarray(s.T_world_specimen_nominal, np.float64) for s in manifest.setups}
    for setup_name in placements:
        T = placements[setup_name]
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor((vertices @ T[:3, :3].T + T[:3, 3]).astype(np.float32)),
                            o3d.core.Tensor(triangles.astype(np.uint32)))
        for k, (name, entry) in enumerate(passes):
            if name != setup_name:
                continue
            for n, (_, points) in enumerate(sampled):
                # a stretch shorter than 3 samples is dropped: a line's end seen past a plate's edge
                sees = _pass_sees(entry, manifest.scanner, points @ T[:3, :3].T + T[:3, 3], scene) & on_part[n]
                seen[n][k] = binary_opening(sees, np.ones(3, bool))
    return PlanCoverage(ids, [LineCoverage(line.name, along, s, on) for line, (along, _), s, on
                              in zip(lines, sampled, seen, on_part)])
