"""The Stanford bunny through the real pipeline: ``weldrecon import-scans`` + ``weldrecon reconstruct``.

    .venv/bin/python bench/bench_bunny_pipeline.py [--data DIR] [--seed N] [--work DIR] [--json OUT.json]

DIR (default ``../shared/data/stanford-bunny`` beside the repository) holds the ten range scans
(ASCII PLY, metres), ``bun.conf`` (the lab's alignment) and ``bun_zipper.ply`` (the lab's mesh).
Two cases, each a new sample imported with ``--units m`` (the pipeline works in mm) and
reconstructed with ``deploy/configs/bunny.yaml``, one process per command as a user runs them:

(a) rough poses: ``bun.conf``'s poses, each turned 5 degrees about a random axis through its
    scan's centroid and shifted 5 mm in a random direction (numpy generator ``--seed``, as
    ``bench/bench_bunny.py``), written to a .conf and imported with ``--poses``: the flow
    registers them "surfaces from given poses";
(b) no poses: imported without ``--poses``: "surfaces, global".

Per scan: rotation (deg) and translation (mm, at the scan's centroid) between the pipeline's pose
(``T_common_pass`` of stage refine after the scan's imported pose) and the lab's, both relative to
bun000 (the common gauge removed). The published mesh is put into the lab's frame by the one
rigid transform that takes bun000's pose to the lab's, and compared with ``bun_zipper.ply``: the
lab's vertices to our mesh (median / RMS / 95 %), and ours (the part within 1 mm of a merged
point: Poisson also closes the unscanned bottom) to the lab's mesh.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

SCANS = ("bun000", "bun045", "bun090", "bun180", "bun270", "top2", "top3", "bun315", "chin", "ear_back")
CONFIG = ROOT / "deploy" / "configs" / "bunny.yaml"


def write_conf(path: Path, names: list[str], T: np.ndarray) -> None:
    """A scanalyze .conf of poses ``T`` (mm) in metres: ``p_world = R(q)^T p + t`` (see
    ``data_catalog.pointclouds.read_conf_poses``), so the quaternion written is R^T's."""
    from scipy.spatial.transform import Rotation

    lines = ["camera 0 0 0 0 0 0 1"]
    for name, pose in zip(names, T):
        q = Rotation.from_matrix(pose[:3, :3].T).as_quat()  # x, y, z, w
        values = list(pose[:3, 3] / 1000.0) + list(q)
        lines.append(f"bmesh {name} " + " ".join(f"{v:.17g}" for v in values))
    path.write_text("\n".join(lines) + "\n")


def weldrecon(*args: str) -> float:
    """Run one weldrecon command in its own process; its wall time (s). Fails loudly."""
    start = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"weldrecon {' '.join(args)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return time.perf_counter() - start


def run_case(label: str, work: Path, files: list[Path], extra: list[str], reuse: bool = False) -> dict:
    sample, run = work / f"sample-{label}", work / f"run-{label}"
    if reuse and (run / "results" / "report.json").is_file():  # evaluate an earlier run again (no times)
        return dict(sample=sample, run=run, import_s=float("nan"), reconstruct_s=float("nan"))
    t_import = weldrecon("import-scans", str(sample), *map(str, files), "--units", "m", *extra)
    t_flow = weldrecon("reconstruct", str(sample), "--config", str(CONFIG), "--out", str(run))
    return dict(sample=sample, run=run, import_s=t_import, reconstruct_s=t_flow)


def final_poses(case: dict) -> tuple[np.ndarray, dict, list[np.ndarray]]:
    """T_common_scan (n, 4, 4): refine's T_common_pass after each scan's imported pose; the
    report; each scan's points (scan frame, mm)."""
    from data_catalog.manifests import load_manifest
    from data_catalog.scans import read_scan
    from data_catalog.stages import load_arrays

    from flows.stages.outputs import REPORT

    report = REPORT.read_path(case["run"] / "results" / "report.json")
    refined = load_arrays(case["run"] / "stages" / "refine" / report.stage_keys["refine"] / "refined.zarr",
                          "T_common_pass")["T_common_pass"]
    manifest = load_manifest(case["sample"])
    T, points = [], []
    for k, (_, entry) in enumerate(manifest.passes()):
        scan = read_scan(case["sample"] / entry.file, pass_id=entry.pass_id)
        T.append(refined[k] @ (scan.T_world_pass if scan.T_world_pass is not None else np.eye(4)))
        points.append(scan.points_mm)
    return np.array(T), report, points


