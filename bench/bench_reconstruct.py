"""Benchmark of the reconstruction on the ``demo`` sample.

Part 1: every stage of the registry (flows.stages.STAGES) in a fresh process (earlier stages come from the stage store), its wall
time and peak RSS. Part 2: on the same data, in one process, our denoise, merge and meshing
against Open3D's ``remove_statistical_outlier``, ``voxel_down_sample`` and
``create_from_point_cloud_poisson`` (same neighbours / cell / depth), as time ratios.

    .venv/bin/python bench/bench_reconstruct.py [SAMPLE_DIR]   (default: out/demo/sample)
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CONFIG = ROOT / "deploy" / "configs" / "demo.yaml"

from flows.stages import STAGE_NAMES  # noqa: E402 - after the path is set


def _stage_child(sample: str, out: str, upto: str) -> None:
    from data_catalog.manifests import load_manifest
    from data_catalog.stages import StageStore
    from flows.reconstruct import load_config
    from flows.stages import run_in_process

    t0 = time.perf_counter()
    refs = run_in_process(store=StageStore(Path(out)), sample_dir=Path(sample), manifest=load_manifest(Path(sample)),
                          config=load_config(CONFIG), upto=upto)
    ref = refs[upto]
    seconds = sum(r.metrics["seconds"] for r in ref) if isinstance(ref, list) else ref.metrics["seconds"]
    print(json.dumps({"stage": upto, "seconds": round(seconds, 2), "wall_s": round(time.perf_counter() - t0, 2),
                      "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}))


def _refs(sample: Path, out: Path) -> dict:
    """The finished stages' refs (all cached by the children: looked up, not recomputed)."""
    from data_catalog.manifests import load_manifest
    from data_catalog.stages import StageStore
    from flows.reconstruct import load_config
    from flows.stages import run_in_process

    return run_in_process(store=StageStore(out), sample_dir=sample, manifest=load_manifest(sample),
                          config=load_config(CONFIG))


def _peers(sample: Path, refs: dict) -> list[dict]:
    import numpy as np
    import open3d as o3d

    from data_catalog.manifests import load_manifest
    from flows.reconstruct import load_config
    from flows.stages.outputs import CLOUD, REGISTRATION, SPECIMEN
    from flows.stages.passes import load_pass_points
    from tasks.denoise import remove_statistical_outliers
    from tasks.merge import merge_box_grid
    from tasks.mesh import screened_poisson

    cfg = load_config(CONFIG)
    m = load_manifest(sample)
    rows = []

    def timed(fn):
        t = time.perf_counter()
        fn()
        return time.perf_counter() - t

    # denoise: every pass, same k and alpha
    ours = peer = 0.0
    n_points = 0
    dc = cfg.denoise
    for _, e in m.passes():
        grid = load_pass_points(sample, m, e)[2]
        flat = grid.reshape(-1, 3)
        flat = flat[np.isfinite(flat).all(1)]
        n_points += len(flat)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat))
        ours += timed(lambda: remove_statistical_outliers(grid, k=dc.k, alpha=dc.alpha, window_rows=dc.window_rows,
                                                          window_cols=dc.window_cols,
                                                          pitch_mm=m.grid_pitch_mm(e)))
        peer += timed(lambda: cloud.remove_statistical_outlier(nb_neighbors=dc.k, std_ratio=dc.alpha))
    rows.append({"stage": "denoise", "points": n_points, "ours_s": ours, "peer": "o3d remove_statistical_outlier",
                 "peer_s": peer})
    # merge: the registered cloud of every pass
    T = REGISTRATION.open(refs["registration"]).T_common_pass
    pts = []
    for k, ref in enumerate(refs["denoise"]):
        g = CLOUD.open(ref).points.reshape(-1, 3).astype(np.float64)
        g = g[np.isfinite(g).all(1)]
        pts.append(g @ T[k][:3, :3].T + T[k][:3, 3])
    pts = np.concatenate(pts)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    rows.append({"stage": "merge", "points": len(pts),
                 "ours_s": timed(lambda: merge_box_grid(pts, cell_mm=cfg.merge.cell_mm)),
                 "peer": "o3d voxel_down_sample", "peer_s": timed(lambda: cloud.voxel_down_sample(cfg.merge.cell_mm))})
    # meshing: the specimen cloud, same normals (merged from the passes' grid normals), same depth
    spec = SPECIMEN.read(refs["segment"])
    normals = spec.normals.astype(np.float64)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(spec.points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    sc = cfg.mesh
    rows.append({"stage": "mesh (Poisson)", "points": len(spec.points),
                 "ours_s": timed(lambda: screened_poisson(spec.points, normals, depth=sc.poisson_depth,
                                                          samples_per_node=sc.samples_per_node,
                                                          point_weight=sc.point_weight, scale=sc.poisson_scale)),
                 "peer": "o3d create_from_point_cloud_poisson",
                 "peer_s": timed(lambda: o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                     pc, depth=sc.poisson_depth, scale=sc.poisson_scale))})
    for r in rows:
        r["ratio"] = r["ours_s"] / r["peer_s"]
    return rows


def _accuracy(sample: Path, refs: dict) -> list[dict]:
    """Pass misalignment against the simulator's truth: target registration alone (the paper's
    method) and after the joint refinement."""
    import numpy as np

    from flows.stages.outputs import REFINED, REGISTRATION
    from simulator.evaluate import pass_misalignment

    if not (sample / "truth" / "truth.json").is_file():
        return []
    rows = []
    for poses, stage, store in (("targets", "registration", REGISTRATION), ("refined", "refine", REFINED)):
        m = pass_misalignment(sample, store.open(refs[stage]).T_common_pass)
        rows.append({"poses": poses, "worst_um": round(1000 * float(m.max_mm.max())),
                     "median_um": round(1000 * float(np.median(m.median_mm)))})
    return rows


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _stage_child(*sys.argv[2:5])
        return 0
    sample = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "out" / "demo" / "sample"
    if not (sample / "manifest.json").is_file():
        print(f"{sample}: no sample there; run `make demo` first", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        stage_rows = []
        for stage in STAGE_NAMES:
            done = subprocess.run([sys.executable, __file__, "--child", str(sample), tmp, stage], check=True,
                                  capture_output=True, text=True, cwd=ROOT)
            stage_rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        refs = _refs(sample, Path(tmp))
        peer_rows = _peers(sample, refs)
        accuracy = _accuracy(sample, refs)
    print(f"{'stage':<13}{'seconds':>9}{'peak RSS MiB':>14}")
    for r in stage_rows:
        print(f"{r['stage']:<13}{r['seconds']:>9}{r['peak_rss_mib']:>14,}")
    print(f"\n{'stage':<16}{'points':>12}{'ours s':>9}{'peer s':>9}{'ours/peer':>10}  peer")
    for r in peer_rows:
        print(f"{r['stage']:<16}{r['points']:>12,}{r['ours_s']:>9.2f}{r['peer_s']:>9.2f}{r['ratio']:>10.2f}  {r['peer']}")
    if accuracy:
        print(f"\n{'poses':<10}{'worst um':>9}{'median of pass medians um':>27}")
        for r in accuracy:
            print(f"{r['poses']:<10}{r['worst_um']:>9}{r['median_um']:>27}")
    results = ROOT / "bench" / "results"
    results.mkdir(exist_ok=True)
    (results / "reconstruct.json").write_text(json.dumps({"stages": stage_rows, "peers": peer_rows,
                                                          "accuracy": accuracy}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
