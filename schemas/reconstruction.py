"""Configuration of the reconstruction: one model per stage, units in the names, bounds checked.
Loaded from YAML over the defaults; the config actually used is written next to the results."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from schemas.acceptance import AcceptanceLimits
from schemas.common import InputModel, Vector3

__all__ = ["DenoiseConfig", "RimEdge", "TargetsConfig", "RegistrationConfig", "SurfaceRegistrationConfig", "RefineConfig",
           "MergeConfig", "SegmentConfig", "PoissonConfig", "WeldGeometryConfig", "VolumeConfig", "QaReportConfig", "ReconstructionConfig"]


class DenoiseConfig(InputModel):
    """Statistical outlier removal on the organized pass (Rusu 2008), then each kept point's
    normal from its grid neighbours (the normals travel through the merge to the mesh)."""

    k: int = Field(default=8, ge=1, le=100)
    alpha: float = Field(default=1.0, gt=0, le=10)
    window_rows: int = Field(default=2, ge=0, le=10)
    window_cols: int = Field(default=2, ge=0, le=20)
    normal_window_mm: float = Field(default=0.5, gt=0, le=20, description=(
        "edge of the window of grid neighbours each normal is fitted to; the paper's 100 neighbours "
        "are a 0.5 mm window at its 0.02 x 0.1 mm grid (5 profiles x 25 columns)"))
    normal_min_points: int = Field(default=6, ge=3, le=1000, description="fewer points: the normal faces the sensor")
    scan_normal_neighbours: int = Field(default=16, ge=3, le=200, description=(
        "imported scans (no grid; the outliers by k and alpha on the k nearest points): each normal "
        "from this many nearest points, turned toward the scan's view direction"))
    preview_cell_mm: float = Field(default=1.0, gt=0, le=50, description=(
        "the pass's thinned copy (preview.zarr) that the QA page's maps read instead of the whole pass: every "
        "k-th profile and column, k as for qa_report.cell_mm (tasks.qa_views.thinning_steps); a page whose "
        "thinning is a multiple of the copy's reads the copy (the paper preset: 1/48 of the points)"))


RimEdge = Literal["halfway", "share"]
"""Where a sticker's rim point lies along a profile (``tasks.targets``, ``TargetsConfig.rim_edge``)."""


class TargetsConfig(InputModel):
    max_rms_mm: float = Field(default=0.08, gt=0, le=1)
    min_rim_coverage: float = Field(default=0.85, gt=0, le=1)
    radius_tolerance: float = Field(default=0.1, gt=0, lt=1)
    rim_edge: RimEdge = Field(default="share", description=(
        "where a rim point lies along a profile (tasks.targets): halfway, where the intensity "
        "crosses halfway between sticker and metal; share, from the two pixels' shares of sticker "
        "(each pixel integrates its footprint). Against the simulator's true stickers, 3-D centre "
        "error median halfway -> share: demo 9.9 -> 7.3 um, ci 8.6 -> 5.5, tjoint 10.0 -> 6.3; "
        "the passes' worst misalignment with refine's default target weights: bench/README.md, "
        "the targets' sigma"))


class RegistrationConfig(InputModel):
    min_common_targets: int = Field(default=3, ge=3)
    max_offset_mm: float = Field(default=3.0, gt=0, le=100, description="coarse alignment error bound")
    tolerance_mm: float = Field(default=0.3, gt=0, le=5)
    min_setup_targets: int = Field(default=4, ge=3, le=100, description=(
        "targets a turned setup's match to the first must bring together: any 3 stickers whose "
        "distances agree fit some rigid motion, so 3 is no evidence"))


