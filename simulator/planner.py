"""Plan a scan from the part's drawing (``weldrecon plan``): the passes and the stickers, chosen
so that the weld toes are measured at full resolution from both sides, every face is seen, every
pair of overlapping passes shares at least ``stickers.min_common`` whole stickers not in a line
wherever the part lies within its placement tolerance, and the setups share enough stickers to
be matched without doubt; the fastest such plan the search finds.

The plan is checked with the simulated cell's own models: each candidate pass is rendered
noise-free (about 0.5 mm apart) against the part as drawn (its weld from the part's ranges, with
the planning seed), on the fixture, at its nominal placement and at the corners of its placement
tolerance. A sticker counts as seen by a pass only when the pass sees it whole, grown by the
robot's and the hand's errors, at every one of those placements.

The search (a dog-bone; ``PlanRefused`` for other parts until they are planned) runs over pass
families, fastest first:

- ``face``: rows along the part's length over its upward face, at the scanner's reference
  distance, as few as leave room for stickers between neighbours;
- ``side``: one row along each side wall, rolled toward it (the walls tie the setups);
- ``end``: one sweep across each end, pitched toward it;
- ``weld``: two sweeps along the weld, pitched either way across it (each toe lit from over the
  plate and from over the weld), each aimed a little off the weld's centre so that its line also
  covers a strip of plate where stickers may go, raised off the reference distance if the strip
  needs it (as long as the points stay as close as the full-resolution scan's).

Every pass runs at the part's robot speed and profile spacing. A plan that meets no requirement
set is refused (``PlanRefused``), naming the face, toe or pass pair that fails.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from schemas.scan_plan import (FaceCoverage, PlanOverlap, PlanPass, PlanRequirements, PlanSticker, ScanPlan, SetupLink,
                               ToeCoverage)
from schemas.manifest import CruciformSpecimen, DogBoneSpecimen, SampleManifest, TJointSpecimen
from schemas.simulation import (FixtureConfig, PlacementConfig, RobotConfig, ScannerConfig, SimulationConfig,
                                SpecimenConfig, StickerConfig, TJointConfig, WeldConfig)
from schemas.truth import PointLabel
from simulator.coverage import CoverageMap, cell_keys, face_params, spread_off_line_mm
from simulator.fixture import build_fixture
from simulator.placement import place_on_fixture
from simulator.robot import PlannedPass, _sensor_frame
from simulator.scanner import LineScanner
from simulator.scene import Scene, StickerSet
from simulator.specimen import Face, Specimen, build_specimen
from simulator.stickers import StickerPlacementError, place_stickers, sticker_candidates
from simulator.tjoint import TJoint, build_tjoint, tjoint_sticker_candidates
from tasks.arrays import distinct
from tasks.frames import invert, rotation_deg, translation

__all__ = ["PlanRefused", "plan_scan", "evaluate_passes", "planned_passes", "Evaluation", "PLANNING_SEED_OFFSET",
           "part_from_manifest"]

log = logging.getLogger(__name__)

RENDER_STEP_MM = 0.5
CELL_MM = 2.0
ROBOT_MARGIN_MM = 0.8  # a sticker grown by this for the robot's own pose error (3 sigma of 0.25 mm, and its tilt)
TOE_STEP_MM = 2.0
TOE_RADIUS_MM = 1.0  # a toe station is measured by the points this close
SIDE_LEAN = math.sin(math.radians(10.0))
"""A ray lights a toe from over the plate (or from over the weld) when it leans at least 10 deg
that way across the toe; a ray straight down the plate's normal lights it from neither side (it
sees both surfaces at the toe, but one viewing direction, where the paper's plan and ours look
from two)."""
SPREAD_DEG = 20.0
"""A fillet's toe is measured from two directions when two rays that reach it within the
incidence limit lean across it at least 20 deg apart (SIDE_LEAN's -10 and +10 deg are as far
apart). It cannot be lit from over the weld as a butt weld's toe is: a stem toe's rays all come
from above it, down the stem; a base toe's from over the weld must clear the stem (a 60 mm stem
beside a 7 mm leg: 6.6 deg at most)."""
DETECTABLE = (0.8, 1.2)
"""A pass finds a sticker where the points along its line lie this many times the pass's median
spacing apart: the target search looks for circles of one radius on a grid of the pass's median
spacing (tasks.target_search: HoughCircles from 0.6 to 1.3 of it), so a sticker on a face seen
more or less obliquely than most of the pass looks like an ellipse it misses (a pass rolled 55 deg
along a 90 deg edge finds the stickers on the face it meets at 55 deg and none on the other)."""
PLACEMENT_TRIES = 5
SIDE_ROLLS_DEG = (45.0, 50.0, 40.0, 55.0, 35.0)  # tried in this order: the walls and the top edge alike oblique first
END_PITCHES_DEG = (30.0, 25.0, 35.0)
WELD_PITCHES_DEG = (25.0, 20.0, 30.0)
PLANNING_SEED_OFFSET = 7919
"""The part's weld for planning is drawn with seed ``part.seed + PLANNING_SEED_OFFSET``: a weld from
the part's ranges that is not the simulated sample's own."""


class PlanRefused(ValueError):
    """No plan the search tried meets the requirements; ``problems`` name the face, toe or pass pair."""

    def __init__(self, problems: list[str]):
        super().__init__("; ".join(problems))
        self.problems = problems


# ---------------------------------------------------------------------------------------------
# The part as drawn, on the fixture


def part_from_manifest(manifest: SampleManifest, *, source: str) -> SimulationConfig:
    """The part a sample manifest describes, to plan its next scan: its dog-bone, T-joint or
    cruciform, its weld's treatment, its stickers' size, its scanner and the speed and profile
    rate of its first pass (the robot's defaults without one). The weld's ranges (a butt cap's,
    a fillet's legs) are the simulator's defaults. The fixture: a dog-bone on two support blocks
    60 mm long under the grips, 45 mm in from the ends; a T-joint or a cruciform on two blocks
    30 mm long, 25 mm in from the base plate's ends, 20 mm taller than the stem (turned over, it
    hangs between them). Refused (``PlanRefused``, naming ``source``) for a part the planner has
    no passes for."""
    part = manifest.specimen
    if not isinstance(part, (DogBoneSpecimen, TJointSpecimen, CruciformSpecimen)):
        kind = getattr(part, "kind", None) or "no specimen"
        raise PlanRefused([f"{source}: part: {kind} is not planned yet (the planner's pass families are a "
                           "dog-bone's, a T-joint's and a cruciform's)"])
    if manifest.sticker_diameter_mm is None or manifest.scanner is None:
        raise PlanRefused([f"{source}: the manifest gives no sticker_diameter_mm or scanner: a plan needs both"])
    sc = manifest.scanner
    robot = RobotConfig(T_flange_sensor=sc.T_flange_sensor)
    passes = [entry for _, entry in manifest.passes() if getattr(entry, "nominal_motion", None) is not None]
    if passes:
        motion = passes[0].nominal_motion
        robot = robot.model_copy(update={"speed_mm_s": motion.speed_mm_s,
                                         "profile_spacing_mm": motion.speed_mm_s / motion.profile_rate_hz})
    common = dict(preset="manifest", seed=0, sample_id=manifest.sample_id,
                  weld=WeldConfig(treatment=manifest.weld.treatment if manifest.weld is not None else "as-welded"),
                  stickers=StickerConfig(diameter_mm=manifest.sticker_diameter_mm),
                  scanner=ScannerConfig(model=sc.model, points_per_profile=sc.points_per_profile,
                                        x_spacing_mm=sc.x_spacing_mm, reference_distance_mm=sc.reference_distance_mm,
                                        z_range_mm=sc.z_range_mm, z_resolution_mm=sc.z_resolution_mm,
                                        camera_offset_mm=sc.camera_offset_mm),
                  robot=robot)
    if not isinstance(part, DogBoneSpecimen):
        if abs(part.stem_x_mm) > 0.5:
            raise PlanRefused([f"{source}: specimen: the planner draws the stem across the base plate's middle "
                               f"(stem_x_mm 0); this part's is at {part.stem_x_mm:g} mm"])
        L, W, H = part.base_length_mm, part.base_width_mm, part.stem_height_mm
        try:
            tjoint = TJointConfig(stems="both" if isinstance(part, CruciformSpecimen) else "one", base_length_mm=L,
                                  base_width_mm=W, base_thickness_mm=part.base_thickness_mm, stem_height_mm=H,
                                  stem_thickness_mm=part.stem_thickness_mm)
        except ValueError as exc:
            raise PlanRefused([f"{source}: specimen: {exc.errors()[0]['msg'] if hasattr(exc, 'errors') else exc}"]) \
                from None
        fixture = FixtureConfig(plate_size_mm=(L + 160.0, max(320.0, W + 200.0), 10.0),
                                block_size_mm=(30.0, min(60.0, 0.5 * W), H + 20.0),
                                block_centres_x_mm=(-(L / 2 - 25.0), L / 2 - 25.0))
        return SimulationConfig(tjoint=tjoint, fixture=fixture, **common)
    lines = manifest.weld_lines() or []
    xs = [p[0] for line in lines for p in line.points_mm]
    if not xs or max(abs(x) for x in xs) > 0.5:
        raise PlanRefused([f"{source}: weld: the planner draws a butt weld across the middle (x = 0); this part's weld "
                           f"lines lie at x = {min(xs, default=float('nan')):g}..{max(xs, default=float('nan')):g} mm"])
    L, W = part.length_mm, part.grip_width_mm
    fixture = FixtureConfig(plate_size_mm=(L + 230.0, max(320.0, W + 220.0), 15.0),
                            block_size_mm=(60.0, min(50.0, 0.8 * W), 40.0), block_centres_x_mm=(-(L / 2 - 45.0), L / 2 - 45.0))
    return SimulationConfig(
        specimen=SpecimenConfig(length_mm=L, grip_width_mm=W, gauge_width_mm=part.gauge_width_mm,
                                gauge_length_mm=part.gauge_length_mm, transition_radius_mm=part.transition_radius_mm,
                                thickness_mm=part.thickness_mm),
        fixture=fixture, **common)


@dataclass
class _Part:
    config: SimulationConfig
    specimen: Specimen | TJoint  # as drawn: a dog-bone's plates in line
    scenes: dict[tuple[str, int], Scene]  # per setup and shape (0: as drawn, 1: misaligned the most)
    placements: list[tuple[int, np.ndarray]]  # (shape, perturbation P, world frame): as drawn at its nominal
    # placement first, then at the corners of the placement tolerance, then the other shape
    z_top_mm: float


def _empty(radius: float) -> StickerSet:
    return StickerSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.uint8), radius, 0.0)


def planning_mesh(config: SimulationConfig) -> SimulationConfig:
    """The part's config with a true mesh fine enough to plan on (the scanner is rendered about
    0.5 mm apart): 1 mm on the plates, 0.2 mm over the weld, 0.1 mm at its toes; a T-joint's
    sections 1 mm apart along its welds."""
    m = config.mesh
    update = {"mesh": m.model_copy(update={
        "plate_dx_mm": max(m.plate_dx_mm, 1.0), "weld_dx_mm": max(m.weld_dx_mm, 0.2),
        "toe_dx_mm": max(m.toe_dx_mm, 0.1), "across_nodes": min(m.across_nodes, 200),
        "wall_rows": min(m.wall_rows, 11)})}
    if config.tjoint is not None:
        update["tjoint"] = config.tjoint.model_copy(update={"along_weld_dx_mm": max(config.tjoint.along_weld_dx_mm, 1.0)})
    return config.model_copy(update=update)


def _part(config: SimulationConfig, req: PlanRequirements) -> _Part:
    """The part as drawn (its weld from the part's ranges with the planning seed; a dog-bone's
    plates in line), and a dog-bone with its plates misaligned the most the weld's ranges allow:
    where a real part's ends may lie (a T-joint's plates are drawn square). Each rests on the
    support blocks as ``place_on_fixture`` settles it."""
    drawn = planning_mesh(config)
    w = drawn.weld
    shapes = []
    if drawn.tjoint is not None:
        shapes.append(build_tjoint(drawn.tjoint, w, drawn.mesh, np.random.default_rng(config.seed + PLANNING_SEED_OFFSET)))
    else:
        for axial, angular in ((0.0, 0.0), (w.axial_misalignment_mm[1], w.angular_misalignment_deg[1])):
            weld = w.model_copy(update={"axial_misalignment_mm": (axial, axial),
                                        "angular_misalignment_deg": (angular, angular)})
            shapes.append(build_specimen(drawn.specimen, weld, drawn.mesh,
                                         np.random.default_rng(config.seed + PLANNING_SEED_OFFSET)))
    fixture = build_fixture(config.fixture)
    radius = config.stickers.diameter_mm / 2
    t, yaw = req.placement_tolerance_mm, req.placement_yaw_deg
    corners = [(sx * t, sy * t, sz * yaw) for sx, sy, sz in itertools.product((-1, 1), repeat=3)] if t or yaw else []
    placements = [(0, np.eye(4))] + [(0, translation([dx, dy, 0.0]) @ rotation_deg("z", dz)) for dx, dy, dz in corners]
    placements += [(k, np.eye(4)) for k in range(1, len(shapes))]
    still = PlacementConfig(translation_mm=0.0, yaw_deg=0.0)
    scenes = {}
    for setup in req.setups:
        for k, shape in enumerate(shapes):
            T = place_on_fixture(shape, config.fixture, still, np.random.default_rng(0), flipped=(setup == "bottom"))
            scenes[(setup, k)] = Scene(shape.mesh, T, fixture, _empty(radius), _empty(radius))
    thickness = config.specimen.thickness_mm if config.tjoint is None else config.tjoint.base_thickness_mm
    return _Part(config, shapes[0], scenes, placements, config.fixture.block_size_mm[2] + thickness)


# ---------------------------------------------------------------------------------------------
# Rendering a pass (noise-free, coarse)


@dataclass(frozen=True)
class _View:
    """What one pass sees at one placement: specimen-frame points, their faces and the laser
    rays' directions (specimen frame)."""

    face: np.ndarray
    points: np.ndarray
    rays: np.ndarray
    spacing_ratio: np.ndarray  # the point spacing along the line here over the pass's median (see DETECTABLE)


