"""The typed description of every stage's output files, one block per stage: a zarr group's
arrays as the fields of a frozen dataclass (shape, type, unit, frame), JSON documents as their
pydantic models (``schemas.stage_documents``, ``schemas.weld_document``), mesh files by name. Readers and writers go through these, so each file and array name is spelled
here only. (Kept apart from the stage bodies, so that a stage's code version does not include the
compute code of the stages whose outputs it reads.)"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flows.stages.contracts import ArrayFile, JsonFile, MeshFile, TextFile
from schemas.stage_documents import FEModelSummary, RefineSummary, RegistrationSummary, Report, StressSummary
from schemas.weld_document import WeldGeometry

from tasks.arrays import distinct


# --- stage denoise ---
@dataclass(frozen=True)
class DenoisedPass:
    points: np.ndarray  # (profiles, columns, 3) float32, mm, coarse world frame; NaN: no return or removed
    normals: np.ndarray  # (profiles, columns, 3) float32, unit, toward the sensor; NaN where points is
    sensor_origins: np.ndarray  # (profiles, 3) float64, mm: the sensor's origin at each profile

CLOUD = ArrayFile("cloud.zarr", DenoisedPass)


@dataclass(frozen=True)
class PassPreview:
    points: np.ndarray  # (p, c, 3) float32, mm: the denoised points[::steps[0], ::steps[1]]; (0, 0, 3): none
    normals: np.ndarray  # (p, c, 3) float32, the same points' normals
    steps: np.ndarray  # (2,) int64: every how many profiles and columns; (0, 0): no copy (an imported scan)

# the thinned copy the QA page's maps read (denoise.preview_cell_mm): made as the pass lands
PREVIEW = ArrayFile("preview.zarr", PassPreview)


# --- stage targets ---
@dataclass(frozen=True)
class PassTargets:
    centres: np.ndarray  # (k, 3) float64, mm, coarse world frame: each sticker's centre on its top face
    normals: np.ndarray  # (k, 3) float64, unit, toward the sensor
    rms_mm: np.ndarray  # (k,) float64, rim fit RMS
    rim_coverage: np.ndarray  # (k,) float64, share of the rim seen
    edge_height_mm: np.ndarray  # (k,) float64: the sticker edge's height the rim fit found
    edge_height_sigma_mm: np.ndarray  # (k,) float64: that height's 1-sigma from the fit's covariance (0: none)
    centre_per_height: np.ndarray  # (k, 3) float64: the centre's move per mm of height along the fit's valley
    pixel: np.ndarray  # (k, 2) float64, (profile, column) of the Hough circle
    preview: np.ndarray  # (rows, cols) uint8: the image searched (intensity / 4), area-averaged to at most 640 rows
    grid_spacing_mm: np.ndarray  # (2,) float64: the pass's points apart (between profiles, between columns); NaN: none
    grid_shape: np.ndarray  # (2,) int64: (profiles, columns) of the pass

TARGETS = ArrayFile("targets.zarr", PassTargets)


# --- stage register ---
@dataclass(frozen=True)
class Registration:
    T_common_pass: np.ndarray  # (n, 4, 4) float64: pass (coarse frame) -> common frame
    residual_mm: np.ndarray  # (e,) float64, per target pair after the solve
    inlier: np.ndarray  # (e,) bool
    edge_passes: np.ndarray  # (e, 2) int64, the passes of each target pair
    points_a: np.ndarray  # (e, 3) float64, mm, the pair's centre in pass a's coarse frame
    points_b: np.ndarray  # (e, 3) float64, mm, in pass b's
    track_positions_mm: np.ndarray  # (t, 3) float64, each physical target in the common frame
    specimen_track: np.ndarray  # (t,) bool: seen from more than one setup (so on the specimen)
    track_members: np.ndarray  # (m, 2) int64: (track, pass) of every observation
    track_centres_mm: np.ndarray  # (m, 3) float64: that observation's centre, coarse frame
    rim_rms_a_mm: np.ndarray  # (e,) float64: the rim fit RMS of the pair's target in pass a (stage targets' rms_mm)
    rim_rms_b_mm: np.ndarray  # (e,) float64: in pass b
    edge_height_a_mm: np.ndarray  # (e,) float64: the edge height its rim fit found (stage targets' edge_height_mm)
    edge_height_b_mm: np.ndarray  # (e,) float64
    edge_height_sigma_a_mm: np.ndarray  # (e,) float64: that height's own sigma
    edge_height_sigma_b_mm: np.ndarray  # (e,) float64
    centre_per_height_a: np.ndarray  # (e,) float64: its centre's move per mm of height (the length of centre_per_height)
    centre_per_height_b: np.ndarray  # (e,) float64

REGISTRATION = ArrayFile("registration.zarr", Registration)
# each pair end's rim fit figures in Registration, as (name, unit suffix): f"{name}_{a|b}{unit}"
END_FIGURES = (("rim_rms", "_mm"), ("edge_height", "_mm"), ("edge_height_sigma", "_mm"), ("centre_per_height", ""))
REGISTRATION_SUMMARY = JsonFile("registration.json", RegistrationSummary)  # pairs, weak pairs, per-pass RMS


# --- stage refine ---
@dataclass(frozen=True)
class RefinedPoses:
    T_common_pass: np.ndarray  # (n, 4, 4) float64: pass (coarse frame) -> common frame
    track_positions_mm: np.ndarray  # (t, 3) float64: each physical target where the refined poses put it
    specimen_track: np.ndarray  # (t,) bool: seen from more than one setup
    target_residual_mm: np.ndarray  # (e,) float64, inlier target pairs after refinement

REFINED = ArrayFile("refined.zarr", RefinedPoses)
REFINE_SUMMARY = JsonFile("refine.json", RefineSummary)  # surface pairs (points, RMS), step per iteration


# --- stage merge ---
@dataclass(frozen=True)
class MergedCloud:
    points: np.ndarray  # (n, 3) float64, mm, common frame: one point per occupied (fine or coarse) cell
    normals: np.ndarray  # (n, 3) float32, unit: the cell's points' normals averaged; NaN where they cancel
    counts: np.ndarray  # (n,) int32: measured points merged into the cell
    fine: np.ndarray  # (n,) bool: a fine cell (the surface bends there) or a whole coarse (flat) one

MERGED = ArrayFile("merged.zarr", MergedCloud)


# --- stage segment ---
@dataclass(frozen=True)
class SpecimenCloud:
    points: np.ndarray  # (n, 3) float64, mm, common frame: the specimen's merged points
    normals: np.ndarray  # (n, 3) float32, unit, outward (toward the sensors)
    fine: np.ndarray  # (n,) bool: from a fine cell (bent surface) or a coarse one (flat)
    measured: np.ndarray  # (n,) bool: a merged measurement; False: the plane closing a single setup's unseen underside

SPECIMEN = ArrayFile("specimen.zarr", SpecimenCloud)


# --- stage weld ---
WELD_GEOMETRY = JsonFile("weld_geometry.json", WeldGeometry)  # per section: figures with 1-sigma, verdicts; statistics


@dataclass(frozen=True)
class WeldToes:
    points_mm: np.ndarray  # (m, 3) float64, mm, common frame: the measured toes, polyline after polyline
    polyline: np.ndarray  # (m,) int64: which toe polyline (one per weld line and side, sorted by both), in order along it
    position_mm: np.ndarray  # (m,) float64: the section's position along its weld line

    def polylines(self) -> list[np.ndarray]:
        """The toes as polylines (k >= 2, 3), common frame, mm."""
        return [self.points_mm[self.polyline == k] for k in distinct(self.polyline)]

WELD_TOES = ArrayFile("toes.zarr", WeldToes)


# --- stage mesh ---
@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # (v, 3) float64, mm, common frame
    triangles: np.ndarray  # (t, 3) int64, counter-clockwise seen from outside

MESH = ArrayFile("mesh.zarr", Mesh)


# --- stage export ---
STL = MeshFile("mesh.stl")  # binary STL, mm
PLY = MeshFile("mesh.ply")  # binary PLY, mm


# --- stage volume ---
# the model files are left out when the surface mesh is open (volume.json says so: "made": false)
VOLUME_INP = MeshFile("model.inp", optional=True)  # Abaqus, C3D10 (or C3D4), mm: ALL, WELD_ZONE_NODES, WELD_ZONE_SURFACE
VOLUME_VTU = MeshFile("model.vtu", optional=True)  # VTU (zlib): min_dihedral_deg, aspect_ratio, weld_zone_boundary
VOLUME_SUMMARY = JsonFile("volume.json", FEModelSummary)  # whether it was made, the solid checks, the quality figures


# --- stage stress ---
STRESS_SUMMARY = JsonFile("stress.json", StressSummary)  # the factor per toe and section, hot spots, checks
STRESS_VTU = MeshFile("sections.vtu", optional=True)  # VTU (zlib): the section models in the specimen frame, their stresses


@dataclass(frozen=True)
class HotSection:
    points_mm: np.ndarray  # (n, 2) float64: the hot spot's section model's nodes (x across the weld, y up), mm
    triangles: np.ndarray  # (e, 3) int64: its triangles' corners
    factor: np.ndarray  # (n,) float32: each node's maximum principal stress over the hot toe's nominal stress
    toe_mm: np.ndarray  # (2,) float64: the hot toe where the section crosses it

# the hot spot's section for the QA page's stress map (empty when no stress was computed)
HOT_SECTION = ArrayFile("hot_section.zarr", HotSection)


@dataclass(frozen=True)
class ElementQualityArrays:
    min_dihedral_deg: np.ndarray  # (e,) float32, each tetrahedron's smallest dihedral angle
    aspect_ratio: np.ndarray  # (e,) float32, circumradius / (3 x inradius)

# beside the model files: the per-element quality as arrays (empty when no model was made)
ELEMENT_QUALITY = ArrayFile("quality.zarr", ElementQualityArrays)

# the surface the model was filled from: the Poisson mesh simplified to volume.max_surface_triangles
# (common frame, mm; empty when the Poisson mesh was open and nothing was simplified). The QA page
# draws the mesh from it: simplifying the paper preset's 4.8 M triangles again took 166 s of 209.
MODEL_SURFACE = ArrayFile("surface.zarr", Mesh)


# --- stage report ---
REPORT = JsonFile("report.json", Report)


# --- stage qa_report ---
QA_REPORT = TextFile("report.html")  # self-contained (pictures inline); AUDIT_MARK filled in when published
