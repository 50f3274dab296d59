"""Stage ``refine`` for a sample registered on its surfaces (``registration: surfaces``: imported
scans, no stickers): the scans' poses from their surfaces alone (``tasks.surface_registration``).

- every scan has a given pose (a .conf, E57): the denoised scans are already in the world frame
  by them; all poses refined together, coarse to fine (``refine.surfaces.gates_given_mm``), the
  first scan held fixed: "surfaces from given poses";
- no scan has one: every pair registered globally (FPFH + RANSAC + ICP, each pair accepted only
  on its surfaces' evidence), chained along a maximum spanning tree of the accepted pairs from
  the first scan, then refined together: "surfaces, global". A scan that no chain of accepted
  pairs reaches stops the run with the reasons, never a guessed pose.

Deterministic: the RANSAC is drawn with numpy from ``refine.surfaces.seed``, the k-d tree queries
use one worker, features and normals are per point (``tasks.surface_registration``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.contracts import zarr_array
from flows.stages.outputs import CLOUD, REFINED, REFINE_SUMMARY, RefinedPoses
from schemas.stage_documents import RefineSummary, SurfaceMatch, SurfacePair
from tasks.refine import NothingToRefine, surface_sample
from tasks.surface_registration import (PairOptions, RefineOptions, refine_scan_poses, register_scans,
                                        scan_features)

__all__ = ["refine_on_surfaces", "register_on_surfaces", "GIVEN", "GLOBAL", "GIVEN_UNREFINED"]

GIVEN = "surfaces from given poses"
GIVEN_UNREFINED = "given poses (refine disabled)"
GLOBAL = "surfaces, global"


def _scan_cloud(ref) -> tuple[np.ndarray, np.ndarray]:
    """A denoised scan's points (n, 3) float64, mm, coarse frame, and its view direction (3,)."""
    points = np.asarray(zarr_array(ref, CLOUD, "points")[...], dtype=np.float64).reshape(-1, 3)
    sensor = np.asarray(zarr_array(ref, CLOUD, "sensor_origins")[0], dtype=np.float64)
    view = sensor - points[0]
    return points, view / np.linalg.norm(view)


def _refine_options(sc, gates) -> RefineOptions:
    return RefineOptions(gates_mm=tuple(gates), neighbour_mm=sc.neighbour_mm, max_plane_rms_mm=sc.max_plane_rms_mm,
                         surface_sigma_mm=sc.surface_sigma_mm, min_normal_cos=sc.min_normal_cos,
                         normal_neighbours=sc.normal_neighbours, max_points_per_pair=sc.max_points_per_pair,
                         iterations_per_level=sc.iterations_per_level, tolerance_mm=sc.tolerance_mm)


def _pair_figures(names, result) -> list[SurfacePair]:
    return [SurfacePair(a=names[a], b=names[b], points=result.pair_count[(a, b)], rms_mm=result.pair_rms_mm[(a, b)])
            for a, b in sorted(result.pair_rms_mm)]


def refine_on_surfaces(ctx) -> dict[str, Any]:
    """Stage refine's body for imported scans, no stickers (the registry picks it): the scans
    registered on their surfaces (settings ``refine.surfaces``)."""
    return register_on_surfaces(ctx, ctx.settings.surfaces)