class _Renderer:
    def __init__(self, part: _Part):
        self.part = part
        sc = part.config.scanner
        self.col_stride = max(1, int(RENDER_STEP_MM / sc.x_spacing_mm))
        n_cols = max(2, math.ceil(sc.points_per_profile / self.col_stride))
        self.scanner = LineScanner(sc.model_copy(update={"points_per_profile": n_cols,
                                                          "x_spacing_mm": sc.x_spacing_mm * self.col_stride}))
        self._cache: dict[tuple, _View] = {}

    def view(self, p: PlannedPass, placement: int) -> _View:
        """The pass over the part at ``_Part.placements[placement]``: at a corner of the tolerance
        the part is moved by the corner's perturbation P, rendered as the sensor moved by P^-1 (the
        fixture, which does not move with the part, is then off by P: a few tenths of a mm)."""
        key = (p.setup, placement, p.T_world_sensor_start.tobytes(), p.travel_world.tobytes(), p.length_mm)
        if key not in self._cache:
            shape, P = self.part.placements[placement]
            self._cache[key] = self._render(p, self.part.scenes[(p.setup, shape)], invert(P))
        return self._cache[key]

    def _render(self, p: PlannedPass, scene: Scene, P_inv: np.ndarray) -> _View:
        step = max(RENDER_STEP_MM, p.speed_mm_s / p.profile_rate_hz)
        s = np.arange(0.0, p.length_mm + 1e-9, step)
        T = P_inv[None] @ p.nominal_sensor_poses(s)
        faces, points, rays, spacing = [], [], [], []
        R_specimen_world = scene.T_specimen_world[:3, :3]
        for start in range(0, len(T), 2000):
            block = T[start:start + 2000]
            prof = self.scanner.render(scene, block, None, keep_specimen_points=True)
            returned = prof.label == PointLabel.VALID
            seen = returned & (prof.face_id != 255)
            d = np.einsum("mij,nj->mni", block[:, :3, :3], self.scanner.fan)
            hits = prof.point_specimen.astype(np.float64)  # specimen frame
            hits[~returned] = np.nan
            gap = np.linalg.norm(np.diff(hits, axis=1), axis=2)  # between neighbouring columns
            local = np.fmin(np.pad(gap, ((0, 0), (1, 0)), constant_values=np.nan),
                            np.pad(gap, ((0, 0), (0, 1)), constant_values=np.nan))
            faces.append(prof.face_id[seen])
            points.append(hits[seen])
            rays.append(d[seen] @ R_specimen_world.T)
            spacing.append(local[seen])
        local = np.concatenate(spacing)
        # the pass's median spacing, as the target search takes it (tasks.target_search.GridSpacing)
        median = float(np.nanmedian(local)) if np.isfinite(local).any() else np.nan
        return _View(np.concatenate(faces), np.concatenate(points), np.concatenate(rays), local / median)


