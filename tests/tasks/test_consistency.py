"""tasks.consistency: what a valid-looking but inconsistent pass looks like (issue 10, item 5)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tasks.consistency import MotionCheck, chunk_jumps, profile_steps, residual_outliers

SPEED = 10.0  # mm/s
DT = 0.032  # s: 0.32 mm profiles at 10 mm/s


def _sweep(n: int, *, tilt_deg: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Times and rigid flange poses of a straight sweep along x at SPEED."""
    t = np.arange(n) * DT
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("xyz", [180.0, tilt_deg, 3.0], degrees=True).as_matrix()
    T[:, :3, 3] = np.stack([SPEED * t, np.full(n, 5.0), np.full(n, 300.0)], axis=1)
    return t, T


def _feed_in_blocks(check: MotionCheck, t: np.ndarray, T: np.ndarray | None, block: int = 64) -> None:
    for start in range(0, len(t), block):
        check.feed(start, t[start:start + block], None if T is None else T[start:start + block])


def test_a_consistent_pass_passes_and_is_summarised():
    t, T = _sweep(300)
    check = MotionCheck("top-L01", SPEED)
    _feed_in_blocks(check, t, T)
    s = check.summary()
    assert s["profiles"] == 300 and s["logged_poses"]
    assert s["rotation_off_orthonormal"] < 1e-12
    assert 0.3 < s["largest_step_of_allowed"] < 0.6  # 0.32 mm of 2 x 0.32 + 0.05 allowed
    assert s["profile_interval_s"] == pytest.approx([DT, DT])


@pytest.mark.parametrize("damage, message", [
    ("scale", r"pass top-L02: profile 130: T_world_flange is not rigid: .* off orthonormal by 0\.02"),
    ("shear", r"pass top-L02: profile 130: T_world_flange is not rigid"),
    ("reflection", r"pass top-L02: profile 130: T_world_flange is a reflection"),
    ("bottom", r"pass top-L02: profile 130: T_world_flange's last row is not \[0, 0, 0, 1\]"),
    ("nan", r"pass top-L02: profile 130: T_world_flange holds NaN"),
    ("jump", r"pass top-L02: profile 130: the logged flange pose jumps 2\.\d+ mm .* the pose log is damaged"),
    ("turn", r"pass top-L02: profile 130: the logged flange pose turns 0\.05\d+ rad"),
])
def test_damaged_poses_name_the_pass_and_the_profile(damage, message):
    t, T = _sweep(300)
    R = T[130, :3, :3]
    if damage == "scale":
        T[130:, :3, :3] = 1.01 * R
    elif damage == "shear":
        T[130:, :3, :3] = R @ np.array([[1, 0.01, 0], [0, 1, 0], [0, 0, 1]])
    elif damage == "reflection":
        T[130, :3, :3] = R @ np.diag([1.0, 1.0, -1.0])
    elif damage == "bottom":
        T[130, 3, 0] = 1e-3
    elif damage == "nan":
        T[130, 0, 3] = np.nan
    elif damage == "jump":
        T[130:, 1, 3] += 2.0
    elif damage == "turn":
        T[130:, :3, :3] = Rotation.from_rotvec([0.05, 0, 0]).as_matrix() @ R
    with pytest.raises(ValueError, match=message):
        _feed_in_blocks(MotionCheck("top-L02", SPEED), t, T)  # profile 130 is inside the third block


@pytest.mark.parametrize("at", [64, 100])  # at a block's first profile, and inside a block
def test_times_out_of_order_name_the_profile(at):
    t, _ = _sweep(300)
    t[at] = t[at - 1]
    with pytest.raises(ValueError, match=rf"pass p: profile {at}: timestamp_s .* is not after the profile before"):
        _feed_in_blocks(MotionCheck("p", SPEED), t, None)
    t, _ = _sweep(300)
    t[at] = np.inf
    with pytest.raises(ValueError, match=rf"pass p: profile {at}: timestamp_s is inf, expected a finite time"):
        _feed_in_blocks(MotionCheck("p", SPEED), t, None)


def test_a_pause_in_the_sweep_is_not_a_jump():
    """The robot may stop between profiles: a longer interval allows a proportionally longer step,
    and a standing robot steps nothing."""
    t, T = _sweep(200)
    t[100:] += 5.0  # a 5 s stop before profile 100
    T[100:, 0, 3] += 0.0  # and it resumes where it stopped
    check = MotionCheck("p", SPEED)
    _feed_in_blocks(check, t, T)
    assert check.summary()["profile_interval_s"][1] == pytest.approx(5.0 + DT)


def test_blocks_must_come_in_profile_order():
    t, T = _sweep(100)
    check = MotionCheck("p", SPEED)
    check.feed(0, t[:50], T[:50])
    with pytest.raises(ValueError, match=r"profiles fed out of order \(60, expected 50\)"):
        check.feed(60, t[60:], T[60:])


