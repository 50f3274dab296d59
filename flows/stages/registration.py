"""Stage ``registration``: match targets between passes (the registration graph) and solve all pass
poses together."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.outputs import END_FIGURES, REGISTRATION, REGISTRATION_SUMMARY, Registration, TARGETS
from schemas.stage_documents import MeasuredTurn, PassPair, RegistrationSummary, SetupEvidence
from tasks.frames import screw_axis_as, turn_about_axis
from tasks.graph import register_passes, setup_turn
from tasks.registration import RegistrationError

__all__ = ["register", "no_target_registration"]


def no_target_registration(ctx) -> dict[str, Any]:
    """A sample registered on its surfaces (imported scans, no stickers): no target registration;
    the passes keep their coarse poses here (given, or none) and stage refine registers them."""
    n = len(ctx.names)
    empty3, empty = np.zeros((0, 3)), np.zeros(0)
    REGISTRATION.write(ctx.out, Registration(
        T_common_pass=np.tile(np.eye(4), (n, 1, 1)), residual_mm=empty, inlier=np.zeros(0, bool),
        edge_passes=np.zeros((0, 2), np.int64), points_a=empty3, points_b=empty3, track_positions_mm=empty3,
        specimen_track=np.zeros(0, bool), track_members=np.zeros((0, 2), np.int64), track_centres_mm=empty3,
        **{f"{name}_{end}{unit}": empty for name, unit in END_FIGURES for end in "ab"}))
    method = "none: registration surfaces (the scans are registered on their surfaces in stage refine)"
    REGISTRATION_SUMMARY.write(ctx.out, RegistrationSummary(method=method, pairs=[], pairs_below_min_common=[],
                                                            pass_rms_mm={}, between_setups=[]))
    return {"target_pairs": 0, "method": method}


def _figures(f) -> dict[str, np.ndarray]:
    """One pass's detections' figures, by ``END_FIGURES``'s names, (k,) each."""
    return {"rim_rms": f.rms_mm, "edge_height": f.edge_height_mm, "edge_height_sigma": f.edge_height_sigma_mm,
            "centre_per_height": np.linalg.norm(np.asarray(f.centre_per_height).reshape(-1, 3), axis=1)}


def _end_figures(found, graph) -> dict[str, np.ndarray]:
    """Each pair end's rim fit figures (``END_FIGURES``, both ends): its target in its pass's
    detections, by its centre (the graph carries the detected centres themselves, so the match is
    exact)."""
    by_centre = [{c.tobytes(): i for i, c in enumerate(np.asarray(f.centres, np.float64))} for f in found]
    figures = [_figures(f) for f in found]
    out = {}
    for end, passes, centres in (("a", graph.edge_passes[:, 0], graph.points_a),
                                 ("b", graph.edge_passes[:, 1], graph.points_b)):
        try:
            index = [by_centre[p][np.asarray(c, np.float64).tobytes()] for p, c in zip(passes, centres)]
        except KeyError:
            raise RuntimeError("registration: a target pair's centre is none of its pass's detections") from None
        out.update({f"{name}_{end}{unit}": np.array([figures[p][name][i] for p, i in zip(passes, index)], np.float64)
                    for name, unit in END_FIGURES})
    return out


def _evidence(reg, setups, s: str, n: int, runner_up: int, turn) -> SetupEvidence:
    """A later setup's evidence; turned by a positioner, with the prior's difference and the turn
    the registered stickers give (its axis through the point nearest the calibrated one, pointing
    the calibrated way)."""
    if turn is None:
        return SetupEvidence(a=setups[0], b=s, targets=n, runner_up=runner_up)
    point, direction, angle, slide = screw_axis_as(setup_turn(setups, reg.T_common_pass, setups[0], s),
                                                   turn.axis_direction, turn.angle_deg, turn.axis_point_mm)
    deg, mm = reg.prior_difference[s]
    return SetupEvidence(a=setups[0], b=s, targets=n, runner_up=runner_up, prior="positioner",
                         prior_difference_deg=round(deg, 6), prior_difference_mm=round(mm, 6),
                         turn=MeasuredTurn(axis_point_mm=tuple(round(float(v), 6) for v in point),
                                           axis_direction=tuple(round(float(v), 9) for v in direction),
                                           angle_deg=round(float(angle), 6), slide_mm=round(float(slide), 6)))