# ---------------------------------------------------------------------------------------------
# Pass families of a dog-bone


@dataclass(frozen=True)
class _Choice:
    rows: int
    side_roll_deg: float
    side_aim: float  # 0: at the wall's middle, 1: at the top edge
    end_pitch_deg: float
    end_inset_mm: float
    weld_pitch_deg: float
    weld_offset_mm: float
    weld_standoff_mm: float


def _lean(view: np.ndarray, travel: np.ndarray) -> tuple[float, float]:
    """(tilt along the travel, roll across it) of a view direction, degrees from straight down."""
    across = np.cross(np.array([0.0, 0.0, 1.0]), travel)
    return (float(np.degrees(np.arcsin(np.clip(view @ travel, -1, 1)))),
            float(np.degrees(np.arcsin(np.clip(view @ across, -1, 1)))))


@dataclass
class _Family:
    passes: list[PlannedPass] = field(default_factory=list)
    info: list[dict] = field(default_factory=list)

    def add(self, setup: str, purpose: str, label: str, view: np.ndarray, aim: np.ndarray, travel: np.ndarray,
            length: float, standoff: float, speed: float, rate: float) -> None:
        """A pass looking along ``view`` at ``aim`` from ``standoff``, named by its setup, purpose
        and count (top-F01, ...)."""
        count = sum(1 for q in self.info if q["setup"] == setup and q["purpose"] == purpose) + 1
        tag = {"face": "F", "side": "S", "end": "E", "weld": "W"}[purpose]
        view = view / np.linalg.norm(view)
        self.passes.append(PlannedPass(f"{setup}-{tag}{count:02d}", setup, label,
                                       _sensor_frame(travel, view, aim, standoff), travel, length, speed, rate))
        tilt, roll = _lean(view, travel)
        self.info.append({"setup": setup, "purpose": purpose, "standoff": standoff, "tilt": tilt, "roll": roll})


def _dog_bone_passes(part: _Part, choice: _Choice, req: PlanRequirements) -> _Family:
    cfg = part.config
    sp, sc, robot = cfg.specimen, cfg.scanner, cfg.robot
    ref = sc.reference_distance_mm
    rate = robot.profile_rate_hz()
    v = robot.speed_mm_s
    L, W, t = sp.length_mm, sp.grip_width_mm, sp.thickness_mm
    c = part.specimen.weld_top.centre_x_mm
    w_weld = float(part.specimen.half_width(np.array([c]))[0]) * 2
    margin = 10.0 + req.placement_tolerance_mm
    fan = sc.points_per_profile * sc.x_spacing_mm  # the line's length at the reference distance
    z_top = part.z_top_mm
    x_axis, y_axis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    family = _Family()

    def add(setup, purpose, label, view, aim, travel, length, standoff):
        family.add(setup, purpose, label, view, aim, travel, length, standoff, v, rate)

    for setup in req.setups:
        # face rows: the outer lines reach 2 mm past the edges
        n = choice.rows
        pitch = (W + 4.0 - fan) / (n - 1) if n > 1 else 0.0
        for k in range(n):
            y = (k - (n - 1) / 2) * pitch
            add(setup, "face", "along-length", np.array([0.0, 0.0, -1.0]), np.array([-L / 2 - margin, y, z_top]),
                x_axis, L + 2 * margin, ref)
        b = math.radians(choice.side_roll_deg)
        for side in (-1.0, 1.0):
            view = np.array([0.0, -side * math.sin(b), -math.cos(b)])
            # aimed at the wall's middle, or up at the top edge to see more of the top face
            aim = np.array([-L / 2 - margin, side * W / 2, z_top - (1 - choice.side_aim) * 0.5 * t * math.sin(b)])
            add(setup, "side", f"along-length, rolled {choice.side_roll_deg:g}", view, aim, x_axis, L + 2 * margin, ref)
        e = math.radians(choice.end_pitch_deg)
        for end in (-1.0, 1.0):  # aimed at the end's top edge (moved inward by the inset): the end and the plate
            view = np.array([-end * math.sin(e), 0.0, -math.cos(e)])
            aim = np.array([end * (L / 2 - choice.end_inset_mm), -W / 2 - margin, z_top])
            add(setup, "end", f"across the end, pitched {choice.end_pitch_deg:g}", view, aim, y_axis, W + 2 * margin, ref)
        g = math.radians(choice.weld_pitch_deg)
        for sign in (-1.0, 1.0):
            view = np.array([sign * math.sin(g), 0.0, -math.cos(g)])
            aim = np.array([c + sign * choice.weld_offset_mm, -w_weld / 2 - margin, z_top])
            add(setup, "weld", f"along the weld, pitched {sign * choice.weld_pitch_deg:+g}", view, aim, y_axis,
                w_weld + 2 * margin, choice.weld_standoff_mm)
    return family


# ---------------------------------------------------------------------------------------------
# Pass families of a T-joint or a cruciform


@dataclass(frozen=True)
class _TChoice:
    rows: int  # rows along the welds over each half of the base plate (the outer one rolled toward the stem)
    end_roll_deg: float  # the outer rows' view, leaning in toward the stem: they see the base's ends
    end_inset_mm: float  # the outer rows aimed this far in from the base's ends
    fillet_rolls_deg: tuple[float, float]  # the two passes along each fillet, rolled toward it
    wall_roll_deg: float  # one pass along each long wall of the base, rolled toward it
    stem_end: bool  # a pass along the stem's end, straight down (its end face seen)
    stem_roll_deg: float  # a pass along each stem face's upper part, rolled toward it
    row_tilt_deg: float = 15.0  # the inner rows' views tilted along their travel (each half the other way):
    # the tjoint preset's hand-made rows' tilt (its worst pass against the truth, seeds 41 and 12: 13.6 and
    # 12.1 um with it, 17.9 and 18.1 straight down)


