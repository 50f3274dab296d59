"""Simulate one sample: specimen, setups, stickers, passes; write the cell's files and the truth.

Output folder (written atomically: it appears only when complete)::

    manifest.json            the sample manifest (schemas.manifest.SampleManifest)
    passes/<pass_id>.zarr    one store per pass (data_catalog.passes)
    truth/                   ground truth, never read by the pipeline (data_catalog.truth)
    preview/                 PNG pictures for a person to check at a glance
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import open3d as o3d

from data_catalog.atomic import atomic_directory, atomic_write_text
from data_catalog.hashing import sha256_tree
from data_catalog.manifests import MANIFEST_NAME, write_manifest
from data_catalog.passes import PassWriter
from data_catalog.truth import FILLET_TRUTH_NAME, TRUTH_DIR, WELD_TRUTH_NAME, TruthPassWriter, write_truth, write_weld_truth
from schemas.manifest import (MANIFEST_SCHEMA_VERSION, DogBoneSpecimen, PositionerTurn, SampleManifest, ScannerSettings,
                              Setup, WeldDescription, dog_bone_weld_lines)
from schemas.scan_plan import ScanPlan
from schemas.simulation import PlacementConfig, ScanPlanConfig, SimulationConfig
from schemas.truth import (GroundTruth, PointLabel, TruePass, TruePositioner, TrueSticker, TrueToeLines, WeldSection,
                           WeldSectionDetail, WeldTruth)
from simulator.coverage import CoverageMap, face_params, spread_off_line_mm
from simulator.fixture import build_fixture
from simulator.placement import (nominal_placement, place_on_fixture, placement_tolerance_mm, positioner_turn,
                                 resting_plate_mm, turned_setup)
from simulator.planner import plan_sticker_set, planned_passes
from simulator.robot import PassMotion, PlannedPass, draw_motion, pass_entry, plan_passes
from simulator.scanner import LineScanner
from simulator.scene import Scene, StickerSet
from simulator.specimen import Face, Specimen, SurfaceMesh, build_specimen
from simulator.stickers import Candidates, place_fixture_stickers, place_stickers, sticker_candidates
from simulator.tjoint import (TJoint, build_tjoint, place_tjoint_fixture_stickers, plan_tjoint_passes, tjoint_specimen,
                              tjoint_sticker_candidates, tjoint_weld_lines, wall_sticker_picks)
from tasks.frames import turn_about_axis

__all__ = ["SimulationSummary", "simulate", "plan_config", "COVERAGE_CELL_MM", "SCAN_DATE", "TOES_NAME"]

TOES_NAME = "toes.json"

log = logging.getLogger(__name__)

COVERAGE_CELL_MM = 2.0
PLANNING_STEP_MM = 0.5
PLANNING_MARGIN_MM = 0.5
SCAN_DATE = datetime(2026, 1, 5, 8, 0, tzinfo=timezone.utc)
"""The simulated cell's clock: fixed, so that a seed reproduces the files bit for bit."""

_LABEL_NAMES = {v: k.lower() for k, v in vars(PointLabel).items() if k.isupper()}


@dataclass(frozen=True)
class SimulationSummary:
    out_dir: Path
    n_passes: int
    n_points: int
    n_valid_points: int
    n_stickers_specimen: int
    n_stickers_fixture: int
    seconds: float


def _empty_stickers(radius: float) -> StickerSet:
    return StickerSet(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.uint8), radius, 0.0)


def _overlapping_pairs(coverage: CoverageMap, candidates: Candidates, config: SimulationConfig) -> list[tuple[int, int]]:
    """Passes overlap when they share sticker-eligible surface (plates, away from weld and edges)
    where both see a sticker (grown by the planning margin) whole, over ``overlap_area_mm2``,
    reaching 1 mm more than the stickers' own required spread off its best line: room for
    stickers not in a line. Slivers of overlap, or overlaps on the weld alone, do not count."""
    sc = config.stickers
    return coverage.overlapping_pairs(candidates.faces, candidates.params(), candidates.centres,
                                      radius_mm=sc.diameter_mm / 2 + PLANNING_MARGIN_MM,
                                      min_area_mm2=sc.overlap_area_mm2, area_per_point_mm2=candidates.step_mm**2,
                                      min_spread_mm=sc.min_spread_mm + 2 * PLANNING_MARGIN_MM + 1.0)