class SurfaceRegistrationConfig(InputModel):
    """Registration of imported scans on their surfaces alone (``registration: surfaces``;
    ``tasks.surface_registration``). Given poses: refined together, coarse to fine, one level per
    gate of ``gates_given_mm`` (the first above the poses' worst error at a point). No poses:
    every pair registered globally (FPFH on a ``voxel_mm`` grid, RANSAC of ``draws`` triples from
    ``seed``, point-to-plane ICP of the ``top_k`` best distinct hypotheses), accepted on its
    surfaces' evidence (overlap ``min_fitness`` within ``inlier_mm``, RMS ``max_rms_mm``, no pose
    ``distinct_mm`` / ``distinct_deg`` away scoring ``max_runner_up_ratio`` of its overlap), chained
    along a maximum spanning tree of the accepted pairs, then refined together (``gates_global_mm``).
    The defaults suit scans of about 0.5 mm point spacing (the Stanford bunny)."""

    sample_spacing_mm: float = Field(default=2.0, gt=0, le=100, description="thinning of each scan's matched points")
    neighbour_mm: float = Field(default=2.0, gt=0, le=100, description="normal neighbourhood and least match radius")
    normal_neighbours: int = Field(default=16, ge=6, le=200)
    max_plane_rms_mm: float = Field(default=0.25, gt=0, le=10, description="curved neighbourhoods are not matched")
    min_normal_cos: float = Field(default=0.8, gt=0, le=1)
    surface_sigma_mm: float = Field(default=0.15, gt=0, le=10)
    max_points_per_pair: int = Field(default=2000, ge=100, le=1_000_000)
    iterations_per_level: int = Field(default=10, ge=1, le=100)
    tolerance_mm: float = Field(default=0.01, gt=0, le=1, description="the last level stops when no point moves more")
    gates_given_mm: tuple[float, ...] = Field(default=(16.0, 8.0, 4.0, 2.0, 1.0), min_length=1, max_length=20)
    gates_global_mm: tuple[float, ...] = Field(default=(8.0, 4.0, 2.0, 1.0), min_length=1, max_length=20)
    voxel_mm: float = Field(default=3.0, gt=0, le=1000, description="FPFH keypoint grid (features over 5 voxels)")
    ransac_inlier_mm: float = Field(default=4.5, gt=0, le=1000)
    inlier_mm: float = Field(default=1.0, gt=0, le=100, description="a surface sample overlaps within this")
    max_rms_mm: float = Field(default=0.4, gt=0, le=100)
    distinct_mm: float = Field(default=10.0, gt=0, le=10000)
    distinct_deg: float = Field(default=10.0, gt=0, le=180)
    min_fitness: float = Field(default=0.25, gt=0, le=1)
    max_runner_up_ratio: float = Field(default=0.7, gt=0, le=1)
    draws: int = Field(default=20000, ge=1, le=10_000_000)
    top_k: int = Field(default=4, ge=1, le=100)
    seed: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _descending(self) -> "SurfaceRegistrationConfig":
        for name in ("gates_given_mm", "gates_global_mm"):
            gates = getattr(self, name)
            if any(g <= 0 for g in gates) or any(b > a for a, b in zip(gates, gates[1:])):
                raise ValueError(f"{name} must be positive and descending, got {list(gates)}")
        return self


