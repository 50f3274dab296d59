"""Accuracy of a finished reconstruction against the simulator's truth.

    .venv/bin/python bench/accuracy.py SAMPLE_DIR RUN_DIR [--json OUT.json]

Pass misalignment (``simulator.evaluate.pass_misalignment``): per pass, the largest and the median
distance between where the reconstruction puts its measured specimen points and where they truly
are, after one rigid fit of the whole; for the target registration alone (the paper's method) and
after the refinement. Mesh to the true surface: every STL vertex, in the specimen frame (fitted on
the registered targets against the true stickers), its distance to the true specimen mesh; over
the scanned length, and within 15 mm of the weld's lines (the manifest's, ``weld_lines()``); for a
part with fillet welds (``truth/toes.json``, the T-joint presets), within 5 mm of the true toe lines
(median, 95 % and max).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def latest_stage(run: Path, stage: str) -> Path:
    """The stage folder the run's audit trail names last for ``stage``."""
    from data_catalog.audit import read_trail

    entries = [e for e in read_trail(run) if e.get("kind") == "stage" and e.get("stage") == stage]
    if not entries:
        raise SystemExit(f"{run}: no finished stage {stage} in its audit trail")
    return run / "stages" / stage / entries[-1]["cache_key"]


class StageFolder:
    """A finished stage's folder as the stage outputs read it (``OUTPUT.read(folder)``: ``.file(name)``)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def file(self, name: str) -> Path:
        return self.folder / name


def stage_folder(run: Path, stage: str) -> StageFolder:
    """The folder of ``stage`` the run's audit trail names last (``latest_stage``), to read its outputs."""
    return StageFolder(latest_stage(run, stage))


def pass_misalignments(sample: Path, run: Path) -> dict:
    """``simulator.evaluate.pass_misalignment`` of the run's target registration ("targets
    alone") and of its refined poses ("refined")."""
    from data_catalog.stages import load_arrays
    from simulator.evaluate import pass_misalignment

    return {poses: pass_misalignment(sample, load_arrays(latest_stage(run, stage) / name, "T_common_pass")["T_common_pass"])
            for poses, stage, name in (("targets alone", "registration", "registration.zarr"),
                                       ("refined", "refine", "refined.zarr"))}


def evaluate(sample: Path, run: Path) -> dict:
    from data_catalog.stages import load_arrays
    from data_catalog.truth import TRUTH_DIR, read_truth

    result: dict = {poses: {"worst_um": round(1000 * float(np.nanmax(m.max_mm)), 1),
                            "median_of_pass_medians_um": round(1000 * float(np.nanmedian(m.median_mm)), 1)}
                    for poses, m in pass_misalignments(sample, run).items()}
    mesh = load_arrays(latest_stage(run, "mesh") / "mesh.zarr", "vertices")["vertices"]
    accuracy = mesh_to_truth(sample, run, mesh)
    result["mesh to truth, scanned length"] = accuracy["scanned length"]
    result["mesh to truth, within 15 mm of the weld"] = accuracy["within 15 mm of the weld"]
    result["mesh to truth, measured surface"] = accuracy["measured surface"]
    result["mesh to truth, measured, within 15 mm of the weld"] = accuracy["measured, within 15 mm of the weld"]
    if "within 5 mm of the toes" in accuracy:
        result["mesh to truth, within 5 mm of the toes"] = accuracy["within 5 mm of the toes"]
    result["gauge targets"] = accuracy["gauge targets"]
    result["sample"] = read_truth(sample / TRUTH_DIR / "truth.json").sample_id
    return result


