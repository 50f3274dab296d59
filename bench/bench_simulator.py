"""Benchmark of the simulated cell: points per second and peak memory for the ``demo`` preset and
for one full-resolution ``paper`` pass, each in a fresh process; and, in the same run, the ratio
of our sensor model's time to the bare Open3D ray casting of the same laser rays (the peer: what
the simulation costs beyond casting one ray per point).

    .venv/bin/python bench/bench_simulator.py [--skip-paper]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _one_paper_pass():
    from simulator.presets import preset_config

    cfg = preset_config("paper")
    plan = cfg.plan.model_copy(update={"setups": ["top"], "vertical_offsets_mm": [0.0], "side_rolls_deg": [],
                                       "width_passes": []})
    return cfg.model_copy(update={"plan": plan, "preset": "paper-one-pass"})


def _child(case: str, out: str) -> None:
    """Run one case in this process and print its figures as JSON."""
    import numpy as np
    import open3d as o3d

    from simulator.presets import preset_config
    from simulator.run import simulate

    cfg = preset_config("demo") if case == "demo" else _one_paper_pass()
    t0 = time.perf_counter()
    summary = simulate(cfg, Path(out) / "sample", previews=False)
    total = time.perf_counter() - t0
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    # Peer: Open3D casting the same number of laser rays, once each, at the same scene and poses.
    from data_catalog.truth import read_truth_pass
    from simulator.scanner import fan_directions
    from tasks.frames import apply

    sample = Path(out) / "sample"
    mesh = o3d.io.read_triangle_mesh(str(sample / "truth" / "specimen.ply"))
    truth = json.loads((sample / "truth" / "truth.json").read_text())
    scene = o3d.t.geometry.RaycastingScene()
    T = np.array(truth["T_world_specimen"]["top"])
    scene.add_triangles(o3d.core.Tensor(apply(T, np.asarray(mesh.vertices)).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.triangles).astype(np.uint32)))
    fan = fan_directions(cfg.scanner.points_per_profile, cfg.scanner.x_spacing_mm, cfg.scanner.reference_distance_mm)
    pass_id = truth["passes"][0]["pass_id"]
    poses = read_truth_pass(sample / "truth" / "passes" / f"{pass_id}.zarr").T_world_sensor
    n_points_pass = len(poses) * len(fan)
    scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 500, 0, 0, -1]], np.float32)))  # builds the BVH
    cast_s = 0.0
    for start in range(0, len(poses), cfg.chunk_profiles):
        block = poses[start:start + cfg.chunk_profiles]
        d = np.einsum("mij,nj->mni", block[:, :3, :3], fan).reshape(-1, 3)
        o = np.repeat(block[:, :3, 3], len(fan), axis=0)
        rays = o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32))
        t = time.perf_counter()
        scene.cast_rays(rays)
        cast_s += time.perf_counter() - t
    print(json.dumps({
        "case": case, "points": summary.n_points, "passes": summary.n_passes, "seconds": round(total, 2),
        "points_per_s": round(summary.n_points / total), "peak_rss_mib": round(peak_mib),
        "peer_cast_points_per_s": round(n_points_pass / cast_s),
        "ratio_ours_vs_peer_time_per_point": round((total / summary.n_points) / (cast_s / n_points_pass), 1),
    }))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--skip-paper", action="store_true")
    parser.add_argument("--child", nargs=2, metavar=("CASE", "DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(*args.child)
        return 0
    cases = ["demo"] if args.skip_paper else ["demo", "paper-pass"]
    rows = []
    for case in cases:
        with tempfile.TemporaryDirectory() as tmp:
            out = subprocess.run([sys.executable, __file__, "--child", case, tmp], check=True, capture_output=True,
                                 text=True, cwd=ROOT)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{'case':<12}{'passes':>7}{'points':>14}{'seconds':>9}{'points/s':>13}{'peak MiB':>10}"
          f"{'o3d cast/s':>13}{'ours/peer':>10}")
    for r in rows:
        print(f"{r['case']:<12}{r['passes']:>7}{r['points']:>14,}{r['seconds']:>9}{r['points_per_s']:>13,}"
              f"{r['peak_rss_mib']:>10,}{r['peer_cast_points_per_s']:>13,}{r['ratio_ours_vs_peer_time_per_point']:>10}")
    results = ROOT / "bench" / "results"
    results.mkdir(exist_ok=True)
    (results / "simulator.json").write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
