"""The positioner's axis, calibrated from stickers: each reconstructed run of a part the
positioner turned between its setups gives the turn its registered poses say (per later setup,
from the first: ``tasks.graph.setup_turn`` on stage refine's poses, as a screw axis); the
calibration is their mean: the axis direction averaged (signs aligned), the point nearest every
axis line (least squares), the angle averaged. Written as a part config's ``positioner`` (YAML)
for ``weldrecon simulate --config`` or ``weldrecon plan --config``, or copied into a cell's
manifests (``setups[].positioner``)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MeasuredAxis", "run_turns", "mean_axis"]


@dataclass(frozen=True)
class MeasuredAxis:
    run: str
    setup: str
    from_setup: str
    point_mm: np.ndarray
    direction: np.ndarray
    angle_deg: float


def _sample_dir(run: Path) -> Path:
    from data_catalog.audit import read_trail

    started = [e for e in read_trail(run) if e.get("kind") == "run-started" and e.get("sample_dir")]
    if not started:
        raise ValueError(f"{run}: its audit trail names no sample (expected a run folder of `weldrecon reconstruct`)")
    return Path(started[-1]["sample_dir"])


def run_turns(run: Path) -> list[MeasuredAxis]:
    """Every later setup's turn from the first, as the run's refined poses give it; ValueError
    naming the run when it has no finished stage refine or a single setup."""
    from data_catalog.audit import read_trail
    from data_catalog.manifests import load_manifest
    from data_catalog.stages import StageStore
    from flows.stages.contracts import StageRef
    from flows.stages.outputs import REFINED
    from tasks.frames import screw_axis, screw_axis_as
    from tasks.graph import setup_turn

    run = Path(run)
    refines = [e for e in read_trail(run) if e.get("kind") == "stage" and e.get("stage") == "refine"]
    if not refines:
        raise ValueError(f"{run}: no finished stage refine in its audit trail (reconstruct it, --stop-after refine "
                         "will do)")
    sample = _sample_dir(run)
    manifest = load_manifest(sample)
    setups = [s for s, _ in manifest.passes()]
    names = list(dict.fromkeys(setups))
    if len(names) < 2:
        raise ValueError(f"{run}: its sample {sample} has one setup ({names[0]!r}); a turn needs two or more")

    store, key = StageStore(run, shared=False), refines[-1]["cache_key"]
    record = store.lookup("refine", key)
    if record is None:
        raise ValueError(f"{run}: stage refine {key} is named by the audit trail but its folder holds no record")
    refine = StageRef(stage="refine", item=None, key=key, path=str(store.path("refine", key)),
                      outputs=dict(record.outputs), cached=True)
    T_common_pass = np.asarray(REFINED.read(refine).T_common_pass, float)
    out = []
    by_name = {s.name: s for s in manifest.setups}
    for name in names[1:]:
        T = setup_turn(setups, T_common_pass, names[0], name)
        turn = by_name[name].positioner
        point, direction, angle, _ = screw_axis(T) if turn is None else \
            screw_axis_as(T, turn.axis_direction, turn.angle_deg, turn.axis_point_mm)
        out.append(MeasuredAxis(str(run), name, names[0], point, direction, float(angle)))
    return out


def mean_axis(turns: list[MeasuredAxis]) -> tuple[np.ndarray, np.ndarray, float, dict]:
    """(point, direction, angle) averaged over ``turns`` (directions aligned with the first's;
    the point: nearest every line, least squares, then moved along the mean direction to the
    plane through the origin across it), and the spread: each turn's tilt (deg) and distance at
    that point (mm) from the mean axis."""
    if not turns:
        raise ValueError("no turns to calibrate from")
    ref = turns[0].direction
    dirs = np.array([t.direction if t.direction @ ref >= 0 else -t.direction for t in turns])
    angles = np.array([t.angle_deg if t.direction @ ref >= 0 else -t.angle_deg for t in turns])
    d = dirs.mean(axis=0)
    d /= np.linalg.norm(d)
    A, b = np.zeros((3, 3)), np.zeros(3)
    for t, u in zip(turns, dirs):
        P = np.eye(3) - np.outer(u, u)
        A += P
        b += P @ t.point_mm
    A += 1e-9 * np.outer(d, d)  # the lines are nearly parallel: fix the point along them
    point = np.linalg.solve(A, b)
    point -= (point @ d) * d
    spread = {}
    for t, u in zip(turns, dirs):
        off = (t.point_mm - point) - ((t.point_mm - point) @ d) * d
        spread[f"{t.run} {t.setup}"] = (float(np.degrees(np.arccos(np.clip(u @ d, -1, 1)))), float(np.linalg.norm(off)))
    return point, d, float(angles.mean()), spread


def calibration_yaml(point: np.ndarray, direction: np.ndarray, angle: float, runs: list[str]) -> str:
    import yaml

    doc = {"positioner": {"axis_point_mm": [round(float(v), 4) for v in point],
                          "axis_direction": [round(float(v), 8) for v in direction],
                          "angle_deg": round(float(angle), 5)}}
    header = "# the positioner's axis from the registered stickers of: " + json.dumps(runs) + "\n"
    return header + yaml.safe_dump(doc, sort_keys=False)