def register_on_surfaces(ctx, sc) -> dict[str, Any]:
    """The body of stage refine for a surfaces sample; ``sc`` its settings ``refine.surfaces``."""
    rc, names = ctx.settings, ctx.names
    entries = [e for _, e in ctx.manifest.passes()]
    clouds = [_scan_cloud(r) for r in ctx.inputs["denoise"]]
    n = len(clouds)
    summary: dict[str, Any] = {}
    if n == 1:
        T, method, result = np.eye(4)[None], "single scan", None
    elif entries[0].has_pose and not rc.enabled:
        T, method, result = np.tile(np.eye(4), (n, 1, 1)), GIVEN_UNREFINED, None
    elif entries[0].has_pose:
        samples = [surface_sample(p, spacing_mm=sc.sample_spacing_mm, normal_radius_mm=sc.neighbour_mm,
                                  neighbours=sc.normal_neighbours, max_plane_rms_mm=sc.max_plane_rms_mm,
                                  view_direction=v) for p, v in clouds]
        try:
            result = refine_scan_poses(samples, np.tile(np.eye(4), (n, 1, 1)),
                                       options=_refine_options(sc, sc.gates_given_mm), fixed=0)
        except NothingToRefine:
            raise ValueError(f"refine: no two scans overlap within {sc.gates_given_mm[0]} mm "
                             "(refine.surfaces.gates_given_mm) at their given poses; are the poses those of these "
                             "scans, in their units?") from None
        T, method = result.T_common_pass, GIVEN
    else:
        features = [scan_features(p, view_direction=v, voxel_mm=sc.voxel_mm, sample_spacing_mm=sc.sample_spacing_mm,
                                  neighbour_mm=sc.neighbour_mm, max_plane_rms_mm=sc.max_plane_rms_mm,
                                  normal_neighbours=sc.normal_neighbours) for p, v in clouds]
        pair = PairOptions(ransac_inlier_mm=sc.ransac_inlier_mm, inlier_mm=sc.inlier_mm, max_rms_mm=sc.max_rms_mm,
                           distinct_mm=sc.distinct_mm, distinct_deg=sc.distinct_deg, min_fitness=sc.min_fitness,
                           max_runner_up_ratio=sc.max_runner_up_ratio, draws=sc.draws, top_k=sc.top_k, seed=sc.seed)
        reg = register_scans(features, pair=pair, refine=_refine_options(sc, sc.gates_global_mm), fixed=0)
        if not reg.registered.all():
            refused = [f"{names[k]} ({reg.reason[k]})" for k in range(n) if not reg.registered[k]]
            raise ValueError(f"refine: scans not registered on their surfaces (no chain of verified pairs to "
                             f"{names[0]}): {'; '.join(refused)}; give rough poses (--poses) or scans that overlap more")
        T, method, result = reg.T_world_scan, GLOBAL, reg.refine
        summary["pairs"] = [SurfaceMatch(a=names[p.source], b=names[p.target], accepted=p.accepted, reason=p.reason,
                                         fitness=round(p.fitness, 6),
                                         rms_mm=None if not np.isfinite(p.rms_mm) else p.rms_mm,
                                         runner_up_fitness=round(p.runner_up_fitness, 6), matches=p.matches)
                            for p in reg.pairs]
        summary["tree"] = [(names[a], names[b]) for a, b in reg.tree]
    pairs = _pair_figures(names, result) if result is not None else []
    steps = list(result.step_mm) if result is not None else []
    REFINED.write(ctx.out, RefinedPoses(T_common_pass=T, track_positions_mm=np.zeros((0, 3)),
                                        specimen_track=np.zeros(0, bool), target_residual_mm=np.zeros(0)))
    REFINE_SUMMARY.write(ctx.out, RefineSummary(method=method, surface_pairs=pairs, step_mm=steps, **summary))
    moved = max(float(np.abs(p @ (T[k] - np.eye(4))[:3, :3].T + (T[k] - np.eye(4))[:3, 3]).max(initial=0.0))
                for k, (p, _) in enumerate(clouds))
    rms = [p.rms_mm for p in pairs]
    return {"enabled": rc.enabled, "registration": "surfaces", "iterations": len(steps),
            "last_step_mm": steps[-1] if steps else 0.0, "surface_pairs": len(pairs),
            "surface_points": int(sum(p.points for p in pairs)), "largest_pose_change_mm": moved,
            "surface_rms_median_mm": float(np.median(rms)) if rms else None,
            "target_residual_median_mm": None, "target_residual_max_mm": None,
            "registration_method": {name: method for name in names}, "reference_pass": names[0], "checks": {}}
