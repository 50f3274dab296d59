"""Our stages against their peers, side by side on the same data in one process.

    .venv/bin/python bench/bench_peers.py SAMPLE_DIR RUN_DIR [--passes N] [--normals-k K]

RUN_DIR is a finished reconstruction of SAMPLE_DIR (its stage store gives the registered poses).
On the first N passes (default 2; for the ``paper`` preset a 12.9 M-point length pass and a 3.3 M
width pass... whatever the manifest's first N are):

- denoise: our window kNN outlier removal (``tasks.denoise``, the stage's kernel) against Open3D's
  ``remove_statistical_outlier`` (k-d tree), same k and alpha; the outlier recall of each against
  the simulator's labels (share of the true outliers removed) and the share of good points removed;
- normals: our grid-window normals (``tasks.normals``) against Open3D's ``estimate_normals`` with
  a k-d tree of k neighbours (default: the points our window holds), on the same kept points; the
  median angle between the two;
- merge: the per-block cell sums and their combination (``tasks.merge``, the stage's code path,
  in memory here) against Open3D's ``voxel_down_sample``, same cell, on the registered points of
  those passes.

Meshing against MeshLab's Poisson on the uniform cloud needs two reconstructions (``bench/README.md``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _timed(fn):
    t = time.perf_counter()
    value = fn()
    return time.perf_counter() - t, value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--normals-k", type=int)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import open3d as o3d

    from bench.accuracy import emit, latest_stage
    from data_catalog.manifests import load_manifest
    from data_catalog.stages import load_arrays
    from data_catalog.truth import TRUTH_DIR, read_truth_pass
    from flows.reconstruct import load_config
    from flows.stages.passes import load_pass_points
    from schemas.truth import PointLabel
    from tasks.denoise import remove_statistical_outliers
    from tasks.merge import CellSums, cell_sums, combine_cell_sums
    from tasks.normals import grid_normals, normal_window

    settings = args.run / "results" / "config.json"  # published with the results they made
    config = load_config(settings) if settings.is_file() else load_config(None)
    manifest = load_manifest(args.sample)
    dc = config.denoise
    T_all = load_arrays(latest_stage(args.run, "refine") / "refined.zarr", "T_common_pass")["T_common_pass"]
    rows: dict[str, dict] = {"denoise": {"ours_s": 0.0, "peer_s": 0.0, "points": 0, "ours_removed_outliers": 0,
                                         "peer_removed_outliers": 0, "outliers": 0, "ours_removed_good": 0,
                                         "peer_removed_good": 0, "good": 0},
                             "normals": {"ours_s": 0.0, "peer_s": 0.0, "points": 0, "angles": []},
                             "merge": {"ours_s": 0.0, "peer_s": 0.0, "points": 0}}
    registered, registered_normals = [], []
    for k, (_, entry) in enumerate(manifest.passes()[:args.passes]):
        _, T, grid = load_pass_points(args.sample, manifest, entry)
        valid = np.isfinite(grid).all(axis=-1)
        label = read_truth_pass(args.sample / TRUTH_DIR / "passes" / f"{entry.pass_id}.zarr").label
        outlier, good = (label == PointLabel.OUTLIER) & valid, (label == PointLabel.VALID) & valid
        flat = grid[valid]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat))
        t_ours, ours = _timed(lambda: remove_statistical_outliers(grid, k=dc.k, alpha=dc.alpha,
                                                                  window_rows=dc.window_rows,
                                                                  window_cols=dc.window_cols,
                                                                  pitch_mm=manifest.grid_pitch_mm(entry)))
        t_peer, (_, kept_index) = _timed(lambda: cloud.remove_statistical_outlier(nb_neighbors=dc.k,
                                                                                  std_ratio=dc.alpha))
        peer_keep = np.zeros(len(flat), bool)
        peer_keep[np.asarray(kept_index, dtype=np.int64)] = True
        r = rows["denoise"]
        r["ours_s"] += t_ours
        r["peer_s"] += t_peer
        r["points"] += len(flat)
        r["outliers"] += int(outlier.sum())
        r["good"] += int(good.sum())
        r["ours_removed_outliers"] += int((outlier & ~ours.keep).sum())
        r["peer_removed_outliers"] += int((~peer_keep & outlier[valid]).sum())
        r["ours_removed_good"] += int((good & ~ours.keep).sum())
        r["peer_removed_good"] += int((~peer_keep & good[valid]).sum())

        kept = np.where(ours.keep[..., None], grid, np.nan)
        nr, nc = normal_window(dc.normal_window_mm, manifest.grid_pitch_mm(entry))
        k_normals = args.normals_k or (2 * nr + 1) * (2 * nc + 1)
        t_ours, normals = _timed(lambda: grid_normals(kept, T[:, :3, 3], window_rows=nr, window_cols=nc,
                                                      min_points=dc.normal_min_points, reference_mm=T[0, :3, 3]))
        points = kept[ours.keep]
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        t_peer, _ = _timed(lambda: pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k_normals)))
        theirs = np.asarray(pc.normals)
        mine = normals[ours.keep]
        cos = np.abs(np.einsum("ij,ij->i", mine, theirs))
        r = rows["normals"]
        r["ours_s"] += t_ours
        r["peer_s"] += t_peer
        r["points"] += len(points)
        r["k"] = k_normals
        r["window"] = [2 * nr + 1, 2 * nc + 1]
        r["angles"].append(np.degrees(np.arccos(np.clip(cos, 0, 1)))[::10])
        R, t = T_all[k][:3, :3], T_all[k][:3, 3]
        registered.append(points @ R.T + t)
        registered_normals.append(mine @ R.T)
        del grid, kept, cloud, pc, theirs, normals

    points = np.concatenate(registered)
    normals = np.concatenate(registered_normals)
    del registered, registered_normals
    cell = config.merge.cell_mm
    block = 1 << 20

    def ours_merge():
        parts = [cell_sums(points[a:a + block], normals[a:a + block], cell_mm=cell) for a in range(0, len(points), block)]
        joined = CellSums(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                            ("keys", "counts", "point_sums", "normal_sums")))
        return combine_cell_sums(joined, cell_mm=cell)

    t_ours, merged = _timed(ours_merge)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.normals = o3d.utility.Vector3dVector(normals)
    t_peer, down = _timed(lambda: pc.voxel_down_sample(cell))
    rows["merge"].update(ours_s=t_ours, peer_s=t_peer, points=len(points), cells_ours=merged.n_points,
                         cells_peer=len(down.points))

    d, n = rows["denoise"], rows["normals"]
    angles = np.concatenate(n.pop("angles"))
    n["median_angle_between_deg"] = round(float(np.median(angles)), 3)
    n["p95_angle_between_deg"] = round(float(np.quantile(angles, 0.95)), 3)
    d["ours_outlier_recall"] = round(d["ours_removed_outliers"] / max(d["outliers"], 1), 4)
    d["peer_outlier_recall"] = round(d["peer_removed_outliers"] / max(d["outliers"], 1), 4)
    d["ours_good_removed"] = round(d["ours_removed_good"] / max(d["good"], 1), 5)
    d["peer_good_removed"] = round(d["peer_removed_good"] / max(d["good"], 1), 5)
    for r in rows.values():
        r["peer_over_ours"] = round(r["peer_s"] / r["ours_s"], 2)
        r["ours_s"], r["peer_s"] = round(r["ours_s"], 2), round(r["peer_s"], 2)
    result = {"sample": str(args.sample), "passes": [e.pass_id for _, e in manifest.passes()[:args.passes]],
              **rows}
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