class RefineConfig(InputModel):
    """Joint refinement of the pass poses on targets and overlapping surfaces (tasks.refine).
    Off, the poses are the paper's: targets alone."""

    enabled: bool = True
    sample_spacing_mm: float = Field(default=1.0, gt=0, le=20, description="thinning of each pass's source points")
    surface_spacing_mm: float = Field(default=0.2, gt=0, le=5, description=(
        "each pass's measured surface is read at about this spacing (every n-th profile and column "
        "of its grid, n >= 1): the points the other passes are matched against"))
    neighbour_mm: float = Field(default=1.0, gt=0, le=10, description="farthest matched point and normal neighbourhood")
    normal_neighbours: int = Field(default=16, ge=6, le=200)
    max_plane_rms_mm: float = Field(default=0.02, gt=0, le=1, description="curved neighbourhoods are not matched")
    min_normal_cos: float = Field(default=0.95, gt=0, le=1)
    max_distance_mm: float = Field(default=0.5, gt=0, le=10, description="first gate on point-to-plane distance")
    final_distance_mm: float = Field(default=0.1, gt=0, le=10, description="last gate on point-to-plane distance")
    target_sigma_mm: float = Field(default=0.03, gt=0, le=1, description=(
        "a target pair's expected error where its targets' own are not used (target_sigma_rim_factor null)"))
    target_sigma_rim_factor: float | None = Field(default=0.5, gt=0, le=10, description=(
        "each target centre's expected error this times its rim fit's RMS (at least "
        "target_sigma_floor_mm, more for a height off the sample's: target_height_gate), a pair's "
        "the two combined; null: target_sigma_mm for every pair. Worst pass misalignment against "
        "the simulator's truth, halfway rim edges and 0.03 mm for all -> share and these defaults "
        "(bench/README.md, the targets' sigma): paper 17.8 -> 6.0 um, demo 30.2 -> 19.7, "
        "ci 33.0 -> 17.9, tjoint 25.2 -> 10.5, tjoint-single 32.7 -> 18.8"))
    target_sigma_floor_mm: float = Field(default=0.002, gt=0, le=1, description=(
        "the least expected error of a target centre (a rim fit's RMS can be near zero by chance)"))
    target_height_gate: float | None = Field(default=2.0, gt=0, le=100, description=(
        "a target centre whose rim fit found an edge height off the sample's median by more than "
        "this many of its expected spread (its own height sigma and the heights' unexplained "
        "scatter) gets target_height_factor x its centre's move for that height added to its sigma "
        "(tasks.target_weights); null: none. Used with target_sigma_rim_factor"))
    target_height_factor: float = Field(default=4.0, ge=0, le=100, description=(
        "the added sigma per mm of a gated centre's move (target_height_gate)"))
    target_height_max_spread: float = Field(default=2.0, gt=0, le=100, description=(
        "the heights are gated on only where their robust spread is at most this many times the "
        "fits' own height sigma (median): where they measure one paper edge. At the sensor's full "
        "resolution (the paper preset) the fits are precise and their heights scatter far more "
        "(spread 20.7 um, own sigma 6.4): gating there spoilt the worst pass 5.8 -> 13.6 um"))
    surface_sigma_mm: float = Field(default=0.05, gt=0, le=1, description=(
        "a surface correspondence's expected error: not the sensor noise alone (~0.01 mm) but what "
        "the local-plane model leaves on rough, textured, differently sampled surfaces; measured on "
        "the demo sample, worst pass misalignment 64/42/30/28/33 um at 0.02/0.03/0.05/0.1/0.2 mm"))
    max_points_per_pair: int = Field(default=3000, ge=100, le=1_000_000)
    normal_space_sampling: bool = Field(default=False, description=(
        "a pair's points are taken round-robin over bins of normal direction (slopes before more "
        "plate) instead of at random; measured, median of the pass medians / worst pass: demo 8.8 -> "
        "7.8 / 31.4 -> 31.8 um, paper 8.4 -> 7.8 / 17.7 -> 18.9 um: off until it helps the worst pass"))
    max_iterations: int = Field(default=10, ge=1, le=100)
    tolerance_mm: float = Field(default=0.001, gt=0, le=1, description="stop when no pass point moves more")
    surfaces: SurfaceRegistrationConfig = Field(default=SurfaceRegistrationConfig(), description=(
        "samples of imported scans (registration: surfaces): their registration on the surfaces alone"))

    @model_validator(mode="after")
    def _gates(self) -> "RefineConfig":
        if self.final_distance_mm > self.max_distance_mm:
            raise ValueError("final_distance_mm must not exceed max_distance_mm")
        return self