def _planning_coverage(config: SimulationConfig, planned: list[PlannedPass], motions: list[PassMotion],
                       scenes: dict[str, Scene]) -> CoverageMap:
    """Coarse, noise-free renders (about 1 mm apart) of every pass: what each pass sees."""
    sc = config.scanner
    col_stride = max(1, int(PLANNING_STEP_MM / sc.x_spacing_mm))
    n_cols = max(2, math.ceil(sc.points_per_profile / col_stride))
    coarse = LineScanner(sc.model_copy(update={"points_per_profile": n_cols, "x_spacing_mm": sc.x_spacing_mm * col_stride}))
    row_stride = max(1, int(PLANNING_STEP_MM / config.robot.profile_spacing_mm))
    coverage = CoverageMap([p.pass_id for p in planned], COVERAGE_CELL_MM)
    for index, (p, motion) in enumerate(zip(planned, motions)):
        poses = motion.T_world_sensor_true[::row_stride]
        for start in range(0, len(poses), 2000):
            prof = coarse.render(scenes[p.setup], poses[start:start + 2000], None, keep_specimen_points=True)
            seen = prof.label == PointLabel.VALID
            seen &= prof.face_id != 255
            coverage.add(index, prof.face_id[seen], prof.point_specimen[seen].astype(np.float64))
    return coverage


def _weld_sections(specimen: Specimen, step_mm: float = 5.0) -> list[WeldSection]:
    sections = []
    hw = specimen.config.grip_width_mm / 2
    for side, cap in (("top", specimen.weld_top), ("bottom", specimen.weld_bottom)):
        for y in np.arange(-hw, hw + 1e-9, step_mm):
            ya = np.array([y])
            sections.append(WeldSection(
                side=side, y_mm=float(y), centre_x_mm=float(cap.centre(ya)[0]),
                height_mm=float(cap.height(ya)[0]), width_mm=float(cap.width(ya)[0]),
                flank_angle_deg=(float(cap.effective_flank_deg(ya, 0)[0]), float(cap.effective_flank_deg(ya, 1)[0])),
                toe_radius_mm=(float(cap.toe_radius[0](ya)[0]), float(cap.toe_radius[1](ya)[0])),
                undercut_depth_mm=(float(cap.undercut[0](ya)[0]), float(cap.undercut[1](ya)[0])),
            ))
    return sections


def _weld_truth(specimen: Specimen, treatment: str, step_mm: float = 1.0) -> WeldTruth:
    """The drawn caps every ``step_mm`` along the weld, with what a section measures (the
    profile's peak, the grooves' depth, width and radius); draws nothing from the random stream."""
    sections = []
    hw = specimen.config.grip_width_mm / 2
    for side, cap in (("top", specimen.weld_top), ("bottom", specimen.weld_bottom)):
        for y in np.arange(-hw, hw + 1e-9, step_mm):
            ya = np.array([y])
            half = float(cap.width(ya)[0]) / 2
            centre = float(cap.centre(ya)[0])
            # the peak over the line between the plates' surfaces at the drawn toes (the plates'
            # misalignment included: it steps under the cap, and a gauge measures from the toes)
            x = centre + np.arange(-half, half + 1e-9, 0.005)
            outward = 1.0 if side == "top" else -1.0  # the bottom face's heights are along -z
            face = cap.height_mm(x, np.full(x.shape, y))[0] + outward * specimen.z_shift(x)
            plate = outward * specimen.z_shift(x[[0, -1]])  # the plates' level at the toes
            profile = face - (plate[0] + (plate[1] - plate[0]) * (x - x[0]) / (x[-1] - x[0]))
            grooves = None
            if cap.groove_width is not None and cap.groove_depth is not None:
                w = [float(g(ya)[0]) for g in cap.groove_width]
                d = [float(g(ya)[0]) for g in cap.groove_depth]
                grooves = (tuple(w), tuple(d), tuple((wk * wk / 4 + dk * dk) / (2 * dk) for wk, dk in zip(w, d)),
                           tuple(bool(half + 0.25 * wk - wk / 2 < half) for wk in w))
            sections.append(WeldSectionDetail(
                side=side, y_mm=float(y), centre_x_mm=centre, cap_height_mm=float(cap.height(ya)[0]),
                peak_height_mm=float(profile.max()), width_mm=2 * half,
                flank_angle_deg=(float(cap.effective_flank_deg(ya, 0)[0]), float(cap.effective_flank_deg(ya, 1)[0])),
                toe_radius_mm=(float(cap.toe_radius[0](ya)[0]), float(cap.toe_radius[1](ya)[0])),
                undercut_depth_mm=(float(cap.undercut[0](ya)[0]), float(cap.undercut[1](ya)[0])),
                groove_width_mm=None if grooves is None else grooves[0],
                groove_depth_mm=None if grooves is None else grooves[1],
                groove_radius_mm=None if grooves is None else grooves[2],
                toe_within_groove=None if grooves is None else grooves[3]))
    return WeldTruth(treatment=treatment, step_mm=step_mm, axial_misalignment_mm=specimen.axial_misalignment_mm,
                     angular_misalignment_deg=specimen.angular_misalignment_deg, sections=sections)