def register(ctx) -> dict[str, Any]:
    rc, names = ctx.settings, ctx.names
    setups = [s for s, _ in ctx.manifest.passes()]
    found = [TARGETS.read(r) for r in ctx.inputs["targets"]]
    targets = [f.centres for f in found]
    turns = {s.name: s.positioner for s in ctx.manifest.setups if s.positioner is not None}
    first = setups[0]
    priors = {}
    for name, turn in turns.items():
        if turn.from_setup != first:
            raise ValueError(f"setups.{name}.positioner.from_setup: {turn.from_setup!r}; the registration matches "
                             f"every setup to the first, {first!r}: expected {first!r}")
        # the part's point at p in the first setup lies at T p in this one: this setup's frame into the first's;
        # each setup's coarse frame is its first pass's, off by the robot's error (max_offset_mm) as well
        T = turn_about_axis(turn.axis_point_mm, turn.axis_direction, turn.angle_deg)
        priors[name] = (np.linalg.inv(T), turn.tolerance_mm + rc.max_offset_mm)
    try:
        reg = register_passes(targets, setups, names=names, min_common=rc.min_common_targets,
                              max_offset_mm=rc.max_offset_mm, tolerance_mm=rc.tolerance_mm,
                              min_setup_targets=rc.min_setup_targets, priors=priors)
    except RegistrationError as exc:
        weak = [f"{names[p.pass_a]}|{names[p.pass_b]} ({p.n_common})" for p in exc.weak_pairs]
        raise RegistrationError(f"{exc}; overlapping pass pairs with fewer than {rc.min_common_targets} common "
                                f"targets: {', '.join(weak) or 'none'}", exc.unregistered) from None
    members = np.array([(k, p) for k, track in enumerate(reg.tracks) for p, _ in track], dtype=np.int64)
    centres = np.array([targets[p][t] for track in reg.tracks for p, t in track], dtype=np.float64)
    REGISTRATION.write(ctx.out, Registration(
        T_common_pass=reg.T_common_pass, residual_mm=reg.result.residual_mm, inlier=reg.result.inlier,
        edge_passes=reg.graph.edge_passes, points_a=reg.graph.points_a, points_b=reg.graph.points_b,
        track_positions_mm=reg.track_positions_mm, specimen_track=reg.specimen_track,
        track_members=members.reshape(-1, 2), track_centres_mm=centres.reshape(-1, 3),
        **_end_figures(found, reg.graph)))
    REGISTRATION_SUMMARY.write(ctx.out, RegistrationSummary(
        pairs=[PassPair(a=names[p.pass_a], b=names[p.pass_b], common_targets=p.n_common) for p in reg.pairs],
        pairs_below_min_common=[PassPair(a=names[p.pass_a], b=names[p.pass_b], common_targets=p.n_common)
                                for p in reg.weak_pairs],
        pass_rms_mm={n: (None if not np.isfinite(v) else float(v)) for n, v in zip(names, reg.result.pass_rms_mm)},
        # why each turned setup's match is not a chance agreement: the targets it brought together
        # against the most a clearly different transform did (the fixture's, staying put, or none)
        between_setups=[_evidence(reg, setups, s, n, r, turns.get(s)) for s, (n, r) in reg.setup_evidence.items()]))
    res = reg.result.residual_mm[reg.result.inlier]
    return {"target_pairs": int(reg.result.inlier.sum()), "outlier_pairs": int((~reg.result.inlier).sum()),
            "residual_median_mm": float(np.median(res)), "residual_max_mm": float(res.max()),
            "specimen_targets": int(reg.specimen_track.sum()), "weak_pairs": len(reg.weak_pairs)}