class MergeConfig(InputModel):
    """Box-grid merge at ``cell_mm`` where the surface bends, at ``coarse_factor`` times that where
    it is flat (non-uniform resolution; 1: uniform, the paper's)."""

    cell_mm: float = Field(default=0.1, gt=0, le=10, description="box-grid filter cell (paper: 0.1 mm)")
    coarse_factor: int = Field(default=4, ge=1, le=16, description=(
        "a coarse cell is this many fine cells on an edge; its fine cells merge into one point where flat"))
    flat_normal_deg: float = Field(default=4.0, gt=0, le=90, description=(
        "flat: every fine cell's normal within this angle of the coarse cell's mean normal"))
    flat_deviation_mm: float = Field(default=0.02, gt=0, le=1, description=(
        "flat: every fine cell's point within this distance of the coarse cell's plane; above a fine "
        "cell mean's noise and the passes' residual misalignment (measured on the paper preset: 0.01 "
        "kept 63 % of the fine cells fine, 0.02 43 %, 0.04 39 %)"))
    weld_zone_mm: float = Field(default=15.0, ge=0, le=1000, description=(
        "cells within this distance of the manifest's weld line (plus the setup's placement "
        "tolerance) stay fine, flat or not: the zone FE models of the weld toes need; 0: off "
        "(needs the setups' T_world_specimen_nominal, else curvature alone decides)"))


class SegmentConfig(InputModel):
    """Two setups: the components holding the stickers seen in both are the part. One setup: the
    fixture's plane, the part's drawing box where the setup puts it, one body of its size
    (``tasks.single_setup``); the fields below ``link_mm`` are for that case."""

    link_mm: float = Field(default=1.0, gt=0, le=50, description="points closer than this are connected")
    up_world: Vector3 = Field(default=(0.0, 0.0, 1.0), description=(
        "single setup: the cell's up direction in the robot (world) frame; the fixture's plane is "
        "the lowest large plane facing it"))
    plane_clearance_mm: float = Field(default=1.0, ge=0, le=50, description=(
        "single setup: points within this of the fixture's plane (or below it) go with it"))
    size_tolerance: float = Field(default=0.1, ge=0, le=1, description=(
        "the kept body's two longest extents may exceed the drawing box's by this fraction (more: "
        "refused, the setups were not registered as one body or the fixture is kept)"))
    min_seen_fraction: float = Field(default=0.7, gt=0, le=1, description=(
        "single setup: and fall short of them down to this fraction (a part not scanned all round)"))
    underside_fill_mm: float = Field(default=1.0, ge=0, le=20, description=(
        "single setup: the part's underside, never seen, is closed by a plane at its lowest measured "
        "height, one point per this many mm (marked not measured); 0: left open (Poisson then runs "
        "out to its bounding cube: no watertight mesh)"))


class PoissonConfig(InputModel):
    poisson_depth: int = Field(default=12, ge=4, le=14, description="octree depth (paper: 12)")
    samples_per_node: float = Field(default=1.5, gt=0, le=50)
    point_weight: float = Field(default=4.0, ge=0, le=100)
    poisson_scale: float = Field(default=1.3, ge=1.0, le=3.0, description=(
        "reconstruction cube over the points' bounding cube; > 1 so that unscanned faces (the "
        "specimen's ends) close inside it instead of being cut open"))