def _write_mesh(path: Path, mesh: SurfaceMesh) -> None:
    o3d_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                         o3d.utility.Vector3iVector(mesh.triangles))
    if not o3d.io.write_triangle_mesh(str(path), o3d_mesh, write_ascii=False, compressed=False,
                                      write_vertex_normals=False, write_vertex_colors=False):
        raise OSError(f"could not write {path}")


def _manifest(config: SimulationConfig, planned: list[PlannedPass], hashes: dict[str, str]) -> SampleManifest:
    sp, sc, robot = config.specimen, config.scanner, config.robot
    setups = []
    for setup in config.plan.setups:
        entries = [pass_entry(p, robot, hashes.get(p.pass_id)) for p in planned if p.setup == setup]
        tj = config.tjoint
        if tj is None:
            description = "as welded, top face up" if setup == "top" else "turned 180 deg about its length by hand"
        elif tj.stems == "both":
            description = "the upper stem up, the base plate on the support blocks, the lower stem hanging between " \
                "them" if setup == "top" else "turned over by hand about the base plate's length: the lower stem up"
        else:
            description = "stem up, the base plate on the support blocks" if setup == "top" else \
                "turned over by hand about the base plate's length: the stem hangs between the support blocks"
        thickness, half_width = resting_plate_mm(config)
        nominal = nominal_placement(config.fixture, thickness, flipped=(setup == "bottom"))
        turn = None
        if config.positioner is not None and setups:
            turn, nominal, description = turned_setup(config, from_setup=setups[0].name)
        setups.append(Setup(name=setup, description=description, passes=entries,
                            T_world_specimen_nominal=nominal.tolist(),
                            placement_tolerance_mm=round(placement_tolerance_mm(config.placement, half_width), 3),
                            positioner=turn))
    if config.tjoint is not None:
        specimen = tjoint_specimen(config.tjoint)
        weld = WeldDescription(joint="double fillet" if config.tjoint.stems == "one" else "cruciform fillet",
                               weld_lines=tjoint_weld_lines(config.tjoint),
                               treatment=config.weld.treatment)
    else:
        specimen = DogBoneSpecimen(length_mm=sp.length_mm, grip_width_mm=sp.grip_width_mm,
                                   gauge_width_mm=sp.gauge_width_mm, gauge_length_mm=sp.gauge_length_mm,
                                   transition_radius_mm=sp.transition_radius_mm, thickness_mm=sp.thickness_mm)
        # the simulated weld is drawn about x = 0
        weld = WeldDescription(joint="double-sided butt", weld_lines=dog_bone_weld_lines(specimen, 0.0),
                               treatment=config.weld.treatment)
    return SampleManifest(
        schema_version=MANIFEST_SCHEMA_VERSION, units="mm", sample_id=config.sample_id, created=SCAN_DATE, material="S355",
        specimen=specimen,
        weld=weld,
        sticker_diameter_mm=config.stickers.diameter_mm,
        scanner=ScannerSettings(model=sc.model, points_per_profile=sc.points_per_profile,
                                x_spacing_mm=sc.x_spacing_mm, z_resolution_mm=sc.z_resolution_mm,
                                reference_distance_mm=sc.reference_distance_mm, z_range_mm=sc.z_range_mm,
                                camera_offset_mm=sc.camera_offset_mm, T_flange_sensor=robot.T_flange_sensor),
        setups=setups,
    )