TJOINT_END_ROLLS_DEG = (35.0, 30.0, 40.0)
TJOINT_FILLET_ROLLS_DEG = ((40.0, 65.0), (35.0, 65.0), (35.0, 60.0), (30.0, 60.0))
TJOINT_STEM_ROLLS_DEG = (55.0, 50.0, 60.0)
TJOINT_WALL_ROLLS_DEG = (50.0, 45.0, 55.0)


def _tjoint_passes(part: _Part, choice: _TChoice, req: PlanRequirements) -> _Family:
    """Per setup with a stem up (a T-joint's top, both of a cruciform's): rows along the welds
    over each half of the base plate, the outer one rolled in to see the base's end; two passes
    along each fillet rolled toward it (``fillet_rolls_deg``: both toes from two directions); one
    along each face of the stem's upper part, rolled toward it (``stem_roll_deg``); a pass along
    the stem's end (``stem_end``); one along each long wall rolled toward it (the walls tie the
    setups). A T-joint turned over: the same rows over its flat underside, one pass along
    its length over its middle (without it the rows are tied only through the wall passes: the
    tjoint preset's worst pass 17.0 um against the truth, with it 11.8), and the walls.
    Every pass along the welds (y) runs the base's width and a margin: the camera, ahead along the
    travel, is never hidden by the stem."""
    cfg = part.config
    tj, sc, robot = cfg.tjoint, cfg.scanner, cfg.robot
    ref = sc.reference_distance_mm
    rate, v = robot.profile_rate_hz(), robot.speed_mm_s
    L, W, t = tj.base_length_mm, tj.base_width_mm, tj.base_thickness_mm
    x0, leg = tj.stem_thickness_mm / 2, float(np.mean(tj.leg_mm))
    margin = 10.0 + req.placement_tolerance_mm
    fan = sc.points_per_profile * sc.x_spacing_mm
    z_top = part.z_top_mm
    x_axis, y_axis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    family = _Family()

    def add(setup, purpose, label, view, aim, travel, length, standoff=ref):
        family.add(setup, purpose, label, view, aim, travel, length, standoff, v, rate)

    def along_y(setup, purpose, label, x, z, view, standoff=ref):
        add(setup, purpose, label, view, np.array([x, -W / 2 - margin, z]), y_axis, W + 2 * margin, standoff)

    e = math.radians(choice.end_roll_deg)
    for setup in req.setups:
        stem_up = setup == "top" or tj.stems == "both"
        # the inner row's line starts 10 mm short of the fillet's base toe (or the plate's middle)
        first = (x0 + leg + fan / 2 - 10.0) if stem_up else fan / 2 - 10.0
        outer = L / 2 - choice.end_inset_mm
        for side in (-1.0, 1.0):
            n_inner = choice.rows - 1
            last = outer - fan / 2  # the outer rolled row reaches in about this far
            xs = [first + (last - first) * k / max(n_inner - 1, 1) for k in range(n_inner)] if n_inner > 1 else \
                [first] * n_inner
            tilt = math.radians(choice.row_tilt_deg)
            for x in xs:
                along_y(setup, "face", "along the weld, over the base", side * x, z_top,
                        np.array([0.0, -side * math.sin(tilt), -math.cos(tilt)]))
            along_y(setup, "face", f"along the weld, over the base's end, rolled {choice.end_roll_deg:g} in",
                    side * outer, z_top, np.array([-side * math.sin(e), 0.0, -math.cos(e)]))
        if stem_up:
            for side in (-1.0, 1.0):
                for roll in choice.fillet_rolls_deg:
                    r = math.radians(roll)
                    # the shallower at the weld's face, the steeper at the stem toe: both toes in the
                    # middle of both lines (aimed up to the stem's end instead, the steeper pass met the
                    # stem toe near its line's end: 96 % of the toes measured within 0.2 mm, against 98.9)
                    reach, rise = (leg / 2, leg / 2) if roll < 55 else (leg / 4, leg * 1.5)
                    along_y(setup, "weld", f"along the fillet, rolled {roll:g} toward it", side * (x0 + reach),
                            z_top + rise, np.array([-side * math.sin(r), 0.0, -math.cos(r)]))
                r = math.radians(choice.stem_roll_deg)
                along_y(setup, "end", f"along the stem's face, rolled {choice.stem_roll_deg:g} toward it",
                        side * x0, z_top + 0.7 * tj.stem_height_mm, np.array([-side * math.sin(r), 0.0, -math.cos(r)]))
            if choice.stem_end:
                along_y(setup, "end", "along the stem's end", 0.0, z_top + tj.stem_height_mm, np.array([0.0, 0.0, -1.0]))
        else:  # the flat side up: one pass along its length, over its middle, ties every row
            pitch = math.radians(15.0)
            add(setup, "face", "along the base, over its middle, pitched 15", np.array([math.sin(pitch), 0.0,
                                                                                   -math.cos(pitch)]),
                np.array([-L / 2 - margin, 0.0, z_top]), x_axis, L + 2 * margin)
        w = math.radians(choice.wall_roll_deg)
        for side in (-1.0, 1.0):
            view = np.array([0.0, -side * math.sin(w), -math.cos(w)])
            add(setup, "side", f"along the base's wall, rolled {choice.wall_roll_deg:g}", view,
                np.array([-L / 2 - margin, side * W / 2, z_top - t / 2]), x_axis, L + 2 * margin)
    return family


def _reachable(tilt: float, families) -> list[list[float]]:
    """Per (angles, what) family, its angles the robot's tilt reaches; ``PlanRefused`` naming
    every family left with none."""
    reached, unreachable = [], []
    for angles, what in families:
        reached.append([a for a in angles if a <= tilt])
        if not reached[-1]:
            unreachable.append(f"{what} lean {min(angles):g} to {max(angles):g} deg from straight down; the "
                               f"robot's largest tilt is {tilt:g} deg (reach.max_tilt_deg)")
    if unreachable:
        raise PlanRefused(unreachable)
    return reached


def _tjoint_choices(part: _Part, req: PlanRequirements) -> list[_TChoice]:
    tilt = req.reach.max_tilt_deg
    fillets = [pair for pair in TJOINT_FILLET_ROLLS_DEG if max(pair) <= tilt]
    walls, ends, stems = _reachable(tilt, (
        ([max(pair) for pair in TJOINT_FILLET_ROLLS_DEG], "the fillets' toes: the steeper of the passes along them"),
        (TJOINT_WALL_ROLLS_DEG, "faces side_neg and side_pos: the passes along the base's walls"),
        (TJOINT_END_ROLLS_DEG, "faces end_neg and end_pos: the outer rows over the base"),
        (TJOINT_STEM_ROLLS_DEG, "faces stem_neg and stem_pos: the passes along the stem")))[1:]
    return [_TChoice(rows, end, inset, pair, wall, stem_end, stem)
            for rows in (2, 3)
            for stem_end in (False, True)
            for pair in fillets
            for stem in stems
            for wall in walls
            for end in ends
            for inset in (35.0, 25.0, 45.0)]


