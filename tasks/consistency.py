"""Checks that valid-looking input is also consistent: what a damaged or doctored pass looks like
when every file still decodes and every hash matches (issue 10, item 5).

Hard failures (the input cannot be right, the pass is named and the run stops):
- profile times must be finite and strictly increasing;
- a logged flange pose must be rigid (orthonormal rotation, determinant +1, last row 0 0 0 1),
  to the manifest's own tolerance for poses;
- consecutive logged poses must not jump: the flange may move at most ``STEP_FACTOR`` times the
  pass's nominal speed over the profile interval (plus ``STEP_SLACK_MM``) and turn at most
  ``MAX_TURN_RAD`` per profile.

Flags (the run goes on; the report states them and the command warns):
- a storage chunk boundary where the measured surface steps far more than it does between the
  profiles around it (``chunk_jumps``): a chunk out of place;
- a pass whose target residuals after the pose solve stand far above the sample's
  (``residual_outliers``): its data or poses disagree with the others;
- the surfaces two setups both saw (``surfaces_between_setups``): none overlapping after the
  refinement (only the stickers tie the setups: nothing confirms their match), or overlapping far
  worse than one setup's passes do.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["POSE_TOLERANCE", "STEP_FACTOR", "STEP_SLACK_MM", "MAX_TURN_RAD", "MotionCheck", "profile_steps",
           "chunk_jumps", "residual_outliers", "surfaces_between_setups"]

POSE_TOLERANCE = 1e-6  # largest entry of R^T R - I, as for the manifest's poses (schemas.common)
STEP_FACTOR = 2.0
STEP_SLACK_MM = 0.05
MAX_TURN_RAD = 0.01
MIN_TRAVEL_SHARE = 0.5  # the logged flange must travel at least this share of the nominal sweep
CHUNK_JUMP_FACTOR = 10.0  # a boundary step this many times the largest step around it
CHUNK_JUMP_FLOOR_MM = 0.05  # and at least this large (the sensor's noise is ~0.01 mm)
CHUNK_JUMP_CONTEXT = 8  # profile steps looked at on each side of a boundary
RESIDUAL_FACTOR = 3.0  # a pass's median target residual this many times the sample's median
SHARED_SURFACE_FACTOR = 3.0  # surfaces of two setups this many times further apart than one setup's
SHARED_SURFACE_FLOOR_MM = 0.01  # and at least this much further (the sensor's noise)


@dataclass
class MotionCheck:
    """Profile times and logged flange poses of one pass, fed block by block in profile order
    (``feed``); raises ValueError naming the pass and the profile at the first inconsistency.
    ``summary`` is what was checked and the extremes seen."""

    pass_id: str
    speed_mm_s: float
    _last_t: float | None = None
    _last_T: np.ndarray | None = None
    _poses: bool = False
    _profiles: int = 0
    _worst_rotation: float = 0.0
    _largest_step_ratio: float = 0.0
    _largest_turn_rad: float = 0.0
    _path_mm: float = 0.0  # the logged flange's travel, summed over the profiles
    _first_t: float | None = None
    _intervals: list[float] = field(default_factory=lambda: [np.inf, 0.0])

    def _fail(self, profile: int, what: str) -> None:
        raise ValueError(f"pass {self.pass_id}: profile {profile}: {what}")

    def feed(self, start: int, timestamp_s: np.ndarray, T_world_flange: np.ndarray | None) -> None:
        t = np.asarray(timestamp_s, dtype=np.float64)
        if start != self._profiles:
            raise ValueError(f"pass {self.pass_id}: profiles fed out of order ({start}, expected {self._profiles})")
        bad = np.flatnonzero(~np.isfinite(t))
        if len(bad):
            self._fail(start + int(bad[0]), f"timestamp_s is {t[bad[0]]}, expected a finite time")
        times = t if self._last_t is None else np.concatenate([[self._last_t], t])
        first = start if self._last_t is None else start - 1
        dt = np.diff(times)
        bad = np.flatnonzero(dt <= 0)
        if len(bad):
            i = int(bad[0])
            self._fail(first + i + 1, f"timestamp_s {times[i + 1]:.6f} s is not after the profile before "
                                      f"({times[i]:.6f} s): profiles must be stored in time order")
        if len(dt):
            self._intervals = [min(self._intervals[0], float(dt.min())), max(self._intervals[1], float(dt.max()))]
        if T_world_flange is not None:
            self._poses = True
            self._check_poses(start, times, first, np.asarray(T_world_flange, dtype=np.float64))
        if self._first_t is None and len(t):
            self._first_t = float(t[0])
        self._last_t = float(t[-1]) if len(t) else self._last_t
        self._profiles += len(t)

    def _check_poses(self, start: int, times: np.ndarray, first: int, T: np.ndarray) -> None:
        if not np.isfinite(T).all():
            row = int(np.flatnonzero(~np.isfinite(T.reshape(len(T), -1)).all(axis=1))[0])
            self._fail(start + row, "T_world_flange holds NaN or inf")
        bottom = np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
        if (bottom > 0).any():
            self._fail(start + int(np.argmax(bottom > 0)), "T_world_flange's last row is not [0, 0, 0, 1]")
        R = T[:, :3, :3]
        deviation = np.abs(np.einsum("nki,nkj->nij", R, R) - np.eye(3)).max(axis=(1, 2))
        worst = int(np.argmax(deviation)) if len(deviation) else 0
        if len(deviation) and deviation[worst] > POSE_TOLERANCE:
            self._fail(start + worst, f"T_world_flange is not rigid: its rotation part is off orthonormal by "
                                      f"{deviation[worst]:.2g} (largest entry of R^T R - I; a rigid pose: at most "
                                      f"{POSE_TOLERANCE:g}), e.g. scaled or sheared")
        det = np.linalg.det(R)
        if (det < 0).any():
            self._fail(start + int(np.argmax(det < 0)), "T_world_flange is a reflection (determinant -1), not a pose")
        self._worst_rotation = max(self._worst_rotation, float(deviation.max(initial=0.0)))
        poses = T if self._last_T is None else np.concatenate([self._last_T[None], T])
        if len(poses) > 1:
            step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
            allowed = STEP_FACTOR * self.speed_mm_s * np.diff(times) + STEP_SLACK_MM
            ratio = step / allowed
            i = int(np.argmax(ratio))
            if ratio[i] > 1:
                self._fail(first + i + 1, f"the logged flange pose jumps {step[i]:.3f} mm from the profile before "
                                          f"in {np.diff(times)[i]:.4f} s (at most {allowed[i]:.3f} mm at {STEP_FACTOR:g} "
                                          f"x the pass's nominal {self.speed_mm_s:g} mm/s): the pose log is damaged")
            cos = (np.einsum("nij,nij->n", poses[1:, :3, :3], poses[:-1, :3, :3]) - 1) / 2
            turn = np.arccos(np.clip(cos, -1.0, 1.0))
            j = int(np.argmax(turn))
            if turn[j] > MAX_TURN_RAD:
                self._fail(first + j + 1, f"the logged flange pose turns {turn[j]:.4f} rad from the profile before "
                                          f"(at most {MAX_TURN_RAD:g} rad): the pose log is damaged")
            self._largest_step_ratio = max(self._largest_step_ratio, float(ratio[i]))
            self._path_mm += float(step.sum())
            self._largest_turn_rad = max(self._largest_turn_rad, float(turn[j]))
        self._last_T = T[-1].copy() if len(T) else self._last_T

    def summary(self) -> dict:
        """What was checked, after the last block; also refuses a pose log that does not move: the
        logged flange travels less than half the nominal sweep over the pass's time (poses stuck
        at one value, a log of another robot axis), which the per-profile limits cannot see."""
        if self._poses and self._profiles > 1:
            nominal = self.speed_mm_s * (self._last_t - self._first_t)
            if self._path_mm < MIN_TRAVEL_SHARE * nominal:
                raise ValueError(f"pass {self.pass_id}: the logged flange poses travel {self._path_mm:.3f} mm over the "
                                 f"pass, the nominal sweep {nominal:.1f} mm ({self.speed_mm_s:g} mm/s for "
                                 f"{self._last_t - self._first_t:.2f} s); expected the robot's motion (is the pose log "
                                 "stuck?)")
        out = {"profiles": self._profiles, "times": "finite, strictly increasing",
               "profile_interval_s": [round(v, 9) for v in self._intervals] if self._profiles > 1 else None,
               "logged_poses": self._poses}
        if self._poses:
            out.update(rotation_off_orthonormal=self._worst_rotation,
                       largest_step_of_allowed=round(self._largest_step_ratio, 4),
                       largest_turn_rad=self._largest_turn_rad)
        return out


def profile_steps(z_mm: np.ndarray) -> np.ndarray:
    """(profiles - 1,) the median over columns of |z| change between consecutive profiles (mm,
    columns where both measured; NaN where none is)."""
    z = np.asarray(z_mm, dtype=np.float64)
    d = np.abs(np.diff(z, axis=0))
    out = np.full(len(d), np.nan)
    ok = np.isfinite(d)
    rows = np.flatnonzero(ok.any(axis=1))
    if len(rows):
        masked = np.where(ok[rows], d[rows], np.nan)
        out[rows] = np.nanmedian(masked, axis=1)
    return out


def chunk_jumps(steps: np.ndarray, chunk_profiles: int) -> list[dict]:
    """Storage chunk boundaries (profile b, b a multiple of ``chunk_profiles``) where the surface
    steps (``steps[b - 1]``: from profile b - 1 to b) by more than ``CHUNK_JUMP_FACTOR`` times the
    largest step among the ``CHUNK_JUMP_CONTEXT`` on each side, and by at least
    ``CHUNK_JUMP_FLOOR_MM``: where a chunk's profiles do not continue their neighbours'."""
    steps = np.asarray(steps, dtype=np.float64)
    found = []
    for b in range(chunk_profiles, len(steps) + 1, chunk_profiles):
        step = steps[b - 1]
        around = np.concatenate([steps[max(0, b - 1 - CHUNK_JUMP_CONTEXT):b - 1], steps[b:b + CHUNK_JUMP_CONTEXT]])
        around = around[np.isfinite(around)]
        if not np.isfinite(step) or len(around) < CHUNK_JUMP_CONTEXT:
            continue
        if step >= CHUNK_JUMP_FLOOR_MM and step > CHUNK_JUMP_FACTOR * around.max():
            found.append({"profile": b, "step_mm": round(float(step), 4), "around_mm": round(float(around.max()), 4)})
    return found


def residual_outliers(per_pass: dict[str, float], *, floor_mm: float) -> list[dict]:
    """Passes whose median target residual (mm) is more than ``RESIDUAL_FACTOR`` times the
    median over the passes and more than ``floor_mm`` (the expected target error)."""
    values = np.array([v for v in per_pass.values() if np.isfinite(v)])
    if len(values) < 3:
        return []
    typical = float(np.median(values))
    return [{"pass": p, "residual_median_mm": round(v, 5), "sample_median_mm": round(typical, 5)}
            for p, v in per_pass.items() if np.isfinite(v) and v > RESIDUAL_FACTOR * typical and v > floor_mm]


def surfaces_between_setups(setup_of: list[str], pair_rms_mm: dict[tuple[int, int], float],
                            pair_count: dict[tuple[int, int], int]) -> dict | None:
    """Independent evidence for the match between setups: the refined surface pairs (pass
    indices (a, b) -> RMS mm and point count, as ``tasks.refine`` gives them), split into pairs of
    one setup and pairs across setups (``setup_of``: each pass's setup). None with fewer than two
    setups; else the figures and ``flagged``: None, or why (no pair across setups, or their median
    RMS over ``SHARED_SURFACE_FACTOR`` times one setup's and ``SHARED_SURFACE_FLOOR_MM`` more)."""
    setups = list(dict.fromkeys(setup_of))
    if len(setups) < 2:
        return None
    cross = [k for k in pair_rms_mm if setup_of[k[0]] != setup_of[k[1]] and pair_count.get(k, 0) > 0]
    within = [k for k in pair_rms_mm if setup_of[k[0]] == setup_of[k[1]] and pair_count.get(k, 0) > 0]
    cross_rms = float(np.median([pair_rms_mm[k] for k in cross])) if cross else None
    within_rms = float(np.median([pair_rms_mm[k] for k in within])) if within else None
    flagged = None
    if not cross:
        flagged = (f"no surface of one setup overlaps one of another ({', '.join(setups)}) after the refinement: "
                   "only the stickers tie the setups, nothing confirms their match")
    elif within_rms is not None and cross_rms > max(SHARED_SURFACE_FACTOR * within_rms,
                                                    within_rms + SHARED_SURFACE_FLOOR_MM):
        flagged = (f"the surfaces two setups both saw lie {cross_rms * 1000:.0f} um apart (median RMS over {len(cross)} "
                   f"pass pairs), over {SHARED_SURFACE_FACTOR:g} x one setup's {within_rms * 1000:.0f} um: the setups "
                   "disagree where they overlap")
    return {"pairs_across": len(cross), "points_across": int(sum(pair_count[k] for k in cross)),
            "rms_median_across_mm": None if cross_rms is None else round(cross_rms, 6),
            "pairs_within": len(within), "rms_median_within_mm": None if within_rms is None else round(within_rms, 6),
            "flagged": flagged}