@contextlib.contextmanager
def _live_directory(path: Path) -> Iterator[Path]:
    """``path`` itself, created now (it must not exist): a paced simulation shows its passes as
    they land. On any error it is removed, so no half sample stays behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.mkdir()
    try:
        yield path
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise


def _true_turn(turn: PositionerTurn, config: SimulationConfig, rng: np.random.Generator) -> TruePositioner:
    """The positioner's true axis: the calibrated one moved across itself (``axis_error_mm``, one
    sigma each way), tilted (``axis_error_deg`` about a random direction across it) and its angle
    off by ``angle_error_deg`` (one sigma)."""
    pc = config.positioner
    d = np.asarray(turn.axis_direction, float)
    d /= np.linalg.norm(d)
    u = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    a, b = rng.normal(0.0, pc.axis_error_mm, 2)
    point = np.asarray(turn.axis_point_mm, float) + a * u + b * v
    tilt = np.radians(rng.normal(0.0, pc.axis_error_deg))
    phi = rng.uniform(0.0, 2 * np.pi)
    across = np.cos(phi) * u + np.sin(phi) * v
    direction = np.cos(tilt) * d + np.sin(tilt) * across
    angle = turn.angle_deg + rng.normal(0.0, pc.angle_error_deg)
    return TruePositioner(from_setup=turn.from_setup, setup="", axis_point_mm=tuple(float(x) for x in point),
                          axis_direction=tuple(float(x) for x in direction), angle_deg=float(angle))


def plan_config(plan: ScanPlan, *, seed: int | None = None, sample_id: str | None = None) -> SimulationConfig:
    """The simulation config that scans ``plan``: its part, its setups, the part put on the
    fixture within the plan's placement tolerance."""
    req = plan.requirements
    update = {"plan": ScanPlanConfig(setups=list(req.setups)),
              "placement": PlacementConfig(translation_mm=req.placement_tolerance_mm, yaw_deg=req.placement_yaw_deg),
              "preset": f"plan of {plan.part.preset}"}
    if seed is not None:
        update["seed"] = seed
    if sample_id is not None:
        update["sample_id"] = sample_id
    return plan.part.model_copy(update=update)


