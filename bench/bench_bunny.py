"""Registration without stickers on real laser-triangulation scans: the Stanford bunny.

    .venv/bin/python bench/bench_bunny.py [--data DIR] [--seed N] [--json OUT.json]

DIR (default ``../shared/data/stanford-bunny`` beside the repository) holds the ten range scans
(ASCII PLY, metres; read here into mm), ``bun.conf`` (the lab's alignment) and ``bun_zipper.ply``
(the lab's reconstruction). Cases (``tasks.surface_registration``):

(a) rough poses: the lab's poses, each turned 5 degrees about a random axis through its scan's
    centroid and shifted 5 mm in a random direction (numpy generator ``--seed``), then refined
    together on the surfaces (``refine_scan_poses``, gates 16 -> 1 mm), bun000 held fixed;
(b) no poses: every pair registered globally and verified (``register_pair``), poses chained
    along a spanning tree of the accepted pairs, then refined together (``register_scans``).

Per scan: rotation (deg) and translation (mm, at the scan's centroid) from the lab's alignment,
both expressed relative to bun000 (the common gauge removed); every pair's verdict against the
lab's relative pose. Then the registered scans are merged (bun000 where the lab put it) and
meshed (``tasks.mesh``: normals toward each scan's sensor, screened Poisson), and the mesh
compared with ``bun_zipper.ply``; the lab's own alignment goes through the same meshing as a
reference. The lab's mesh was made from the lab's alignment, so it favours it; the scan-to-scan
figure (how far each scan's points lie from the other scans' local planes) does not.
``bun.conf``'s convention (checked against the data: see ``data_catalog.pointclouds.read_conf_poses``):
``p_world = R(q)^T p_scan + t``, ``q = (qx, qy, qz, qw)`` as written. The scans are read by
``data_catalog.pointclouds.read_point_cloud`` (the organized range grids, metres to mm).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

VIEW = np.array([0.0, 0.0, 1.0])  # the Cyberware scans look along -z: the sensor is toward +z
FEATURES = dict(voxel_mm=3.0, sample_spacing_mm=2.0, neighbour_mm=2.0, max_plane_rms_mm=0.25, normal_neighbours=16)
POISSON = dict(depth=9, samples_per_node=3.0, point_weight=4.0, scale=1.3)


def pose_errors(T: np.ndarray, T_ref: np.ndarray, points: list[np.ndarray], base: int = 0) -> np.ndarray:
    """(n, 2): rotation (deg) and translation at each scan's centroid (mm) between ``T`` and
    ``T_ref`` after expressing both relative to scan ``base``. NaN for NaN poses."""
    from scipy.spatial.transform import Rotation

    out = np.full((len(T), 2), np.nan)
    A, B = np.linalg.inv(T[base]) @ T, np.linalg.inv(T_ref[base]) @ T_ref
    for k, p in enumerate(points):
        if np.isfinite(A[k]).all():
            c = p.mean(axis=0)
            out[k, 0] = np.degrees(Rotation.from_matrix(A[k, :3, :3].T @ B[k, :3, :3]).magnitude())
            out[k, 1] = np.linalg.norm(A[k, :3, :3] @ c + A[k, :3, 3] - B[k, :3, :3] @ c - B[k, :3, 3])
    return out


def perturb(T: np.ndarray, points: list[np.ndarray], *, seed: int, degrees: float, mm: float) -> np.ndarray:
    """Each pose turned ``degrees`` about a random axis through its scan's centroid (in the common
    frame), then shifted ``mm`` in a random direction."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = T.copy()
    for k, p in enumerate(points):
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
        c = T[k, :3, :3] @ p.mean(axis=0) + T[k, :3, 3]
        D = np.eye(4)
        D[:3, :3] = R
        D[:3, 3] = c - R @ c + mm * shift / np.linalg.norm(shift)
        out[k] = D @ T[k]
    return out


def scan_consistency(T: np.ndarray, points: list[np.ndarray]) -> np.ndarray:
    """How well the registered scans agree with each other, whatever the lab's mesh says: for
    each ordered pair of scans, every 4th point of one within 2 mm of 16 points of the other, the
    median distance to their plane (mm); pairs with fewer than 500 such points are left out."""
    from scipy.spatial import cKDTree

    world = [p @ T[k, :3, :3].T + T[k, :3, 3] for k, p in enumerate(points) if np.isfinite(T[k]).all()]
    trees = [cKDTree(w) for w in world]
    out = []
    for a, wa in enumerate(world):
        for b, tree in enumerate(trees):
            if a == b:
                continue
            dist, idx = tree.query(wa[::4], k=16, distance_upper_bound=2.0, workers=1)
            ok = np.isfinite(dist).all(axis=1)
            if ok.sum() < 500:
                continue
            near = world[b][idx[ok]]
            centre = near.mean(axis=1)
            spread = near - centre[:, None]
            normal = np.linalg.eigh(np.einsum("kni,knj->kij", spread, spread))[1][:, :, 0]
            out.append(np.median(np.abs(np.einsum("ij,ij->i", wa[::4][ok] - centre, normal))))
    return np.array(out)