class WeldGeometryConfig(InputModel):
    """The weld measured on the specimen's merged points (``tasks.weld_geometry``): sections
    across each of the manifest's weld lines, fits per toe, judged against ``acceptance``."""

    section_step_mm: float = Field(default=1.0, gt=0, le=100, description="distance between sections along the line")
    section_half_width_mm: float = Field(default=0.5, gt=0, le=10, description=(
        "a section reads the points this close to it along the line (the toe fits; the figures vary "
        "over ~15 mm along a weld)"))
    height_half_width_mm: float = Field(default=0.15, gt=0, le=10, description=(
        "the peak (reinforcement height) is read this close to the section: bead ripples of 1.5-3 mm "
        "wavelength along the weld would be averaged away over the whole section"))
    reach_mm: float = Field(default=32.0, gt=0, le=500, description="points this far across the line are read")
    plate_window_mm: tuple[float, float] = Field(default=(16.0, 30.0), description=(
        "each plate's line is fitted this far (from, to) beside the weld's centre: beyond the cap and "
        "its HFMI groove (half a 20 mm cap + 3/4 of a 6 mm groove = 14.5 mm)"))
    toe_window_mm: tuple[float, float] = Field(default=(1.5, 1.5), description=(
        "a toe is fitted on this much flank and this much plate around where the weld starts"))
    toe_threshold_mm: float = Field(default=0.1, gt=0, le=5, description="height over the plate where the weld starts")
    min_height_mm: float = Field(default=0.25, ge=0, le=10, description=(
        "a cap lower than this over its plates is no evidence of a weld (a sticker's paper is 0.1 mm; a weld line "
        "placed beside the weld read one as a cap): the section is not measured"))
    groove_min_depth_mm: float = Field(default=0.05, gt=0, le=5, description=(
        "a treated toe's dip below the plate deeper than this is fitted as a groove"))
    groove_plate_gap_mm: float = Field(default=0.5, gt=0, le=10, description=(
        "a stretch of plate longer than this between a groove and the weld's flank: the toe is not "
        "within the groove (part of the original toe is left)"))
    undercut_min_depth_mm: float = Field(default=0.03, gt=0, le=5, description=(
        "an as-welded toe's dip below the plate deeper than this is fitted as undercut"))
    end_margin_mm: float = Field(default=2.0, ge=0, le=100, description=(
        "sections start and stop this far inside where the face's points along the line end (cut edges)"))
    min_normal_cos: float = Field(default=0.2, ge=-1, lt=1, description=(
        "points whose normal is within acos(this) of the face's normal are read (flanks up to ~78 deg)"))
    min_points: int = Field(default=8, ge=4, le=10000, description="fewer points in a fit: not measured")
    acceptance: AcceptanceLimits | None = Field(default=None, description=(
        "acceptance limits per joint and treatment (schemas.acceptance), given inline in the settings "
        "file; None: the project's defaults with their sources, data_catalog/weld_acceptance.yaml"))

    @model_validator(mode="after")
    def _windows(self) -> "WeldGeometryConfig":
        near, far = self.plate_window_mm
        if not 0 < near < far <= self.reach_mm:
            raise ValueError(f"plate_window_mm must be 0 < from < to <= reach_mm ({self.reach_mm}), got {list(self.plate_window_mm)}")
        if min(self.toe_window_mm) <= 0:
            raise ValueError(f"toe_window_mm must be positive, got {list(self.toe_window_mm)}")
        return self