def _stickers_by_hand(plan: ScanPlan, specimen: Specimen | TJoint, rng: np.random.Generator) -> StickerSet:
    """The plan's stickers as a hand puts them from the printed map on the real part: each within
    the plan's sticker tolerance of its mark (uniform over the disc), flat on its face (a
    dog-bone's plates' misalignment and its walls' taper followed; a T-joint's faces are flat
    where stickers go)."""
    marks = plan_sticker_set(plan)
    tol = plan.requirements.sticker_tolerance_mm
    n = marks.normals
    helper = np.where(np.abs(n[:, [2]]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    radius = tol * np.sqrt(rng.random(len(n)))
    angle = rng.uniform(0, 2 * np.pi, len(n))
    centres = marks.centres + (radius * np.cos(angle))[:, None] * u + (radius * np.sin(angle))[:, None] * v
    normals = marks.normals.copy()
    if isinstance(specimen, TJoint):
        return StickerSet(centres=centres, normals=normals, ids=marks.ids, faces=marks.faces,
                          radius_mm=marks.radius_mm, thickness_mm=marks.thickness_mm)
    eps = 0.05
    for face, z_of, sign in ((Face.TOP, specimen.top_z, 1.0), (Face.BOTTOM, specimen.bottom_z, -1.0)):
        on = marks.faces == face
        x, y = centres[on, 0], centres[on, 1]
        centres[on, 2] = z_of(x, y)
        dzdx = (z_of(x + eps, y) - z_of(x - eps, y)) / (2 * eps)
        dzdy = (z_of(x, y + eps) - z_of(x, y - eps)) / (2 * eps)
        nn = np.stack([-dzdx * sign, -dzdy * sign, np.full_like(x, sign)], 1)
        normals[on] = nn / np.linalg.norm(nn, axis=1, keepdims=True)
    for face, side in ((Face.SIDE_NEG, -1.0), (Face.SIDE_POS, 1.0)):
        on = marks.faces == face
        x = centres[on, 0]
        centres[on, 1] = side * specimen.half_width(x)
        centres[on, 2] += specimen.z_shift(x)
    return StickerSet(centres=centres, normals=normals, ids=marks.ids, faces=marks.faces,
                      radius_mm=marks.radius_mm, thickness_mm=marks.thickness_mm)


def simulate(config: SimulationConfig, out_dir: Path, *, progress: Callable[[str], None] | None = None,
             previews: bool = True, pace: float | None = None, plan: ScanPlan | None = None) -> SimulationSummary:
    """Simulate the sample described by ``config`` into ``out_dir`` (which must not exist).

    With ``plan`` (``weldrecon plan``; ``config`` from ``plan_config``) the robot runs the plan's
    passes and the stickers are put by hand where the plan's map marks them, instead of the
    preset's program and stickers placed for it.

    Without ``pace`` the folder appears only when complete (written beside it, then renamed).
    With ``pace`` (1: the robot's own speed, N: N times faster) the folder and the manifest (the
    scan plan, without content hashes) appear first, and each pass store appears, complete, when
    the robot would have finished it (written under a hidden name, then renamed), as a cell's
    passes land during a scan; the truth comes last."""
    if pace is not None and not pace > 0:
        raise ValueError(f"pace must be a positive speed-up over the robot, got {pace}")
    say = progress or (lambda message: log.info(message))
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise FileExistsError(f"{out_dir} already exists; refusing to overwrite it")
    t0 = time.perf_counter()
    seeds = np.random.SeedSequence(config.seed).spawn(6)  # the first five as before the positioner's
    rng_specimen, rng_place, rng_stickers, rng_fixture = (np.random.default_rng(s) for s in seeds[:4])

    tj = config.tjoint
    if tj is None:
        specimen = build_specimen(config.specimen, config.weld, config.mesh, rng_specimen)
    else:
        specimen = build_tjoint(tj, config.weld, config.mesh, rng_specimen)
    fixture_mesh = build_fixture(config.fixture)
    T_world_specimen = {setup: place_on_fixture(specimen, config.fixture, config.placement, rng_place,
                                                flipped=(setup == "bottom")) for setup in ("top", "bottom")}
    true_turn = None
    if config.positioner is not None:  # the later setups: the first turned by the positioner's true axis
        first, *later = config.plan.setups
        for setup in later:
            true_turn = _true_turn(positioner_turn(config, from_setup=first), config,
                                   np.random.default_rng(seeds[5])).model_copy(update={"setup": setup})
            T_world_specimen[setup] = turn_about_axis(true_turn.axis_point_mm, true_turn.axis_direction,
                                                      true_turn.angle_deg) @ T_world_specimen[first]
    if plan is not None:
        planned = planned_passes(plan)
    elif tj is None:
        z_top = config.fixture.block_size_mm[2] + config.specimen.thickness_mm
        planned = plan_passes(config.plan, config.specimen, config.robot, z_top_mm=z_top,
                              standoff_mm=config.scanner.reference_distance_mm, setups=tuple(config.plan.setups))
    else:
        planned = plan_tjoint_passes(config, z_top_mm=config.fixture.block_size_mm[2] + tj.base_thickness_mm,
                                     setups=tuple(config.plan.setups))
    pass_seeds = seeds[4].spawn(len(planned))
    motions, render_rngs = [], []
    for p, s in zip(planned, pass_seeds):
        motion_seed, render_seed = s.spawn(2)
        motions.append(draw_motion(p, config.robot, np.random.default_rng(motion_seed)))
        render_rngs.append(np.random.default_rng(render_seed))
    say(f"specimen meshed: {len(specimen.mesh.triangles):,} triangles; {len(planned)} passes planned")

    radius = config.stickers.diameter_mm / 2
    if plan is not None:  # the plan's stickers, put by hand from its map
        index_of = {p.pass_id: k for k, p in enumerate(planned)}
        pairs = [(index_of[o.pass_a], index_of[o.pass_b]) for o in plan.overlaps]
        specimen_stickers = _stickers_by_hand(plan, specimen, rng_stickers)
    else:
        planning_scenes = {s: Scene(specimen.mesh, T_world_specimen[s], fixture_mesh, _empty_stickers(radius),
                                    _empty_stickers(radius)) for s in config.plan.setups}
        coverage = _planning_coverage(config, planned, motions, planning_scenes)
        candidates = sticker_candidates(specimen, config) if tj is None else tjoint_sticker_candidates(specimen, config)
        # Plan for more pairs than the final check will call overlapping: the coarse planning
        # renders see a little less than the real passes.
        pairs = _overlapping_pairs(coverage, candidates, config)
        paired = {i for pair in pairs for i in pair}
        for index, p in enumerate(planned):
            if index not in paired:
                log.warning("pass %s overlaps no other pass with room for stickers: it cannot be registered", p.pass_id)
        first: tuple[int, ...] = ()
        if tj is not None and tj.wall_stickers:
            seen = coverage.disc_masks(candidates.faces, candidates.params(), radius + PLANNING_MARGIN_MM)
            first = wall_sticker_picks(candidates, seen, specimen, rng_stickers)
        specimen_stickers = place_stickers(candidates, coverage, pairs, config, rng_stickers,
                                           margin_mm=PLANNING_MARGIN_MM, first=first)
    if tj is None:
        fixture_stickers = place_fixture_stickers(config, rng_fixture, first_id=len(specimen_stickers.ids))
    else:
        fixture_stickers = place_tjoint_fixture_stickers(config, rng_fixture, first_id=len(specimen_stickers.ids))
    say(f"stickers placed: {len(specimen_stickers.ids)} on the specimen, {len(fixture_stickers.ids)} on the "
        f"fixture; {len(pairs)} overlapping pass pairs")
    scenes = {s: Scene(specimen.mesh, T_world_specimen[s], fixture_mesh, specimen_stickers, fixture_stickers)
              for s in config.plan.setups}

    scanner = LineScanner(config.scanner)
    final = CoverageMap([p.pass_id for p in planned], COVERAGE_CELL_MM)
    chunk = config.chunk_profiles
    n_cols = config.scanner.points_per_profile
    true_passes, hashes = [], {}
    total = valid_total = 0
    live = pace is not None
    with (_live_directory(out_dir) if live else atomic_directory(out_dir)) as tmp:
        (tmp / "passes").mkdir()
        (tmp / TRUTH_DIR / "passes").mkdir(parents=True)
        if live:
            write_manifest(tmp / MANIFEST_NAME, _manifest(config, planned, {}))
            scan_start, scanned_s = time.perf_counter(), 0.0
            say(f"manifest written; passes land at {pace:g} x the robot's speed")
        for index, (p, motion, rng) in enumerate(zip(planned, motions, render_rngs)):
            t_pass = time.perf_counter()
            n = p.n_profiles
            final_path = tmp / "passes" / f"{p.pass_id}.zarr"
            pass_path = final_path.with_name(f".{p.pass_id}.zarr.partial") if live else final_path
            writer = PassWriter(pass_path, pass_id=p.pass_id, n_profiles=n,
                                n_columns=n_cols, chunk_profiles=chunk, with_poses=config.robot.log_profile_poses)
            truth_writer = TruthPassWriter(tmp / TRUTH_DIR / "passes" / f"{p.pass_id}.zarr",
                                           n_profiles=n, n_columns=n_cols, chunk_profiles=chunk)
            counts = np.zeros(256, np.int64)
            for start in range(0, n, chunk):
                stop = min(start + chunk, n)
                prof = scanner.render(scenes[p.setup], motion.T_world_sensor_true[start:stop], rng,
                                      keep_specimen_points=True)
                writer.write(start, x_mm=prof.x_mm, z_mm=prof.z_mm, intensity=prof.intensity,
                             timestamp_s=motion.timestamp_s[start:stop],
                             T_world_flange=motion.T_world_flange_logged[start:stop])
                truth_writer.write(start, T_world_sensor=motion.T_world_sensor_true[start:stop],
                                   label=prof.label, material=prof.material, sticker_id=prof.sticker_id)
                seen = (prof.label == PointLabel.VALID) & (prof.face_id != 255)
                final.add(index, prof.face_id[seen], prof.point_specimen[seen].astype(np.float64))
                counts += np.bincount(prof.label.ravel(), minlength=256)
            writer.close()
            if live:  # the pass lands when the robot would have finished it
                scanned_s += p.duration_s
                time.sleep(max(0.0, scan_start + scanned_s / pace - time.perf_counter()))
                os.rename(pass_path, final_path)
            hashes[p.pass_id] = sha256_tree(final_path)
            label_counts = {_LABEL_NAMES[k]: int(counts[k]) for k in _LABEL_NAMES}
            true_passes.append(TruePass(pass_id=p.pass_id, setup=p.setup, T_nominal_true=motion.T_error.tolist(),
                                        n_points=int(n * n_cols), label_counts=label_counts))
            total += n * n_cols
            valid_total += label_counts["valid"] + label_counts["outlier"]
            say(f"pass {index + 1}/{len(planned)} {p.pass_id}: {p.length_mm:.0f} mm, {n} profiles x {n_cols} "
                f"points, {p.duration_s:.1f} s scan time, {time.perf_counter() - t_pass:.1f} s")

        # The planned overlaps, checked on what the passes really saw: whole stickers, not in a line.
        final_pairs = pairs
        masks = final.disc_masks(specimen_stickers.faces,
                                 face_params(specimen_stickers.faces, specimen_stickers.centres), radius)
        common = {}
        for i, j in final_pairs:
            both = (np.uint64(1) << np.uint64(i)) | (np.uint64(1) << np.uint64(j))
            ids = [int(k) for k in specimen_stickers.ids if masks[k] & both == both]
            common[f"{planned[i].pass_id}|{planned[j].pass_id}"] = ids
            if len(ids) < config.stickers.min_common or \
                    spread_off_line_mm(specimen_stickers.centres[ids]) < config.stickers.min_spread_mm:
                log.warning("passes %s and %s share only %d stickers whole", planned[i].pass_id,
                            planned[j].pass_id, len(ids))

        manifest = _manifest(config, planned, {} if live else hashes)
        if not live:
            write_manifest(tmp / MANIFEST_NAME, manifest)
        truth = GroundTruth(
            sample_id=config.sample_id, seed=config.seed, preset=config.preset,
            T_world_specimen={s: T_world_specimen[s].tolist() for s in config.plan.setups},
            stickers=_true_stickers(specimen_stickers, fixture_stickers, config.stickers.diameter_mm),
            weld_sections=_weld_sections(specimen) if tj is None else [],
            misalignment={} if tj is not None else {"axial_mm": specimen.axial_misalignment_mm,
                                                    "angular_deg": specimen.angular_misalignment_deg},
            passes=true_passes,
            overlapping_pairs=[(planned[i].pass_id, planned[j].pass_id) for i, j in final_pairs],
            common_stickers=common,
            positioner=true_turn,
        )
        write_truth(tmp / TRUTH_DIR / "truth.json", truth)
        if tj is None:  # the drawn butt weld, section by section
            write_weld_truth(tmp / TRUTH_DIR / WELD_TRUTH_NAME, _weld_truth(specimen, config.weld.treatment))
        else:  # the true toe lines, and the fillets as drawn every 1 mm
            atomic_write_text(tmp / TRUTH_DIR / TOES_NAME, TrueToeLines(
                sample_id=config.sample_id, toes=specimen.toes).model_dump_json(indent=1) + "\n")
            atomic_write_text(tmp / TRUTH_DIR / FILLET_TRUTH_NAME, specimen.fillet_truth().model_dump_json(indent=1) + "\n")
        atomic_write_text(tmp / TRUTH_DIR / "simulation.json", config.simulation_json())
        _write_mesh(tmp / TRUTH_DIR / "specimen.ply", specimen.mesh)
        _write_mesh(tmp / TRUTH_DIR / "fixture.ply", fixture_mesh)
        if previews:
            from simulator.preview import write_previews
            write_previews(tmp, manifest, truth, config)
        say(f"wrote {total:,} points ({valid_total:,} returns) in {len(planned)} passes")
    return SimulationSummary(out_dir=out_dir, n_passes=len(planned), n_points=int(total),
                             n_valid_points=int(valid_total), n_stickers_specimen=len(specimen_stickers.ids),
                             n_stickers_fixture=len(fixture_stickers.ids), seconds=time.perf_counter() - t0)


def _true_stickers(specimen_stickers: StickerSet, fixture_stickers: StickerSet, diameter: float) -> list[TrueSticker]:
    out = []
    for on, stickers in (("specimen", specimen_stickers), ("fixture", fixture_stickers)):
        for row, k in enumerate(stickers.ids):
            out.append(TrueSticker(sticker_id=int(k), on=on, face=Face.NAMES[stickers.faces[row]],
                                   centre_mm=tuple(float(v) for v in stickers.centres[row]),
                                   normal=tuple(float(v) for v in stickers.normals[row]), diameter_mm=diameter))
    return out