def mesh_against(T: np.ndarray, points: list[np.ndarray], normals: list[np.ndarray], zipper) -> dict:
    """Merge the scans with finite poses, mesh them, compare with the lab's mesh (mm)."""
    import open3d as o3d

    from tasks.mesh import screened_poisson

    ok = [k for k in range(len(points)) if np.isfinite(T[k]).all()]
    merged = np.concatenate([points[k] @ T[k, :3, :3].T + T[k, :3, 3] for k in ok])
    merged_n = np.concatenate([normals[k] @ T[k, :3, :3].T for k in ok])
    start = time.perf_counter()
    surface = screened_poisson(merged, merged_n, **POISSON)
    seconds = time.perf_counter() - start

    def distances(vertices, triangles, query):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
        return scene.compute_distance(o3d.core.Tensor(query.astype(np.float32))).numpy().astype(np.float64)

    def figures(d):
        return dict(median=float(np.median(d)), rms=float(np.sqrt(np.mean(d ** 2))), p95=float(np.percentile(d, 95)))

    from scipy.spatial import cKDTree

    zv, zt = zipper
    # the lab's surface -> ours; ours -> the lab's where ours lies on measured surface (within
    # 1 mm of a scan point: Poisson also closes the unscanned bottom, which the lab's mesh leaves open)
    measured = cKDTree(merged).query(surface.vertices, distance_upper_bound=1.0, workers=1)[0] < np.inf
    return dict(scans=len(ok), points=len(merged), vertices=surface.report.n_vertices,
                watertight=surface.report.watertight, seconds=seconds,
                lab_to_ours=figures(distances(surface.vertices, surface.triangles, zv)),
                ours_to_lab=figures(distances(zv, zt, surface.vertices[measured])))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "stanford-bunny")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import pymeshlab  # noqa: F401  (first: beside Open3D it must load first)
    import open3d as o3d

    from data_catalog.pointclouds import read_conf_poses, read_point_cloud
    from tasks.mesh import estimate_normals
    from tasks.surface_registration import (PairOptions, RefineOptions, refine_scan_poses, register_scans,
                                            scan_features)

    times = {}
    start = time.perf_counter()
    lab = read_conf_poses(args.data / "bun.conf", units="m")
    names, T_lab = list(lab), np.array(list(lab.values()))
    points = [read_point_cloud(args.data / name, units="m").points_mm for name in names]
    zipper_mesh = o3d.io.read_triangle_mesh(str(args.data / "bun_zipper.ply"))
    zipper = (np.asarray(zipper_mesh.vertices) * 1000.0, np.asarray(zipper_mesh.triangles))
    normals = [estimate_normals(p, p + 1e4 * VIEW, k=16) for p in points]
    times["read, normals"] = time.perf_counter() - start

    start = time.perf_counter()
    scans = [scan_features(p, view_direction=VIEW, **FEATURES) for p in points]
    times["features"] = time.perf_counter() - start

    rough = RefineOptions(gates_mm=(16.0, 8.0, 4.0, 2.0, 1.0), neighbour_mm=2.0, max_plane_rms_mm=0.25,
                          surface_sigma_mm=0.15, tolerance_mm=0.01, min_normal_cos=0.8, normal_neighbours=16,
                          max_points_per_pair=2000, iterations_per_level=10)
    start = time.perf_counter()
    T_start = perturb(T_lab, points, seed=args.seed, degrees=5.0, mm=5.0)
    refined = refine_scan_poses([s.surface for s in scans], T_start, options=rough, fixed=0)
    times["(a) refine from rough poses"] = time.perf_counter() - start

    start = time.perf_counter()
    pair = PairOptions(ransac_inlier_mm=4.5, inlier_mm=1.0, max_rms_mm=0.4, distinct_mm=10.0)
    fine = dataclasses.replace(rough, gates_mm=(8.0, 4.0, 2.0, 1.0))
    glob = register_scans(scans, pair=pair, refine=fine, fixed=0)
    times["(b) global + refine"] = time.perf_counter() - start

    err_start = pose_errors(T_start, T_lab, points)
    err_a = pose_errors(refined.T_common_pass, T_lab, points)
    err_b = pose_errors(glob.T_world_scan, T_lab, points)
    parent = {int(c): int(p) for p, c in glob.tree}
    rows = []
    for k, name in enumerate(names):
        best = max((p for p in glob.pairs if p.accepted and k in (p.source, p.target)), key=lambda p: p.fitness,
                   default=None)
        rows.append(dict(scan=name[:-4], points=len(points[k]), start_deg=err_start[k, 0], start_mm=err_start[k, 1],
                         a_deg=err_a[k, 0], a_mm=err_a[k, 1], b_method=glob.method[k], b_deg=err_b[k, 0],
                         b_mm=err_b[k, 1], b_parent=names[parent[k]][:-4] if k in parent else "-",
                         b_accepted_pairs=sum(p.accepted and k in (p.source, p.target) for p in glob.pairs),
                         b_best_overlap=best.fitness if best else np.nan, reason=glob.reason[k]))

    # every pair's verdict against the lab's alignment (a pose within 2 deg / 2 mm of it is "right")
    pairs = []
    for p in glob.pairs:
        truth = np.linalg.inv(T_lab[p.target]) @ T_lab[p.source]
        e = pose_errors(np.stack([np.eye(4), p.T_target_source]), np.stack([np.eye(4), truth]),
                        [points[p.target], points[p.source]])[1]
        pairs.append(dict(source=names[p.source][:-4], target=names[p.target][:-4], accepted=p.accepted,
                          right=bool(e[0] < 2 and e[1] < 2), deg=e[0], mm=e[1], fitness=p.fitness, rms_mm=p.rms_mm,
                          runner_up_fitness=p.runner_up_fitness, reason=p.reason))

    meshes = {}
    for label, T in (("lab (bun.conf)", T_lab), ("(a) rough poses, refined", refined.T_common_pass),
                     ("(b) no poses", glob.T_world_scan)):
        start = time.perf_counter()
        # the gauge: bun000 where the lab put it (case (a) held it at its perturbed pose)
        T = T_lab[0] @ np.linalg.inv(T[0]) @ T
        meshes[label] = mesh_against(T, points, normals, zipper)
        consistency = scan_consistency(T, points)
        meshes[label]["scan_to_scan"] = dict(pairs=len(consistency), median=float(np.median(consistency)),
                                             max=float(consistency.max()))
        times[f"mesh {label}"] = time.perf_counter() - start

    print("| scan | points | (a) start deg / mm | (a) refined deg / mm | (b) method | (b) deg / mm | (b) chained from "
          "| (b) accepted pairs | (b) best overlap |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scan']} | {r['points']:,} | {r['start_deg']:.2f} / {r['start_mm']:.2f} | {r['a_deg']:.3f} / "
              f"{r['a_mm']:.3f} | {r['b_method']} | {r['b_deg']:.3f} / {r['b_mm']:.3f} | {r['b_parent']} | "
              f"{r['b_accepted_pairs']} | {r['b_best_overlap']:.2f} |")
    acc = [p for p in pairs if p["accepted"]]
    ref = [p for p in pairs if not p["accepted"]]
    print(f"\npairs: {len(pairs)}; accepted {len(acc)} (wrong: {sum(not p['right'] for p in acc)}, worst "
          f"{max(p['deg'] for p in acc):.2f} deg / {max(p['mm'] for p in acc):.2f} mm); refused {len(ref)} "
          f"(of which right: {sum(p['right'] for p in ref)}); RMS accepted {min(p['rms_mm'] for p in acc):.3f}-"
          f"{max(p['rms_mm'] for p in acc):.3f} mm, refused and off the lab's pose "
          f"{min(p['rms_mm'] for p in ref if not p['right'] and np.isfinite(p['rms_mm'])):.3f}+ mm")
    words = (("overlap", " below "), ("RMS", " above "), ("ambiguous", "ambiguous"), ("no hypothesis", "no hypothesis"))
    causes = {cause: sum(word in p["reason"] for p in ref) for cause, word in words}
    print("refused for (a pair may have several causes): " + ", ".join(f"{k} {v}" for k, v in causes.items()))
    ratios = [p["runner_up_fitness"] / p["fitness"] for p in acc]
    print(f"accepted pairs with a distinct runner-up whose RMS passes: {sum(r > 0 for r in ratios)} of {len(acc)} "
          f"(largest runner-up / best overlap {max(ratios):.2f})")
    print("\n| alignment | scans | mesh vertices | watertight | lab mesh -> ours: median / RMS / 95 % (mm) "
          "| ours (measured part) -> lab mesh: median / RMS / 95 % (mm) | scan to scan: median / worst pair (mm) |")
    print("|---|---|---|---|---|---|---|")
    for label, m in meshes.items():
        a, b, c = m["lab_to_ours"], m["ours_to_lab"], m["scan_to_scan"]
        print(f"| {label} | {m['scans']} | {m['vertices']:,} | {m['watertight']} | {a['median']:.3f} / "
              f"{a['rms']:.3f} / {a['p95']:.3f} | {b['median']:.3f} / {b['rms']:.3f} / {b['p95']:.3f} | "
              f"{c['median']:.3f} / {c['max']:.3f} ({c['pairs']} pairs) |")
    print("\n| step | seconds |\n|---|---|")
    for label, seconds in times.items():
        print(f"| {label} | {seconds:.1f} |")
    if args.json:
        args.json.write_text(json.dumps(dict(scans=rows, pairs=pairs, meshes=meshes, seconds=times), indent=1,
                                        default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