def _choices(part: _Part, req: PlanRequirements) -> list[_Choice]:
    """Every family setting, fastest first (then the reference distance, then the gentlest angles)."""
    cfg = part.config
    sc, robot = cfg.scanner, cfg.robot
    ref, far = sc.reference_distance_mm, sc.z_range_mm[1]
    full = max(sc.x_spacing_mm, robot.profile_spacing_mm)  # the full-resolution scan's coarsest spacing
    standoffs = [s for s in np.arange(ref, far - 40.0 + 1e-9, 15.0) if sc.x_spacing_mm * s / ref <= full + 1e-12]
    fan = sc.points_per_profile * sc.x_spacing_mm
    # neighbouring rows must overlap by a sticker grown by every error, and a little
    need = cfg.stickers.diameter_mm + 2 * (ROBOT_MARGIN_MM + req.sticker_tolerance_mm + req.placement_tolerance_mm) + 2.0
    if need >= fan:
        raise PlanRefused([f"face rows: the scan line ({fan:.1f} mm) is too short for two rows to share a sticker of "
                           f"{cfg.stickers.diameter_mm:g} mm with every error ({need:.1f} mm of overlap)"])
    width = cfg.specimen.grip_width_mm + 4.0
    first = max(1, math.ceil((width - fan) / (fan - need)) + 1) if width > fan else 1
    tilt = req.reach.max_tilt_deg
    sides, ends, welds = _reachable(tilt, (
        (SIDE_ROLLS_DEG, "faces side_neg and side_pos: the passes along the walls"),
        (END_PITCHES_DEG, "faces end_neg and end_pos: the passes across the ends"),
        (WELD_PITCHES_DEG, "the weld's toes: the passes along the weld")))
    out = [_Choice(n, side, aim, end, inset, pitch, offset, standoff)
           for n in range(first, first + 3)
           for standoff in standoffs
           for pitch in welds
           for offset in (0.0, 6.0, 12.0, -6.0, -12.0)
           for side in sides
           for aim in (0.0, 1.0)
           for end in ends
           for inset in (0.0, 5.0, 10.0)]
    strip = {ch: _weld_strip_mm(part, ch, req) for ch in out}
    room = [ch for ch in out if strip[ch] >= 2 * _strip_half_mm(cfg, req)]
    if out and not room:
        widest = max(strip.values())
        raise PlanRefused([f"passes along the weld (W) and the face rows (F) of every setup: a weld pass sees at most "
                           f"{max(widest, 0.0):.1f} mm of plate beside the weld zone where stickers may go; "
                           f"{2 * _strip_half_mm(cfg, req):.1f} mm are needed for {cfg.stickers.min_common} stickers "
                           f"of {cfg.stickers.diameter_mm:g} mm off a line (smaller stickers, or a scanner with a "
                           "longer line)"])
    return sorted(room, key=lambda ch: (ch.rows, ch.weld_standoff_mm, -round(strip[ch], 1)))


def _strip_half_mm(cfg: SimulationConfig, req: PlanRequirements) -> float:
    """Half the width a strip of sticker centres needs for three stickers off a line."""
    return 0.75 * (cfg.stickers.min_spread_mm + 2 * (ROBOT_MARGIN_MM + req.sticker_tolerance_mm)) + 1.0


def _weld_strip_mm(part: _Part, choice: _Choice, req: PlanRequirements) -> float:
    """Width of the strip of sticker centres beside the weld zone that a weld sweep's line covers
    on the plate (the wider side), every error allowed for: sweeps whose strip cannot hold three
    stickers off a line are not tried."""
    cfg = part.config
    sc = cfg.scanner
    g = math.radians(choice.weld_pitch_deg)
    phi = math.atan(sc.points_per_profile * sc.x_spacing_mm / 2 / sc.reference_distance_mm)
    h = choice.weld_standoff_mm * math.cos(g)  # the sensor's height over the plate
    reach = [h * math.tan(g + phi) - choice.weld_standoff_mm * math.sin(g),
             h * math.tan(g - phi) - choice.weld_standoff_mm * math.sin(g)]  # the line's ends, from the aim
    lo, hi = min(reach) + choice.weld_offset_mm, max(reach) + choice.weld_offset_mm
    margin = ROBOT_MARGIN_MM + req.sticker_tolerance_mm
    tol = req.placement_tolerance_mm + cfg.specimen.grip_width_mm / 2 * math.sin(math.radians(req.placement_yaw_deg))
    zone = part.specimen.weld_zone_half_mm() + cfg.stickers.weld_clearance_mm + cfg.stickers.diameter_mm / 2
    inner = zone + margin + tol
    edge = cfg.stickers.diameter_mm / 2 + margin + tol
    return max(hi - edge - inner, -lo - edge - inner)


# ---------------------------------------------------------------------------------------------
# Checking a set of passes


@dataclass
class Evaluation:
    passes: list[PlannedPass]
    faces: list[FaceCoverage]
    toes: list[ToeCoverage]
    problems: list[str]
    stickers: StickerSet | None = None
    overlaps: list[PlanOverlap] = field(default_factory=list)
    setup_links: list[SetupLink] = field(default_factory=list)

    @property
    def scan_time_s(self) -> float:
        return float(sum(p.duration_s for p in self.passes))


def _reach_problems(passes: list[PlannedPass], req: PlanRequirements) -> list[str]:
    lo, hi = np.asarray(req.reach.workspace_min_mm), np.asarray(req.reach.workspace_max_mm)
    problems = []
    for p in passes:
        start = p.T_world_sensor_start[:3, 3]
        for name, tcp in (("start", start), ("end", start + p.length_mm * p.travel_world)):
            if np.any(tcp < lo) or np.any(tcp > hi):
                problems.append(f"pass {p.pass_id}: its TCP at the {name}, {np.round(tcp, 1).tolist()} mm, is outside "
                                f"the robot's workspace {list(req.reach.workspace_min_mm)}..{list(req.reach.workspace_max_mm)}")
        tilt = math.degrees(math.acos(np.clip(-p.T_world_sensor_start[2, 2], -1, 1)))
        if tilt > req.reach.max_tilt_deg + 1e-9:
            problems.append(f"pass {p.pass_id}: its view leans {tilt:.0f} deg from straight down, more than the "
                            f"robot's largest tilt, {req.reach.max_tilt_deg:g} deg")
    return problems


FACE_SAMPLE_MM2 = 1.0  # the drawn faces sampled about one point per mm^2
SEEN_WITHIN_MM = 1.0  # a face sample is seen by a pass with a point this close on the same face


@dataclass(frozen=True)
class _Targets:
    """What a plan must see: samples of every face, the toe stations."""

    face: np.ndarray  # (k,) face of each sample
    samples: np.ndarray  # (k, 3) specimen frame
    areas: dict[int, float]
    toes: list["_Toe"]


def _targets(specimen: Specimen | TJoint) -> _Targets:
    mesh = specimen.mesh
    v = mesh.vertices[mesh.triangles]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    rng = np.random.default_rng(0)
    count = rng.poisson(area / FACE_SAMPLE_MM2)
    tri = np.repeat(np.arange(len(v)), count)
    a, b = rng.random(tri.size), rng.random(tri.size)
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    pts = v[tri, 0] + a[:, None] * (v[tri, 1] - v[tri, 0]) + b[:, None] * (v[tri, 2] - v[tri, 0])
    areas = {int(f): float(area[mesh.face_id == f].sum()) for f in np.unique(mesh.face_id)}
    return _Targets(mesh.face_id[tri], pts, areas, _toe_stations(specimen))


