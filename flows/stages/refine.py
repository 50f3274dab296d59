"""Stage ``refine``: every pass pose again, on the target pairs and the overlapping measured
surfaces together (or, disabled, the target registration's poses: the paper's method)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from flows.stages.contracts import block_rows, zarr_array
from flows.stages.outputs import END_FIGURES, CLOUD, REFINED, REFINE_SUMMARY, REGISTRATION, RefinedPoses
from schemas.stage_documents import RefineSummary, SurfacePair
from tasks.consistency import residual_outliers, surfaces_between_setups
from tasks.refine import SurfaceSample, refine_poses, surface_sample
from tasks.target_weights import HeightSpread, centre_sigmas, height_spread

__all__ = ["refine", "refine_arguments", "pass_surface_sample", "target_pairs", "weighed_target_pairs", "TargetPairs"]


def _thinned_grid(ref, stride: tuple[int, int]) -> np.ndarray:
    """A denoised pass's points, every ``stride`` profile and column, read block by block."""
    points = zarr_array(ref, CLOUD, "points")
    n, m = points.shape[:2]
    step = block_rows(m, chunk_profiles=points.chunks[0])
    rs, cs = stride
    step = max(rs, step // rs * rs)  # blocks start on a kept profile
    return np.concatenate([np.asarray(points[a:a + step])[::rs, ::cs] for a in range(0, n, step)])


def pass_surface_sample(manifest, entry, ref, rc) -> SurfaceSample:
    """One denoised pass's surface sample as the refine stage matches it (``rc``: RefineConfig):
    its grid thinned to about ``surface_spacing_mm``, then ``tasks.refine.surface_sample``."""
    row_mm, col_mm = manifest.grid_pitch_mm(entry)
    stride = (max(1, int(rc.surface_spacing_mm / row_mm)), max(1, int(rc.surface_spacing_mm / col_mm)))
    return surface_sample(_thinned_grid(ref, stride), spacing_mm=rc.sample_spacing_mm, normal_radius_mm=rc.neighbour_mm,
                          neighbours=rc.normal_neighbours, max_plane_rms_mm=rc.max_plane_rms_mm)


def refine_arguments(rc) -> dict[str, Any]:
    """``tasks.refine.refine_poses``'s settings from a RefineConfig, all but the target pairs' sigma
    (``target_pairs`` gives it with the pairs)."""
    return dict(max_iterations=rc.max_iterations, tolerance_mm=rc.tolerance_mm, max_distance_mm=rc.max_distance_mm,
                final_distance_mm=rc.final_distance_mm, neighbour_mm=rc.neighbour_mm,
                normal_neighbours=rc.normal_neighbours, surface_sigma_mm=rc.surface_sigma_mm,
                max_points_per_pair=rc.max_points_per_pair, normal_space=rc.normal_space_sampling,
                min_normal_cos=rc.min_normal_cos, max_plane_rms_mm=rc.max_plane_rms_mm)


@dataclass(frozen=True)
class TargetPairs:
    """The registration's inlier target pairs, as the refinement weighs them (``target_pairs``)."""

    edges: np.ndarray  # (e, 2) int64: the two passes
    points_a: np.ndarray  # (e, 3) mm: the centre in pass a's coarse frame
    points_b: np.ndarray  # (e, 3) mm: in pass b's
    sigma_mm: float | np.ndarray  # each pair's expected error (e,), or one for all
    heights: HeightSpread | None  # the sample's edge heights, each target once (None: not used)
    gated: int  # pair ends whose centre's sigma grew for its height


def weighed_target_pairs(reg, rc) -> TargetPairs:
    """The registration's inlier target pairs and each pair's expected error: each centre's from
    its own rim fit (``tasks.target_weights.centre_sigmas``: ``rc.target_sigma_rim_factor`` x its
    RMS, at least ``rc.target_sigma_floor_mm``, more where its edge height is off the sample's by
    over ``rc.target_height_gate`` of its expected spread), the two combined; or
    ``rc.target_sigma_mm`` for all."""
    inlier = reg.inlier.astype(bool)
    E, A, B = reg.edge_passes[inlier], reg.points_a[inlier], reg.points_b[inlier]
    if rc.target_sigma_rim_factor is None or not len(E):
        return TargetPairs(E, A, B, rc.target_sigma_mm, None, 0)
    ends = {end: {name: np.asarray(getattr(reg, f"{name}_{end}{unit}"), np.float64)[inlier]
                  for name, unit in END_FIGURES} for end in "ab"}
    spread = None
    if rc.target_height_gate is not None:  # the sample's heights, each target (pass, centre) once
        keys = np.concatenate([np.column_stack([E[:, 0], A]), np.column_stack([E[:, 1], B])])
        _, first = np.unique(keys, axis=0, return_index=True)
        spread = height_spread(*(np.concatenate([ends["a"][n], ends["b"][n]])[first]
                                 for n in ("edge_height", "edge_height_sigma")))
    (a, gated_a), (b, gated_b) = (
        centre_sigmas(e["rim_rms"], e["edge_height"], e["edge_height_sigma"], e["centre_per_height"], spread,
                      rim_factor=rc.target_sigma_rim_factor, floor_mm=rc.target_sigma_floor_mm,
                      gate=rc.target_height_gate, height_factor=rc.target_height_factor,
                      max_spread_ratio=rc.target_height_max_spread) for e in (ends["a"], ends["b"]))
    return TargetPairs(E, A, B, np.sqrt(a * a + b * b), spread, int(gated_a.sum() + gated_b.sum()))


def target_pairs(reg, rc) -> tuple[np.ndarray, np.ndarray, np.ndarray, float | np.ndarray]:
    """``weighed_target_pairs``'s pairs (passes, centre in a, centre in b) and sigmas."""
    t = weighed_target_pairs(reg, rc)
    return t.edges, t.points_a, t.points_b, t.sigma_mm


def _heights_metrics(t: TargetPairs, rc) -> dict[str, Any] | None:
    """What the sample's edge heights said and did (the stage's metrics), or None where unused."""
    if t.heights is None:
        return None
    h = t.heights
    return {"median_mm": round(h.median_mm, 6), "spread_mm": round(h.spread_mm, 6),
            "own_sigma_mm": round(h.own_sigma_mm, 6), "scatter_mm": round(h.scatter_mm, 6),
            "consistent": h.consistent(rc.target_height_max_spread), "gated_pair_ends": t.gated}


def refine(ctx) -> dict[str, Any]:
    rc, names = ctx.settings, ctx.names
    reg = REGISTRATION.read(ctx.inputs["registration"])
    T_targets = reg.T_common_pass
    inlier = reg.inlier.astype(bool)
    pairs, counts, steps, samples, heights = {}, {}, [], [], None
    T = T_targets
    target_res = reg.residual_mm[inlier]
    if rc.enabled:
        samples = [pass_surface_sample(ctx.manifest, entry, r, rc)
                   for (_, entry), r in zip(ctx.manifest.passes(), ctx.inputs["denoise"])]
        if not any(len(sample.points_mm) for sample in samples):
            raise ValueError(
                f"refine: no pass kept a surface point to match: none has {rc.normal_neighbours} points "
                f"(refine.normal_neighbours) within {rc.neighbour_mm} mm (refine.neighbour_mm) on a plane within "
                f"{rc.max_plane_rms_mm} mm (refine.max_plane_rms_mm) at this sample's point spacing; widen "
                f"refine.neighbour_mm or lower refine.normal_neighbours, or set refine.enabled: false")
        weighed = weighed_target_pairs(reg, rc)
        heights = _heights_metrics(weighed, rc)
        result = refine_poses(samples, T_targets, weighed.edges, weighed.points_a, weighed.points_b,
                              **refine_arguments(rc), target_sigma_mm=weighed.sigma_mm)
        T, pairs, counts, steps = result.T_common_pass, result.pair_rms_mm, result.pair_count, result.step_mm
        target_res = result.target_residual_mm
    # each physical target where the refined poses put it: the mean of its observations
    track, pass_of = reg.track_members[:, 0], reg.track_members[:, 1]
    seen = np.einsum("nij,nj->ni", T[pass_of, :3, :3], reg.track_centres_mm) + T[pass_of, :3, 3]
    n_tracks = len(reg.track_positions_mm)
    counts_per_track = np.bincount(track, minlength=n_tracks)[:, None]
    positions = np.stack([np.bincount(track, seen[:, i], minlength=n_tracks) for i in range(3)], axis=1)
    positions /= np.maximum(counts_per_track, 1)
    moved = max((float(np.abs(np.einsum("ij,nj->ni", (T[k] - T_targets[k])[:3, :3], s.points_mm)
                              + (T[k] - T_targets[k])[:3, 3]).max(initial=0.0)) for k, s in enumerate(samples)),
                default=0.0)
    REFINED.write(ctx.out, RefinedPoses(T_common_pass=T, track_positions_mm=positions,
                                        specimen_track=reg.specimen_track,
                                        target_residual_mm=np.asarray(target_res, dtype=np.float64)))
    REFINE_SUMMARY.write(ctx.out, RefineSummary(
        surface_pairs=[SurfacePair(a=names[a], b=names[b], points=counts[(a, b)], rms_mm=pairs[(a, b)])
                       for a, b in sorted(pairs)], step_mm=steps))
    surface_rms = list(pairs.values())
    # each pass's target residuals (its edges) against the sample's: a pass whose data or poses
    # disagree with the others stands out here even when every file is valid
    edges = reg.edge_passes[inlier]
    per_pass = {}
    for k, name in enumerate(names):
        mine = np.asarray(target_res)[(edges == k).any(axis=1)] if len(edges) else np.zeros(0)
        per_pass[name] = float(np.median(mine)) if len(mine) else float("nan")
    flagged = residual_outliers(per_pass, floor_mm=rc.target_sigma_mm)
    setup_of = [setup for setup, _ in ctx.manifest.passes()]
    shared = surfaces_between_setups(setup_of, pairs, counts) if rc.enabled else None
    return {"enabled": rc.enabled, "iterations": len(steps), "last_step_mm": steps[-1] if steps else 0.0,
            "surface_pairs": len(pairs), "surface_points": int(sum(counts.values())),
            "largest_pose_change_mm": moved,
            "surface_rms_median_mm": float(np.median(surface_rms)) if surface_rms else None,
            "target_residual_median_mm": float(np.median(target_res)) if len(target_res) else None,
            "target_residual_max_mm": float(np.max(target_res)) if len(target_res) else None,
            "registration_method": {name: "targets" for name in names},
            "target_heights": heights,
            "checks": {"target_residuals": {"per_pass_median_mm": {p: (round(v, 6) if np.isfinite(v) else None)
                                                                   for p, v in per_pass.items()},
                                            "flagged": flagged},
                       **({"surfaces_between_setups": shared} if shared else {})}}