def mesh_to_truth(sample: Path, run: Path, vertices: np.ndarray) -> dict:
    """Distances of mesh ``vertices`` (in ``run``'s common frame) to the true specimen surface:
    statistics over the scanned length (the part's extent along the specimen frame's x, less the
    never-scanned 2 mm at each end) and within 15 mm of any of the manifest's weld lines."""
    import open3d as o3d

    from data_catalog.manifests import load_manifest
    from data_catalog.stages import load_arrays
    from data_catalog.truth import TRUTH_DIR
    from simulator.evaluate import fit_gauge
    from tasks.weld_zone import PolylineZone

    refined = load_arrays(latest_stage(run, "refine") / "refined.zarr", "track_positions_mm", "specimen_track")
    positions = refined["track_positions_mm"]
    on_specimen = refined["specimen_track"].astype(bool)  # seen in two setups; a single setup has none:
    gauge = fit_gauge(sample, positions[on_specimen] if on_specimen.any() else positions, positions)  # all
    G_inv = np.linalg.inv(gauge.T_recon_specimen)
    v = np.asarray(vertices, np.float64) @ G_inv[:3, :3].T + G_inv[:3, 3]
    true_mesh = o3d.io.read_triangle_mesh(str(sample / TRUTH_DIR / "specimen.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(true_mesh))
    dist = scene.compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy().astype(np.float64)
    manifest = load_manifest(sample)
    lo, hi = manifest.specimen.bounds_mm()
    scanned = (v[:, 0] > lo[0] + 2) & (v[:, 0] < hi[0] - 2)  # the ends were never scanned: Poisson closes them freely
    near_weld = np.zeros(len(v), bool)
    for line in manifest.weld_lines():
        near_weld |= PolylineZone(tuple(line.points_mm), 15.0).contains(v)
    weld = scanned & near_weld
    # measured: within 0.5 mm of a point the segment kept (a single setup never sees the part's
    # underside, which Poisson closes freely; two setups leave only the ends unseen)
    from scipy.spatial import cKDTree
    cloud = load_arrays(latest_stage(run, "segment") / "specimen.zarr", "points", "measured")
    kept = cloud["points"][cloud["measured"].astype(bool)]
    d_kept, _ = cKDTree(np.asarray(kept, np.float64)).query(np.asarray(vertices, np.float64), distance_upper_bound=0.5)
    measured = np.isfinite(d_kept)

    def stats(d):
        return {"vertices": int(len(d)), "median_um": round(1000 * float(np.median(d)), 1),
                "rms_um": round(1000 * float(np.sqrt(np.mean(d**2))), 1),
                "p95_um": round(1000 * float(np.quantile(d, 0.95)), 1),
                "max_um": round(1000 * float(np.max(d)), 1)}

    out = {"scanned length": stats(dist[scanned]), "within 15 mm of the weld": stats(dist[weld]),
           "measured surface": stats(dist[measured]), "measured, within 15 mm of the weld": stats(dist[measured & weld]),
           "gauge targets": gauge.n_targets}
    near_toes = near_true_toes(sample, v, TOE_ZONE_MM)
    if near_toes is not None:
        out["within 5 mm of the toes"] = stats(dist[near_toes])
    return out


TOE_ZONE_MM = 5.0


def near_true_toes(sample: Path, vertices_specimen: np.ndarray, radius_mm: float) -> np.ndarray | None:
    """(n,) bool: the vertices (n, 3) (specimen frame, mm) within ``radius_mm`` of a true toe line
    (``truth/toes.json``); None for a part without one (the dog-bone presets)."""
    from data_catalog.truth import TRUTH_DIR, read_true_toes
    from simulator.run import TOES_NAME
    from tasks.weld_zone import PolylineZone

    path = Path(sample) / TRUTH_DIR / TOES_NAME
    if not path.is_file():
        return None
    near = np.zeros(len(vertices_specimen), bool)
    for toe in read_true_toes(path).toes:
        points = toe.points_mm[::8] + toe.points_mm[-1:]  # every 2 mm: the toes are straight over that
        near |= PolylineZone(tuple(points), radius_mm).contains(vertices_specimen)
    return near


def emit(result: dict, json_path: Path | None) -> None:
    """Print ``result`` as JSON, and write it to ``json_path`` when given."""
    print(json.dumps(result, indent=1))
    if json_path:
        json_path.write_text(json.dumps(result, indent=1) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    emit(evaluate(args.sample, args.run), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