class _Seen:
    """Per pass (rendered at the nominal placement): which face samples it sees, and which toe
    stations it measures from over the plate and from over the weld. Cached, so that a candidate
    plan's coverage is the union of its passes'."""

    def __init__(self, renderer: "_Renderer", targets: _Targets, req: PlanRequirements):
        self.renderer, self.targets, self.req = renderer, targets, req
        self._cache: dict[tuple, tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]] = {}

    def of(self, p: PlannedPass) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        key = (p.setup, p.T_world_sensor_start.tobytes(), p.travel_world.tobytes(), p.length_mm)
        if key not in self._cache:
            view = self.renderer.view(p, 0)
            self._cache[key] = (self._face_mask(view), self._toe_masks(view))
        return self._cache[key]

    def _face_mask(self, view: _View) -> np.ndarray:
        t = self.targets
        seen = np.zeros(len(t.samples), bool)
        for f in np.unique(view.face):
            on = np.flatnonzero(t.face == f)
            if on.size == 0:
                continue
            d, _ = cKDTree(view.points[view.face == f]).query(t.samples[on], distance_upper_bound=SEEN_WITHIN_MM)
            seen[on[np.isfinite(d)]] = True
        return seen

    def _toe_masks(self, view: _View) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per toe: the least and the most lean across the toe (the sine of the laser's angle
        toward the plate's outward direction; < 0: from over the plate) of the rays that measure
        each station within the incidence limit; +inf and -inf where none does."""
        cos_limit = math.cos(math.radians(self.req.toe_incidence_limit_deg))
        out = []
        for toe in self.targets.toes:
            lo = np.full(len(toe.stations), np.inf)
            hi = np.full(len(toe.stations), -np.inf)
            d, hit = cKDTree(toe.stations).query(view.points, distance_upper_bound=TOE_RADIUS_MM)
            near = np.isfinite(d) & (-(view.rays @ toe.normal) >= cos_limit)
            lean = view.rays[near] @ toe.outward
            np.minimum.at(lo, hit[near], lean)
            np.maximum.at(hi, hit[near], lean)
            out.append((lo, hi))
        return out

    def faces(self, passes: list[PlannedPass]) -> tuple[list[FaceCoverage], list[str]]:
        t = self.targets
        counts = np.zeros(len(t.samples), np.int32)
        for p in passes:
            counts += self.of(p)[0]
        out, problems = [], []
        for f in sorted(t.areas):
            on = t.face == f
            share = float(np.count_nonzero(counts[on]) / max(np.count_nonzero(on), 1))
            median = float(np.median(counts[on][counts[on] > 0])) if np.any(counts[on]) else 0.0
            name = Face.NAMES[f]
            out.append(FaceCoverage(face=name, area_mm2=round(t.areas[f], 1), seen=round(share, 4),
                                    passes_median=median))
            if share < self.req.face_coverage:
                problems.append(f"face {name}: {100 * share:.1f} % of it is seen, the plan must see "
                                f"{100 * self.req.face_coverage:.0f} %")
        return out, problems

    def toes(self, passes: list[PlannedPass]) -> tuple[list[ToeCoverage], list[str]]:
        out, problems = [], []
        for k, toe in enumerate(self.targets.toes):
            lo = np.full(len(toe.stations), np.inf)
            hi = np.full(len(toe.stations), -np.inf)
            for p in passes:
                a, b = self.of(p)[1][k]
                lo, hi = np.minimum(lo, a), np.maximum(hi, b)
            if toe.rule == "both sides":
                plate, weld = lo <= -SIDE_LEAN, hi >= SIDE_LEAN
                both = plate & weld
            else:  # two directions SPREAD_DEG apart, whichever side they come from
                plate = np.isfinite(lo)
                both = weld = plate & (np.degrees(np.arcsin(np.clip(hi, -1, 1)) - np.arcsin(np.clip(lo, -1, 1)))
                                       >= SPREAD_DEG - 1e-9)
            stations = toe.stations
            length = float(np.linalg.norm(np.diff(stations, axis=0), axis=1).sum())
            out.append(ToeCoverage(toe=toe.name, rule=toe.rule, length_mm=round(length, 1), stations=len(stations),
                                   plate_side=round(float(plate.mean()), 4), weld_side=round(float(weld.mean()), 4),
                                   both_sides=round(float(both.mean()), 4)))
            if both.mean() < self.req.toe_coverage:
                missing = stations[~both, 1]
                how = "from both sides" if toe.rule == "both sides" else f"from two directions {SPREAD_DEG:g} deg apart"
                problems.append(f"toe {toe.name}: {100 * both.mean():.1f} % of it is measured {how}, the plan "
                                f"must reach {100 * self.req.toe_coverage:.0f} % (missed between y = "
                                f"{missing.min():.0f} and {missing.max():.0f} mm)")
        return out, problems


@dataclass(frozen=True)
class _Toe:
    name: str
    stations: np.ndarray  # (k, 3) specimen frame, every TOE_STEP_MM along the toe
    outward: np.ndarray  # (3,) along the plate, away from the weld
    normal: np.ndarray  # (3,) the plate's outward normal
    rule: str  # "both sides" (a butt weld's toe) or "two directions" (a fillet's)


def _toe_stations(specimen: Specimen | TJoint) -> list[_Toe]:
    """The toes a plan must measure: a butt weld's four (top and bottom, each side of the cap),
    stations every TOE_STEP_MM across the part 1 mm in from its edges; a fillet-welded part's
    true toe lines (two per fillet: on the base plate and on the stem), as many stations."""
    if isinstance(specimen, TJoint):
        out = []
        half = specimen.config.base_width_mm / 2
        for line in specimen.toes:
            pts = np.asarray(line.points_mm, float)
            y = np.arange(-half + 1.0, half - 1.0 + 1e-9, TOE_STEP_MM)
            stations = np.stack([np.interp(y, pts[:, 1], pts[:, 0]), y, np.interp(y, pts[:, 1], pts[:, 2])], axis=1)
            side, face = np.sign(np.median(pts[:, 0])), np.sign(np.median(pts[:, 2]))
            across, up = np.array([side, 0.0, 0.0]), np.array([0.0, 0.0, face])
            outward, normal = (across, up) if line.plate == "base" else (up, across)
            out.append(_Toe(line.name.removesuffix("-toe"), stations, outward, normal, "two directions"))
        return out
    out = []
    for side, cap, z_of, normal in (("top", specimen.weld_top, specimen.top_z, (0.0, 0.0, 1.0)),
                                    ("bottom", specimen.weld_bottom, specimen.bottom_z, (0.0, 0.0, -1.0))):
        hw = float(specimen.half_width(np.array([cap.centre_x_mm]))[0])
        y = np.arange(-hw + 1.0, hw - 1.0 + 1e-9, TOE_STEP_MM)
        centre, width = cap.centre(y), cap.width(y)
        for toe, sign in (("neg", -1.0), ("pos", 1.0)):
            x = centre + sign * width / 2
            stations = np.stack([x, y, z_of(x, y)], axis=1)
            out.append(_Toe(f"{side}-{toe}", stations, np.array([sign, 0.0, 0.0]), np.array(normal), "both sides"))
    return out


def _sticker_coverage(renderer: _Renderer, passes: list[PlannedPass]) -> CoverageMap:
    """Cells each pass sees at every placement within tolerance, where it can find a sticker
    (``DETECTABLE``)."""
    n_placements = len(renderer.part.placements)
    coverage = CoverageMap([p.pass_id for p in passes], CELL_MM)
    lo, hi = DETECTABLE
    for index, p in enumerate(passes):
        keys = None
        for k in range(n_placements):
            view = renderer.view(p, k)
            ok = (view.spacing_ratio >= lo) & (view.spacing_ratio <= hi)
            these = distinct(cell_keys(view.face[ok], face_params(view.face[ok], view.points[ok]), CELL_MM))
            keys = these if keys is None else np.intersect1d(keys, these, assume_unique=True)
        coverage._seen[index] = keys
    return coverage


def _place(part: _Part, passes: list[PlannedPass], coverage: CoverageMap, req: PlanRequirements,
           rng: np.random.Generator) -> tuple[StickerSet, list[PlanOverlap], list[SetupLink], list[str]]:
    cfg = part.config
    st = cfg.stickers
    margin = ROBOT_MARGIN_MM + req.sticker_tolerance_mm
    candidates = tjoint_sticker_candidates(part.specimen, cfg) if isinstance(part.specimen, TJoint) else \
        sticker_candidates(part.specimen, cfg)
    radius = st.diameter_mm / 2
    # Two passes overlap when the room both see for stickers is wide enough: in a strip of centres
    # h either side of its middle, three stickers lie at most 4/3 h off their best line (two on
    # one edge, one on the other), and a greedy placement needs a millimetre more; the stickers
    # placed are checked against the rule below.
    pairs = coverage.overlapping_pairs(candidates.faces, candidates.params(), candidates.centres,
                                       radius_mm=radius + margin, min_area_mm2=st.overlap_area_mm2,
                                       area_per_point_mm2=candidates.step_mm**2,
                                       min_spread_mm=_strip_half_mm(cfg, req))
    # Within a setup the passes are tied pair by pair; the setups are tied by the stickers both see
    # (tasks.graph: the setups matched on all of them at once), so passes of different setups
    # sharing one wall's strip need not hold three stickers off a line between them.
    pairs = [(i, j) for i, j in pairs if passes[i].setup == passes[j].setup]
    problems = []
    parent = list(range(len(passes)))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs:
        parent[find(i)] = find(j)
    for setup in req.setups:
        groups: dict[int, list[str]] = {}
        for i, p in enumerate(passes):
            if p.setup == setup:
                groups.setdefault(find(i), []).append(p.pass_id)
        if len(groups) > 1:
            biggest = max(groups.values(), key=len)
            for members in groups.values():
                if members is not biggest:
                    problems.append(f"passes {', '.join(members)}: no overlap with room for {st.min_common} whole "
                                    f"stickers ties them to the rest of setup {setup}")
    masks = coverage.disc_masks(candidates.faces, candidates.params(), radius + margin)
    # then the requirement's extra stickers (the part's own fill density is the simulator's way to
    # put some on a preset's part). The placement is greedy and random: where a narrow overlap is
    # left without three stickers off a line, it is tried again from the start with other draws
    # (PLACEMENT_TRIES in all, each deterministic) before the candidate is given up.
    extra = cfg.model_copy(update={"stickers": st.model_copy(
        update={"fill_density_per_1000mm2": req.extra_stickers_per_1000mm2})})
    for attempt in range(PLACEMENT_TRIES):
        draw = rng if attempt == 0 else np.random.default_rng([cfg.seed, PLANNING_SEED_OFFSET, attempt])
        try:
            first = _link_picks(candidates, masks, passes, req, cfg, draw)
            stickers = place_stickers(candidates, coverage, pairs, extra, draw, margin_mm=margin, first=first)
            break
        except StickerPlacementError as exc:
            failure = str(exc)
    else:
        return _empty(radius), [], [], problems + [f"{failure} ({PLACEMENT_TRIES} placements tried)"]
    masks = coverage.disc_masks(stickers.faces, face_params(stickers.faces, stickers.centres), radius + margin)
    overlaps = []
    for i, j in pairs:
        both = (np.uint64(1) << np.uint64(i)) | (np.uint64(1) << np.uint64(j))
        ids = [int(k) for k in stickers.ids if masks[k] & both == both]
        spread = spread_off_line_mm(stickers.centres[ids])
        overlaps.append(PlanOverlap(pass_a=passes[i].pass_id, pass_b=passes[j].pass_id, sticker_ids=ids,
                                    spread_mm=round(spread, 2)))
        if len(ids) < st.min_common or spread < st.min_spread_mm:
            problems.append(f"passes {passes[i].pass_id} and {passes[j].pass_id}: {len(ids)} whole stickers shared, "
                            f"{spread:.1f} mm off a line; {st.min_common} and {st.min_spread_mm:g} mm needed")
    links = []
    setups = list(req.setups)
    for a, b in itertools.combinations(setups, 2):
        in_a = np.uint64(sum(1 << i for i, p in enumerate(passes) if p.setup == a))
        in_b = np.uint64(sum(1 << i for i, p in enumerate(passes) if p.setup == b))
        ids = [int(k) for k in stickers.ids if (masks[k] & in_a) and (masks[k] & in_b)]
        spread = spread_off_line_mm(stickers.centres[ids])
        links.append(SetupLink(setups=(a, b), sticker_ids=ids, spread_mm=round(spread, 2)))
        if len(ids) < req.min_setup_stickers or spread < st.min_spread_mm:
            problems.append(f"setups {a} and {b}: {len(ids)} stickers are seen whole from both ({spread:.1f} mm off a "
                            f"line); {req.min_setup_stickers} not in a line are needed to match them without doubt")
    return stickers, overlaps, links, problems


def _link_picks(candidates, masks: np.ndarray, passes: list[PlannedPass], req: PlanRequirements,
                cfg: SimulationConfig, rng: np.random.Generator) -> tuple[int, ...]:
    """Stickers for the setups to share: among the places passes of every setup see whole, as
    many as ``min_setup_stickers`` and two more, each as far from those already picked as it can
    be (the first at random), never closer than the stickers' spacing; on a T-joint's or a
    cruciform's walls (the only faces both setups see) as many as fit ``wall_sticker_pitch_mm``
    apart."""
    setups = list(req.setups)
    if len(setups) < 2:
        return ()
    eligible = np.ones(len(masks), bool)
    for setup in setups:
        in_setup = np.uint64(sum(1 << i for i, p in enumerate(passes) if p.setup == setup))
        eligible &= (masks & in_setup) != 0
    pool = np.flatnonzero(eligible)
    if pool.size == 0:
        return ()
    spacing = cfg.stickers.spacing_factor * cfg.stickers.diameter_mm
    count = req.min_setup_stickers + 2
    if cfg.tjoint is not None:
        spacing, count = max(spacing, cfg.tjoint.wall_sticker_pitch_mm), len(pool)
    centres = candidates.centres[pool]
    picks = [int(rng.integers(pool.size))]
    nearest = np.linalg.norm(centres - centres[picks[0]], axis=1)
    while len(picks) < count:
        k = int(np.argmax(nearest))
        if nearest[k] < spacing:
            break
        picks.append(k)
        nearest = np.minimum(nearest, np.linalg.norm(centres - centres[k], axis=1))
    return tuple(int(pool[k]) for k in picks)


def _resolution_problems(part: _Part, passes: list[PlannedPass], info: list[dict], req: PlanRequirements) -> list[str]:
    sc, robot = part.config.scanner, part.config.robot
    full = max(sc.x_spacing_mm, robot.profile_spacing_mm)
    plate = req.plate_spacing_mm if req.plate_spacing_mm is not None else sc.x_spacing_mm
    problems = []
    for p, meta in zip(passes, info):
        spacing = sc.x_spacing_mm * meta["standoff"] / sc.reference_distance_mm
        limit = full if meta["purpose"] == "weld" else plate
        if spacing > limit + 1e-9:
            problems.append(f"pass {p.pass_id}: {spacing:.3f} mm between points at its {meta['standoff']:.0f} mm "
                            f"stand-off, coarser than the {limit:.3f} mm required")
    return problems


def evaluate_passes(part_config: SimulationConfig, req: PlanRequirements, passes: list[PlannedPass], *,
                    stickers: bool = True) -> Evaluation:
    """Check a set of passes (a plan's, or a preset's hand-made one) against the requirements."""
    part = _part(part_config, req)
    seen = _Seen(_Renderer(part), _targets(part.specimen), req)
    problems = _reach_problems(passes, req)
    toes, toe_problems = seen.toes(passes)
    faces, face_problems = seen.faces(passes)
    evaluation = Evaluation(passes, faces, toes, problems + toe_problems + face_problems)
    if stickers:
        coverage = _sticker_coverage(seen.renderer, passes)
        rng = np.random.default_rng(part_config.seed)
        evaluation.stickers, evaluation.overlaps, evaluation.setup_links, more = _place(part, passes, coverage, req, rng)
        evaluation.problems += more
    return evaluation


# ---------------------------------------------------------------------------------------------
# The search


def plan_scan(config: SimulationConfig, req: PlanRequirements, *,
              progress: Callable[[str], None] | None = None) -> ScanPlan:
    """The fastest plan of the search that meets every requirement; ``PlanRefused`` naming what
    the best candidate still missed when none does."""
    say = progress or (lambda message: log.info(message))
    part = _part(config, req)
    renderer = _Renderer(part)
    seen = _Seen(renderer, _targets(part.specimen), req)
    say(f"part drawn: {len(part.specimen.mesh.triangles):,} triangles, {len(req.setups)} setup(s), "
        f"{len(part.placements)} placements each")
    best: tuple[int, list[str]] | None = None
    tried = 0
    dead: set[tuple] = set()  # family settings whose passes were left without stickers to share

    tjoint = config.tjoint is not None

    def keys(choice) -> dict[str, tuple]:
        if tjoint:
            return {"face": ("face", choice.rows, choice.end_roll_deg, choice.end_inset_mm),
                    "side": ("side", choice.rows, choice.wall_roll_deg),
                    "weld": ("weld", choice.rows, choice.fillet_rolls_deg),
                    "end": ("end", choice.rows, choice.stem_end, choice.stem_roll_deg)}
        return {"face": ("face", choice.rows), "side": ("side", choice.rows, choice.side_roll_deg, choice.side_aim),
                "end": ("end", choice.rows, choice.end_pitch_deg, choice.end_inset_mm),
                "weld": ("weld", choice.rows, choice.weld_pitch_deg, choice.weld_offset_mm, choice.weld_standoff_mm)}

    for choice in (_tjoint_choices if tjoint else _choices)(part, req):
        if any(k in dead for k in keys(choice).values()):
            continue
        tried += 1
        family = (_tjoint_passes if tjoint else _dog_bone_passes)(part, choice, req)
        passes = family.passes
        problems = _reach_problems(passes, req) + _resolution_problems(part, passes, family.info, req)
        stage = 0
        if not problems:
            stage = 1
            toes, problems = seen.toes(passes)
        if not problems:
            stage = 2
            faces, problems = seen.faces(passes)
        if not problems:
            stage = 3
            coverage = _sticker_coverage(renderer, passes)
            stickers, overlaps, links, problems = _place(part, passes, coverage, req, np.random.default_rng(config.seed))
        if not problems:
            say(f"plan found after {tried} candidates: {len(passes)} passes, {sum(p.duration_s for p in passes):.0f} s "
                f"scan time, {len(stickers.ids)} stickers")
            return _scan_plan(config, req, passes, family.info, stickers, overlaps, links, faces, toes, tried,
                              part.specimen)
        # a family left without stickers to share (isolated, or no room in an overlap) is not
        # tried again with the same settings: the narrower family of a pair is blamed
        purpose_of = {p.pass_id: meta["purpose"] for p, meta in zip(passes, family.info)}
        for q in problems:
            if "ties them" in q:
                isolated = {purpose_of.get(name) for name in q.split(":")[0].removeprefix("passes ").split(", ")}
                if len(isolated) == 1 and None not in isolated:
                    dead.add(keys(choice)[isolated.pop()])
        for q in problems:
            named = [purpose_of[w] for w in q.replace(",", " ").split() if w in purpose_of]
            if "leave no room" in q and len(named) == 2:
                blamed = [x for x in named if x != "face"] or named
                dead.add(keys(choice)[blamed[0]])
        if best is None or stage > best[0] or (stage == best[0] and len(problems) < len(best[1])):
            best = (stage, problems)
        log.debug("candidate %s: %s", choice, "; ".join(problems))
        if tried % 20 == 0:
            say(f"{tried} candidates checked; the best so far still misses: {best[1][0]}")
    raise PlanRefused(best[1] if best else ["no candidate plan"])


def _as_drawn(specimen: Specimen | TJoint, stickers: StickerSet) -> tuple[np.ndarray, np.ndarray]:
    """The stickers' marks on the part as drawn: the planning weld's plate misalignment taken
    out (top and bottom faces flat at +-thickness/2, the walls' heights from the mid-plane), so
    that a hand (``simulator.run``) puts them on the real part, whatever its misalignment. A
    T-joint's faces are drawn flat where stickers go: its marks are where they were placed."""
    centres, normals = stickers.centres.copy(), stickers.normals.copy()
    if isinstance(specimen, TJoint):
        return centres, normals
    half_t = specimen.config.thickness_mm / 2
    for face, z in ((Face.TOP, half_t), (Face.BOTTOM, -half_t)):
        on = stickers.faces == face
        centres[on, 2] = z
        normals[on] = (0.0, 0.0, np.sign(z))
    walls = np.isin(stickers.faces, (Face.SIDE_NEG, Face.SIDE_POS))
    centres[walls, 2] -= specimen.z_shift(centres[walls, 0])
    return centres, normals


def _scan_plan(config, req, passes, info, stickers, overlaps, links, faces, toes, tried, specimen) -> ScanPlan:
    plan_passes = [PlanPass(pass_id=p.pass_id, setup=p.setup, purpose=meta["purpose"], direction=p.direction,
                            T_world_sensor_start=np.round(p.T_world_sensor_start, 9).tolist(),
                            travel_world=tuple(float(v) for v in p.travel_world), length_mm=round(p.length_mm, 6),
                            speed_mm_s=p.speed_mm_s, profile_rate_hz=p.profile_rate_hz,
                            standoff_mm=round(float(meta["standoff"]), 6), tilt_deg=round(meta["tilt"], 3),
                            roll_deg=round(meta["roll"], 3))
                   for p, meta in zip(passes, info)]
    plan_stickers = [PlanSticker(sticker_id=int(k), face=Face.NAMES[stickers.faces[row]],
                                 centre_mm=tuple(round(float(v), 4) for v in centre),
                                 normal=tuple(round(float(v), 6) for v in normal))
                     for row, (k, centre, normal) in enumerate(zip(stickers.ids, *_as_drawn(specimen, stickers)))]
    keep_out = specimen.weld_zone_half_mm() + config.stickers.weld_clearance_mm
    if isinstance(specimen, TJoint):  # about the stem, x = 0
        c, keep_out = 0.0, keep_out + specimen.config.stem_thickness_mm / 2
    else:
        c = specimen.weld_top.centre_x_mm
    return ScanPlan(part=config, requirements=req, passes=plan_passes, stickers=plan_stickers, overlaps=overlaps,
                    no_sticker_x_mm=(round(c - keep_out, 3), round(c + keep_out, 3)),
                    setup_links=links, faces=faces, toes=toes,
                    scan_time_s=round(sum(p.duration_s for p in plan_passes), 3), candidates_tried=tried)


def planned_passes(plan: ScanPlan) -> list[PlannedPass]:
    """The plan's passes as the simulator's robot program."""
    return [PlannedPass(p.pass_id, p.setup, p.direction, np.asarray(p.T_world_sensor_start, float),
                        np.asarray(p.travel_world, float), p.length_mm, p.speed_mm_s, p.profile_rate_hz)
            for p in plan.passes]


def plan_sticker_set(plan: ScanPlan) -> StickerSet:
    """The plan's stickers where the map puts them on the part as drawn (specimen frame)."""
    faces = np.array([Face.NAMES.index(s.face) for s in plan.stickers], np.uint8)
    return StickerSet(centres=np.array([s.centre_mm for s in plan.stickers], float).reshape(-1, 3),
                      normals=np.array([s.normal for s in plan.stickers], float).reshape(-1, 3),
                      ids=np.array([s.sticker_id for s in plan.stickers], np.int64), faces=faces,
                      radius_mm=plan.part.stickers.diameter_mm / 2, thickness_mm=plan.part.stickers.thickness_mm)