class VolumeConfig(InputModel):
    """The FE model: tetrahedra filling the mesh (gmsh), graded toward the weld (``tasks.volume_mesh``).
    Surface elements of ``weld_size_mm`` within ``weld_zone_mm`` of the weld lines (the cap, its
    toes and an HFMI groove), growing by ``growth`` mm per mm beyond, ``size_mm`` at most; inside,
    the sizes grow from the surface's."""

    size_mm: float = Field(default=3.0, gt=0, le=100, description="largest element edge, away from the weld")
    weld_size_mm: float = Field(default=1.0, gt=0, le=100, description=(
        "element edge on the surface within the weld zone (the global model; finer toe models are "
        "sub-models of the WELD_ZONE_SURFACE set)"))
    weld_zone_mm: float = Field(default=14.0, ge=0, le=1000, description=(
        "distance from a weld line kept at weld_size_mm: half the cap's width plus most of an HFMI "
        "groove (the demo's 20 mm cap and 6 mm groove: 10 + 4.5)"))
    toe_size_mm: float = Field(default=0.5, gt=0, le=100, description=(
        "element edge on the surface at the weld toes the weld stage measured (where fatigue cracks start); "
        "no finer than weld_size_mm: off"))
    toe_zone_mm: float = Field(default=1.0, ge=0, le=100, description="distance from a measured toe kept at toe_size_mm")
    growth: float = Field(default=0.3, gt=0, le=10, description="element size growth per mm beyond the weld zone")
    max_surface_triangles: int = Field(default=150_000, ge=1000, le=50_000_000, description=(
        "the Poisson surface is simplified to at most this many triangles before gmsh reparametrises it "
        "(quadric edge collapse: flat faces first; gmsh had not finished the demo's 487,230 in 8 min)"))
    feature_angle_deg: float = Field(default=40.0, gt=0, lt=180, description=(
        "surface patches split where the normals turn by more (gmsh classifySurfaces)"))
    optimize: bool = Field(default=False, description=(
        "Netgen's optimizer after gmsh's HXT and its own optimizer: better elements (the ci sample's worst "
        "smallest dihedral 13.8 -> 20.0 deg) at about 2.4 times the meshing time"))
    element_order: Literal[1, 2] = Field(default=2, description=(
        "2: quadratic tetrahedra (C3D10, the edge nodes at the edges' midpoints), the element FE programs "
        "advise for stress; 1: linear (C3D4), too stiff for stress but a sixth of the nodes"))
    max_volume_difference: float = Field(default=0.005, gt=0, le=1, description=(
        "the solid's volume against the surface mesh's, relative: beyond it the stage fails"))
    timeout_s: float = Field(default=3600.0, gt=0, le=86_400, description=(
        "gmsh gets this many seconds of CPU time for each try (it runs on one thread: its time on an idle "
        "machine; one that waits on nothing is killed after 4 times as long), beyond which its process is "
        "killed and no model is made (said in volume.json and the report; the run publishes the rest)"))
    keep_surface_after_timeout: bool = Field(default=False, description=(
        "where gmsh ran out of timeout_s remeshing the surface, try once more keeping the surface's own "
        "triangles (the provisional FE model does: its surface is whatever the scan gave so far, and gmsh's "
        "patch classification stalled on one)"))