def _surface(n: int, cols: int = 40, seed: int = 0) -> np.ndarray:
    """z of a smooth sweep (a weld-like bump drifting slowly across) with 10 um noise."""
    rng = np.random.default_rng(seed)
    rows = np.arange(n)[:, None] * 0.32
    cols_mm = np.arange(cols)[None, :] * 0.32
    z = 2.0 * np.exp(-((cols_mm - 6.0 - 0.01 * rows) / 2.0) ** 2) + rng.normal(0, 0.01, (n, cols))
    z[:, :3] = np.nan  # columns off the part
    return z


def test_a_chunk_out_of_place_is_found_at_its_boundaries():
    z = _surface(1024)
    assert chunk_jumps(profile_steps(z), 128) == []
    swapped = z.copy()
    swapped[256:384] = z[640:768]  # a chunk of the same pass, 3 chunks further on, in its place
    swapped[256:384] += 1.0  # and from a pose where the part stood 1 mm higher
    found = chunk_jumps(profile_steps(swapped), 128)
    assert [f["profile"] for f in found] == [256, 384]
    assert all(f["step_mm"] > 0.9 and f["around_mm"] < 0.05 for f in found)


def test_a_real_step_inside_a_chunk_and_gaps_are_not_flagged():
    z = _surface(1024)
    z[300:] += 1.5  # the part's own edge, between chunk boundaries
    z[500:530] = np.nan  # nothing measured for 30 profiles
    z[:, 20] = np.nan
    assert chunk_jumps(profile_steps(z), 128) == []


def test_profile_steps_is_nan_where_nothing_was_measured():
    z = np.full((5, 4), np.nan)
    z[0:2, 1] = [1.0, 1.2]
    steps = profile_steps(z)
    assert steps[0] == pytest.approx(0.2) and np.isnan(steps[1:]).all()


def test_a_pass_with_residuals_far_above_the_others_is_flagged():
    per_pass = {f"p{i}": 0.010 + 0.001 * i for i in range(8)}
    assert residual_outliers(per_pass, floor_mm=0.02) == []
    per_pass["p3"] = 0.060
    flagged = residual_outliers(per_pass, floor_mm=0.02)
    assert [f["pass"] for f in flagged] == ["p3"] and flagged[0]["residual_median_mm"] == 0.06
    # three times a tiny median is still within the expected target error: not flagged
    quiet = {f"p{i}": 0.002 for i in range(8)} | {"p3": 0.015}
    assert residual_outliers(quiet, floor_mm=0.02) == []
    assert residual_outliers({"a": 0.01, "b": 1.0}, floor_mm=0.02) == []  # too few passes to judge


def test_a_pose_log_that_does_not_move_is_refused():
    """Every profile logged at the sweep's first pose (a stuck log): each step is within the
    limits, but the flange travels nothing while the pass's nominal sweep is 63.7 mm."""
    t, T = _sweep(200)
    T[:] = T[0]
    check = MotionCheck("top-L03", SPEED)
    _feed_in_blocks(check, t, T)
    with pytest.raises(ValueError, match=r"pass top-L03: the logged flange poses travel 0\.000 mm over the pass, the "
                                         r"nominal sweep 63\.7 mm \(10 mm/s for 6\.37 s\); expected the robot's motion"):
        check.summary()


def test_surfaces_between_setups_are_evidence_for_their_match():
    from tasks.consistency import surfaces_between_setups

    setup_of = ["top", "top", "bottom", "bottom"]
    counts = {(0, 1): 900, (2, 3): 800, (0, 2): 300, (1, 3): 200}
    agree = {(0, 1): 0.010, (2, 3): 0.012, (0, 2): 0.013, (1, 3): 0.015}
    ok = surfaces_between_setups(setup_of, agree, counts)
    assert ok["flagged"] is None and ok["pairs_across"] == 2 and ok["points_across"] == 500
    assert ok["rms_median_across_mm"] == 0.014 and ok["rms_median_within_mm"] == 0.011
    apart = surfaces_between_setups(setup_of, {**agree, (0, 2): 0.09, (1, 3): 0.11}, counts)
    assert apart["flagged"] == ("the surfaces two setups both saw lie 100 um apart (median RMS over 2 pass pairs), "
                                "over 3 x one setup's 11 um: the setups disagree where they overlap")
    none = surfaces_between_setups(setup_of, agree, {**counts, (0, 2): 0, (1, 3): 0})
    assert none["flagged"].startswith("no surface of one setup overlaps one of another (top, bottom)")
    assert surfaces_between_setups(["top"] * 2, {(0, 1): 0.01}, {(0, 1): 10}) is None  # one setup: nothing to tie
