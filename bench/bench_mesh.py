"""Meshing: our non-uniform cloud against MeshLab's screened Poisson on the uniform cloud, side by
side in one process, same depth, same points.

    .venv/bin/python bench/bench_mesh.py SAMPLE_DIR UNIFORM_RUN [--json OUT.json]

UNIFORM_RUN is a finished reconstruction of SAMPLE_DIR with ``merge: coarse_factor: 1`` (the
paper's uniform 0.1 mm box grid); its specimen cloud (stage ``segment``) is "the points".

- peer: pymeshlab's ``generate_surface_reconstruction_screened_poisson`` on those points and
  their normals, at the run's depth, samples per node, point weight and scale, with MeshLab's
  own thread count (its default);
- ours: the same points coarsened where flat and away from the weld (``merge`` with the default
  settings: ``tasks.merge.coarsen_flat_cells`` with the weld zone of ``flows.stages.merge``), then
  the mesh stage's ``tasks.mesh.screened_poisson`` (the same MeshLab filter, one thread: the same
  bytes on every run).

Both meshes are measured against the true surface (``bench/accuracy.py``): within 15 mm of the
weld's lines and over the scanned length.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("uniform_run", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import pymeshlab  # noqa: F401  (first: beside Open3D it must load first)

    from bench.accuracy import emit, latest_stage, mesh_to_truth
    from data_catalog.manifests import load_manifest
    from flows.reconstruct import load_config
    from flows.stages.placement import sample_weld_zone
    from data_catalog.stages import load_arrays
    from tasks.merge import MergeResult, coarsen_flat_cells
    from tasks.mesh import mesh_report, screened_poisson

    run = args.uniform_run
    used = load_config(run / "results" / "config.json")
    if used.merge.coarse_factor != 1:
        raise SystemExit(f"{run}: merged with coarse_factor {used.merge.coarse_factor}; the peer needs the uniform "
                         "cloud (coarse_factor: 1)")
    ms, mc = used.mesh, load_config(None).merge
    cell = used.merge.cell_mm
    specimen = load_arrays(latest_stage(run, "segment") / "specimen.zarr", "points", "normals")
    merged = load_arrays(latest_stage(run, "merge") / "merged.zarr", "points", "counts")
    points, normals = specimen["points"], specimen["normals"].astype(np.float64)
    # each specimen point's measured-point count, from the merged cloud it was cut from
    cells = np.floor(points / cell).astype(np.int64)
    merged_cells = np.floor(merged["points"] / cell).astype(np.int64)
    low = np.minimum(cells.min(axis=0), merged_cells.min(axis=0))
    span = np.maximum(cells.max(axis=0), merged_cells.max(axis=0)) - low + 1
    key = lambda c: np.ravel_multi_index(tuple((c - low).T), tuple(span))  # noqa: E731
    merged_keys = key(merged_cells)
    order = np.argsort(merged_keys)
    where = order[np.searchsorted(merged_keys, key(cells), sorter=order)]
    assert np.array_equal(merged_cells[where], cells), "specimen points are not cells of the merged cloud"
    counts = merged["counts"][where].astype(np.int64)
    del merged, merged_cells, merged_keys, order, where
    result: dict = {"sample": str(args.sample), "points": int(len(points)), "depth": ms.poisson_depth}

    t = time.perf_counter()
    mesh_set = pymeshlab.MeshSet()
    mesh_set.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points),
                                     v_normals_matrix=np.ascontiguousarray(normals)))
    mesh_set.generate_surface_reconstruction_screened_poisson(
        depth=ms.poisson_depth, samplespernode=ms.samples_per_node, pointweight=ms.point_weight,
        scale=ms.poisson_scale, preclean=False, confidence=False)
    peer_mesh = mesh_set.current_mesh()
    peer_vertices = np.array(peer_mesh.vertex_matrix(), dtype=np.float64)
    peer_triangles = np.array(peer_mesh.face_matrix(), dtype=np.int64)
    peer_s = time.perf_counter() - t
    del peer_mesh, mesh_set
    result["peer"] = {"what": "pymeshlab screened Poisson on the uniform cloud, MeshLab's default threads",
                      "seconds": round(peer_s, 1), "points": int(len(points)), "vertices": int(len(peer_vertices)),
                      "watertight": mesh_report(peer_vertices, peer_triangles).watertight,
                      **mesh_to_truth(args.sample, run, peer_vertices)}
    del peer_vertices, peer_triangles

    t = time.perf_counter()
    T_all = load_arrays(latest_stage(run, "refine") / "refined.zarr", "T_common_pass")["T_common_pass"]
    zone = sample_weld_zone(load_manifest(args.sample), T_all, mc.weld_zone_mm, widened=True)
    adaptive = coarsen_flat_cells(
        MergeResult(points_mm=points, normals=normals, sensor_positions_mm=None, counts=counts, cells=cells,
                    cell_mm=cell),
        factor=mc.coarse_factor, max_normal_deg=mc.flat_normal_deg, max_deviation_mm=mc.flat_deviation_mm,
        fine_zone=zone)
    coarsen_s = time.perf_counter() - t
    t = time.perf_counter()
    ours = screened_poisson(adaptive.points_mm, adaptive.normals, depth=ms.poisson_depth,
                            samples_per_node=ms.samples_per_node, point_weight=ms.point_weight, scale=ms.poisson_scale)
    ours_s = time.perf_counter() - t
    result["ours"] = {"what": f"coarse factor {mc.coarse_factor} where flat, weld zone {mc.weld_zone_mm} mm "
                              f"(+ tolerance, {len(zones)} weld-line zones) fine; MeshLab one thread",
                      "seconds": round(coarsen_s + ours_s, 1), "coarsen_s": round(coarsen_s, 1),
                      "poisson_s": round(ours_s, 1), "points": int(len(adaptive.points_mm)),
                      "fine_points": int(adaptive.fine.sum()), "weld_zone_points": int(adaptive.in_zone.sum()),
                      "vertices": int(len(ours.vertices)), "watertight": ours.report.watertight,
                      **mesh_to_truth(args.sample, run, ours.vertices)}
    result["peer_over_ours"] = round(peer_s / (coarsen_s + ours_s), 2)
    emit(result, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