class StressConfig(InputModel):
    """The stress at the weld toes (``flows.stages.stress``): 2-D plane-strain models of the part's
    cross-sections across the weld, pulled along their length as the fatigue test pulls the part
    (``tasks.section_model``), made from the measured points (``tasks.plate_section``)."""

    section_step_mm: float = Field(default=2.0, gt=0, le=1000, description=(
        "distance between the stress sections along the weld (each a 2-D model; the weld stage's "
        "sections nearest to every step are used)"))
    half_width_mm: float = Field(default=0.5, gt=0, le=10, description=(
        "the points within this distance of a section's plane make its outline"))
    bin_mm: float = Field(default=0.1, gt=0, le=5, description="the outline's spacing along the pull (median height per bin)")
    smooth_mm: float = Field(default=0.3, ge=0, le=10, description=(
        "half-window of the outline's smoothing (a quadratic Savitzky-Golay filter, then a Gaussian of one "
        "bin): the points' noise would otherwise read as notches; 0: none"))
    cut_mm: float = Field(default=15.0, ge=0, le=1000, description=(
        "the section is cut straight across this far inside either end of its measured length, where it is "
        "held and pulled (the unscanned ends are not loaded)"))
    toe_size_mm: float = Field(default=0.1, gt=0, le=10, description=(
        "element size at the measured toes; finer where a section's sharpest measured toe radius is under "
        "four times it (a quarter of that radius, the IIW rule, 0.02 mm at the least)"))
    toe_zone_mm: float = Field(default=0.5, ge=0, le=100, description="distance from a toe kept at toe_size_mm")
    size_mm: float = Field(default=3.0, gt=0, le=100, description=(
        "largest element, away from the toes (the demo's 33 sections: 3 mm against 2 mm, 427,359 nodes "
        "against 667,644, 54 s against 81 s, hot spots within 1.4 %)"))
    growth: float = Field(default=0.3, gt=0, le=10, description="element size growth per mm away from the toes")
    peak_reach_mm: float = Field(default=1.5, gt=0, le=20, description=(
        "a toe's peak stress is the highest on the outline within this distance of the measured toe"))
    plate_window_mm: tuple[float, float] = Field(default=(16.0, 30.0), description=(
        "a toe's plate (its thickness: the nominal stress's area; the membrane stress check) from .. to "
        "this far from the weld's centre, on the toe's side"))
    stem_cut_mm: float = Field(default=20.0, gt=0, le=1000, description=(
        "a T-joint's stem is cut this far above the base plate's face (the base's tests load the base "
        "alone: the stem carries nothing beyond its fillets)"))
    max_nodes_per_solve: int = Field(default=100_000, ge=1000, le=50_000_000, description=(
        "as many sections go to one CalculiX run as this many nodes hold (its memory: ~16 kB a node, "
        "~1.6 GB at the default)"))
    timeout_s: float = Field(default=1800.0, gt=0, le=86_400, description=(
        "gmsh and CalculiX get this many seconds of CPU time each (one thread: their time on an idle machine)"))
    notch_stress: bool = Field(default=False, description=(
        "the IIW effective notch stress too: every section solved again with its notches rounded to "
        "notch_radius_mm (twice the solving time), each toe line's notch hot spot and, with a load range in "
        "the manifest, its fatigue life"))
    notch_radius_mm: float = Field(default=1.0, gt=0, le=10, description=(
        "the notches' fictitious radius (IIW: 1 mm for steel plates 5 mm thick or more); the drawn weld's "
        "toes are rounded to it too"))
    fat_mpa: float = Field(default=225.0, gt=0, le=2000, description=(
        "the fatigue class (notch stress range at 2 million cycles) the estimate uses: IIW's 225 MPa for "
        "steel, as welded, maximum principal stress"))
    fat_slope: float = Field(default=3.0, gt=0, le=30, description="the S-N curve's slope up to 1e7 cycles (22 beyond)")

    @model_validator(mode="after")
    def _windows(self) -> "StressConfig":
        near, far = self.plate_window_mm
        if not 0 < near < far:
            raise ValueError(f"plate_window_mm must be 0 < from < to, got {list(self.plate_window_mm)}")
        return self


class QaReportConfig(InputModel):
    """The sample's QA report (``report.html``, ``flows.stages.qa_report``): how finely its maps
    are gridded and how much of the data its pictures show."""

    cell_mm: float = Field(default=1.0, gt=0, le=50, description=(
        "cell of the coverage and disagreement maps on the part's faces"))
    points_per_pass: int = Field(default=200_000, ge=1000, le=50_000_000, description=(
        "an imported scan's points read for the maps, evenly thinned (a cell's passes are thinned to "
        "about nine points a cell)"))
    sections_per_line: int = Field(default=4, ge=0, le=100, description=(
        "weld cross-sections drawn per weld line: the failing ones first (worst first), then evenly along it"))
    mesh_triangles: int = Field(default=60_000, ge=1000, le=2_000_000, description=(
        "the mesh is simplified to at most this many triangles for its renderings (quadric edge collapse)"))


class ReconstructionConfig(InputModel):
    schema_version: Literal["1.0"] = "1.0"
    denoise: DenoiseConfig = DenoiseConfig()
    targets: TargetsConfig = TargetsConfig()
    registration: RegistrationConfig = RegistrationConfig()
    refine: RefineConfig = RefineConfig()
    merge: MergeConfig = MergeConfig()
    segment: SegmentConfig = SegmentConfig()
    mesh: PoissonConfig = PoissonConfig()
    weld: WeldGeometryConfig = WeldGeometryConfig()
    volume: VolumeConfig = VolumeConfig()
    stress: StressConfig = StressConfig()
    qa_report: QaReportConfig = QaReportConfig()
