"""A planned scan against the preset's hand-made plan, side by side, on the same part and scanner.

    .venv/bin/python bench/bench_plan.py PRESET WORK_DIR [--seed N] [--json OUT.json] [--config RECON.yaml]

For PRESET (demo, ci, paper, tjoint, cruciform): ``weldrecon plan PRESET``; the preset's own sample
and the plan's scan (``weldrecon simulate --plan``) simulated with the same seed (the preset's, or
``--seed``: the same specimen and weld) and reconstructed with the same settings; then, for each:

- the scan time, passes and stickers; the predicted coverage (``simulator.planner.evaluate_passes``
  on both plans, the same requirements);
- the worst pass misalignment against the truth (``bench/accuracy.py``), targets alone and refined;
- the weld-toe coverage of the reconstruction: every 1 mm along each drawn toe
  (``truth/weld_sections.json``: centre +- width / 2, top and bottom), in the specimen frame (the
  registered stickers fitted to the true ones), the share of stations with a measured point
  (segment stage, ``measured``) within 0.2 mm across the face, and the median number of points
  within 0.5 mm;
- the weld measurement: sections measured of those tried, toe radius and flank angle against the
  truth (``bench/bench_weld_geometry.py``'s comparison, when it applies).

A T-joint or a cruciform (``truth/toes.json``): the toe coverage every 1 mm along each true toe
line (a measured point within 0.2 mm, in 3-D); the fillets' figures against the drawn ones
(``simulator.evaluate.fillet_errors``: median and 90th percentile of |error|); the stress at the
toes against the same sections of the true surface (``bench/stress_truth.py``). Reconstruct these
with ``--config tests/data/fillet.yaml`` (the ci settings, the weld every 2 mm: the tests' own).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.accuracy import emit, evaluate, latest_stage  # noqa: E402

WELDRECON = str(ROOT / ".venv" / "bin" / "weldrecon")


def run(cmd: list[str], log: Path) -> float:
    started = time.perf_counter()
    with open(log, "w") as out:
        subprocess.run(cmd, check=True, stdout=out, stderr=subprocess.STDOUT)
    return time.perf_counter() - started


def measured_points(sample: Path, run_dir: Path) -> np.ndarray:
    """The run's measured specimen points (segment stage) in the true specimen frame, placed by
    the registered stickers fitted to the true ones."""
    from data_catalog.stages import load_arrays
    from simulator.evaluate import fit_gauge

    refined = load_arrays(latest_stage(run_dir, "refine") / "refined.zarr", "track_positions_mm", "specimen_track")
    positions = refined["track_positions_mm"]
    on_specimen = refined["specimen_track"].astype(bool)
    gauge = fit_gauge(sample, positions[on_specimen] if on_specimen.any() else positions, positions)
    G_inv = np.linalg.inv(gauge.T_recon_specimen)
    cloud = load_arrays(latest_stage(run_dir, "segment") / "specimen.zarr", "points", "measured")
    return np.asarray(cloud["points"][cloud["measured"].astype(bool)], np.float64) @ G_inv[:3, :3].T + G_inv[:3, 3]


def toe_coverage(sample: Path, run_dir: Path) -> dict:
    from scipy.spatial import cKDTree

    from data_catalog.truth import TRUTH_DIR

    pts = measured_points(sample, run_dir)
    sections = json.loads((sample / TRUTH_DIR / "weld_sections.json").read_text())["sections"]
    half_w = json.loads((sample / TRUTH_DIR / "simulation.json").read_text())["specimen"]["gauge_width_mm"] / 2
    out = {}
    for side, sign in (("top", 1.0), ("bottom", -1.0)):
        face = pts[np.sign(pts[:, 2]) == sign]
        tree = cKDTree(face[:, :2])
        for toe, k in (("neg", -1.0), ("pos", 1.0)):
            st = np.array([(s["centre_x_mm"] + k * s["width_mm"] / 2, s["y_mm"]) for s in sections
                           if s["side"] == side and abs(s["y_mm"]) <= half_w - 1.0])
            d, _ = tree.query(st, distance_upper_bound=0.2)
            counts = tree.query_ball_point(st, 0.5, return_length=True)
            out[f"{side}-{toe}"] = {"stations": int(len(st)), "covered": round(float(np.isfinite(d).mean()), 4),
                                    "points_within_0.5mm_median": float(np.median(counts))}
    out["all"] = {"covered": round(float(np.mean([v["covered"] for v in out.values()])), 4)}
    return out


def toe_coverage_fillets(sample: Path, run_dir: Path) -> dict:
    """Every 1 mm along each true toe line (``truth/toes.json``), 1 mm in from the ends: the share
    with a measured point within 0.2 mm, the median count within 0.5 mm."""
    from scipy.spatial import cKDTree

    from data_catalog.truth import TRUTH_DIR, read_true_toes

    tree = cKDTree(measured_points(sample, run_dir))
    out = {}
    for toe in read_true_toes(sample / TRUTH_DIR / "toes.json").toes:
        line = np.asarray(toe.points_mm, float)
        y = np.arange(line[0, 1] + 1.0, line[-1, 1] - 1.0 + 1e-9, 1.0)
        st = np.stack([np.interp(y, line[:, 1], line[:, 0]), y, np.interp(y, line[:, 1], line[:, 2])], axis=1)
        d, _ = tree.query(st, distance_upper_bound=0.2)
        counts = tree.query_ball_point(st, 0.5, return_length=True)
        out[toe.name] = {"stations": int(len(st)), "covered": round(float(np.isfinite(d).mean()), 4),
                         "points_within_0.5mm_median": float(np.median(counts))}
    out["all"] = {"covered": round(float(np.mean([v["covered"] for v in out.values()])), 4)}
    return out


def fillet_figures(sample: Path, run_dir: Path, config: str) -> dict:
    """The fillets' figures against the drawn ones (median and p90 of |error|), and the stress at
    the toes against the true surface's."""
    from data_catalog.manifests import load_manifest
    from flows.preflight import load_config
    from flows.stages.outputs import REFINED, WELD_GEOMETRY
    from simulator.evaluate import T_true_specimen_nominal, fillet_errors
    from stress_truth import compare

    from bench.accuracy import stage_folder

    geometry = WELD_GEOMETRY.read(stage_folder(run_dir, "weld"))
    T = T_true_specimen_nominal(sample, load_manifest(sample), REFINED.open(stage_folder(run_dir, "refine")))
    out = {}
    for name, pairs in fillet_errors(sample, geometry, T).items():
        e = np.abs([err for err, _ in pairs])
        out[name] = {"n": int(len(e)), "median": round(float(np.median(e)), 4), "p90": round(float(np.percentile(e, 90)), 4)}
    stress = compare(run_dir, sample, config=load_config(config))
    out["stress"] = {k: stress[k] for k in ("median_difference", "worst_difference", "toe_sections")}
    out["stress"]["hot_spots"] = {k: v["difference"] for k, v in stress["toes"].items()}
    return out