def mesh_figures(case: dict, report, G: np.ndarray, zipper) -> dict:
    import open3d as o3d
    from scipy.spatial import cKDTree

    from data_catalog.stages import load_arrays

    mesh = o3d.io.read_triangle_mesh(str(case["run"] / "results" / f"{report.sample_id}.ply"))
    v = np.asarray(mesh.vertices) @ G[:3, :3].T + G[:3, 3]
    t = np.asarray(mesh.triangles)
    merged = load_arrays(case["run"] / "stages" / "merge" / report.stage_keys["merge"] / "merged.zarr",
                         "points")["points"] @ G[:3, :3].T + G[:3, 3]

    def distances(vertices, triangles, query):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
        return scene.compute_distance(o3d.core.Tensor(query.astype(np.float32))).numpy().astype(np.float64)

    def figures(d):
        return dict(median=float(np.median(d)), rms=float(np.sqrt(np.mean(d ** 2))), p95=float(np.percentile(d, 95)))

    zv, zt = zipper
    measured = cKDTree(merged).query(v, distance_upper_bound=1.0, workers=1)[0] < np.inf
    return dict(vertices=int(len(v)), watertight=bool(report.mesh["watertight"]),
                lab_to_ours=figures(distances(v, t, zv)), ours_to_lab=figures(distances(zv, zt, v[measured])))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "stanford-bunny")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work", type=Path, help="keep the samples and runs here (default: a temporary folder)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--reuse", action="store_true", help="with --work: evaluate the runs already there")
    args = parser.parse_args()

    import open3d as o3d

    from bench_bunny import perturb, pose_errors
    from data_catalog.pointclouds import read_conf_poses, read_point_cloud

    work = args.work or Path(tempfile.mkdtemp(prefix="bunny-pipeline-"))
    work.mkdir(parents=True, exist_ok=True)
    lab = read_conf_poses(args.data / "bun.conf", units="m")
    names = [f"{s}.ply" for s in SCANS]
    T_lab = np.array([lab[n] for n in names])
    files = [args.data / n for n in names]
    points = [read_point_cloud(f, units="m").points_mm for f in files]
    T_start = perturb(T_lab, points, seed=args.seed, degrees=5.0, mm=5.0)
    if not (args.reuse and (work / "perturbed.conf").is_file()):
        write_conf(work / "perturbed.conf", names, T_start)
    back = read_conf_poses(work / "perturbed.conf", units="m")
    assert max(np.abs(back[n] - T_start[k]).max() for k, n in enumerate(names)) < 1e-9, "the .conf does not round-trip"
    zipper_mesh = o3d.io.read_triangle_mesh(str(args.data / "bun_zipper.ply"))
    zipper = (np.asarray(zipper_mesh.vertices) * 1000.0, np.asarray(zipper_mesh.triangles))

    cases = {"a": run_case("a", work, files, ["--poses", str(work / "perturbed.conf")], args.reuse),
             "b": run_case("b", work, files, [], args.reuse)}
    rows, meshes, methods = {}, {}, {}
    err_start = pose_errors(T_start, T_lab, points)
    for label, case in cases.items():
        T, report, scan_points = final_poses(case)
        assert all(np.abs(p - q).max() < 1e-4 for p, q in zip(scan_points, points)), \
            "the imported points differ from the files' (beyond float32 at 0.1 m)"
        rows[label] = pose_errors(T, T_lab, points)
        G = T_lab[0] @ np.linalg.inv(T[0])  # the common frame into the lab's: bun000 where the lab put it
        meshes[label] = mesh_figures(case, report, G, zipper)
        methods[label] = sorted(set(report.registration_method.values()))
    print("| scan | (a) start deg / mm | (a) given poses, refined: deg / mm | (b) no poses: deg / mm |")
    print("|---|---|---|---|")
    for k, s in enumerate(SCANS):
        print(f"| {s} | {err_start[k, 0]:.2f} / {err_start[k, 1]:.2f} | {rows['a'][k, 0]:.3f} / {rows['a'][k, 1]:.3f} "
              f"| {rows['b'][k, 0]:.3f} / {rows['b'][k, 1]:.3f} |")
    print("\n| case | registration_method | import s | reconstruct s | mesh vertices | watertight "
          "| lab mesh -> ours: median / RMS / 95 % (mm) | ours (measured part) -> lab mesh (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, case in cases.items():
        m = meshes[label]
        a, b = m["lab_to_ours"], m["ours_to_lab"]
        print(f"| ({label}) | {', '.join(methods[label])} | {case['import_s']:.1f} | {case['reconstruct_s']:.1f} | "
              f"{m['vertices']:,} | {'yes' if m['watertight'] else 'no'} | {a['median']:.3f} / {a['rms']:.3f} / "
              f"{a['p95']:.3f} | {b['median']:.3f} / {b['rms']:.3f} / {b['p95']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps(dict(
            scans=list(SCANS), start=err_start.tolist(), a=rows["a"].tolist(), b=rows["b"].tolist(), meshes=meshes,
            methods=methods, seconds={k: dict(import_s=c["import_s"], reconstruct_s=c["reconstruct_s"])
                                      for k, c in cases.items()}), indent=1))
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