def weld_figures(run_dir: Path) -> dict:
    """The weld stage's count of sections, and its figures' spreads (``report.json``)."""
    weld = json.loads((run_dir / "results" / "report.json").read_text())["weld"]
    out = {k: weld[k] for k in ("sections", "sections_measured", "sections_uncertain", "verdict")}
    for name in ("toe_radius_mm", "flank_angle_deg", "groove_depth_mm", "groove_width_mm"):
        figure = weld["statistics"].get(name)
        if figure:
            out[name] = {k: figure[k] for k in ("n", "median", "p5", "p95")}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("preset")
    parser.add_argument("work", type=Path)
    parser.add_argument("--seed", type=int, help="simulate both with this seed instead of the preset's")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--config", default=str(ROOT / "deploy" / "configs" / "demo.yaml"))
    args = parser.parse_args()
    from simulator.plan_files import read_plan
    from simulator.planner import evaluate_passes, planned_passes
    from simulator.presets import preset_config
    from simulator.robot import plan_passes
    from simulator.tjoint import plan_tjoint_passes

    sys.path.insert(0, str(ROOT / "bench"))
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    result: dict = {"preset": args.preset, "seed": args.seed}
    plan_dir = work / "plan"
    if not plan_dir.exists():
        result["plan_s"] = round(run([WELDRECON, "plan", args.preset, "--out", str(plan_dir)], work / "plan.log"), 1)
    plan = read_plan(plan_dir)
    config = preset_config(args.preset)
    if config.tjoint is None:
        hand = plan_passes(config.plan, config.specimen, config.robot,
                           z_top_mm=config.fixture.block_size_mm[2] + config.specimen.thickness_mm,
                           standoff_mm=config.scanner.reference_distance_mm, setups=tuple(config.plan.setups))
    else:
        hand = plan_tjoint_passes(config, z_top_mm=config.fixture.block_size_mm[2] + config.tjoint.base_thickness_mm,
                                  setups=tuple(config.plan.setups))
    req = plan.requirements
    predicted_hand = evaluate_passes(config, req, hand, stickers=False)
    result["hand"] = {"passes": len(hand), "scan_time_s": round(predicted_hand.scan_time_s, 1),
                      "predicted_faces": {f.face: f.seen for f in predicted_hand.faces},
                      "predicted_toes_both_sides": {t.toe: t.both_sides for t in predicted_hand.toes}}
    planned = planned_passes(plan)
    result["plan"] = {"passes": len(planned), "scan_time_s": round(plan.scan_time_s, 1), "stickers": len(plan.stickers),
                      "predicted_faces": {f.face: f.seen for f in plan.faces},
                      "predicted_toes_both_sides": {t.toe: t.both_sides for t in plan.toes}}
    result["scan_time_ratio"] = round(plan.scan_time_s / predicted_hand.scan_time_s, 3)
    for name, extra in (("hand", ["--preset", args.preset]), ("plan", ["--plan", str(plan_dir)])):
        sample = work / f"{name}-sample"
        if not sample.exists():
            seed = [] if args.seed is None else ["--seed", str(args.seed)]
            run([WELDRECON, "simulate", str(sample), *extra, *seed, "--no-preview"], work / f"{name}-simulate.log")
        rec = work / f"{name}-run"
        truth = json.loads((sample / "truth" / "truth.json").read_text())
        result[name]["stickers"] = sum(1 for s in truth["stickers"] if s["on"] == "specimen")
        if not (rec / "results" / "report.json").exists():
            log = work / f"{name}-reconstruct.log"
            try:
                result[name]["reconstruct_s"] = round(run([WELDRECON, "reconstruct", str(sample), "--out", str(rec),
                                                           "--config", args.config], log), 1)
            except subprocess.CalledProcessError:  # a plan whose scan does not reconstruct: say why, go on
                errors = [line for line in log.read_text().splitlines() if line.startswith("weldrecon reconstruct:")]
                result[name]["failed"] = errors[-1] if errors else f"exit status != 0; see {log}"
                continue
        result[name]["accuracy"] = evaluate(sample, rec)
        fillets = config.tjoint is not None
        result[name]["toe_coverage"] = (toe_coverage_fillets if fillets else toe_coverage)(sample, rec)
        result[name]["weld"] = weld_figures(rec)
        if fillets:
            result[name]["fillets"] = fillet_figures(sample, rec, args.config)
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
