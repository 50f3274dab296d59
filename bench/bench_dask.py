"""Throughput of the per-pass stages (denoise and targets, streamed in blocks) on a local Dask
cluster of 1 and of 2 worker processes: the same ``run_stage`` calls the flow's Dask task runner
makes, submitted straight to the cluster (each run into a fresh stage store).

    .venv/bin/python bench/bench_dask.py SAMPLE_DIR [--workers 1 2] [--passes N] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _run_pass(sample: str, store: str, stage_name: str, index: int) -> dict:
    from data_catalog.manifests import load_manifest
    from data_catalog.stages import StageStore
    from flows.stages import run_stage, stage
    from schemas.reconstruction import ReconstructionConfig

    manifest = load_manifest(Path(sample))
    entry = manifest.passes()[index][1]
    ref = run_stage(stage(stage_name), store=StageStore(Path(store)), sample_dir=Path(sample), manifest=manifest,
                    config=ReconstructionConfig(), inputs={}, entry=entry)
    return {"pass": entry.pass_id, "stage": stage_name, "seconds": ref.metrics["seconds"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--passes", type=int, help="the first N passes (default all)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    from distributed import Client, LocalCluster

    from data_catalog.manifests import load_manifest

    manifest = load_manifest(args.sample)
    passes = manifest.passes()[: args.passes or None]
    points = sum(e.n_profiles for _, e in passes) * manifest.scanner.points_per_profile
    rows = []
    for workers in args.workers:
        with tempfile.TemporaryDirectory(dir=ROOT / "bench") as store, \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            client.run(lambda: __import__("tasks.denoise") and __import__("tasks.normals"))  # compile before timing
            warm = client.submit(_run_pass, str(args.sample), store + "/warm", "denoise", len(passes) - 1, pure=False)
            warm.result()
            t0 = time.perf_counter()
            futures = [client.submit(_run_pass, str(args.sample), store, name, k, pure=False)
                       for name in ("denoise", "targets") for k in range(len(passes))]
            done = client.gather(futures)
            wall = time.perf_counter() - t0
        rows.append({"workers": workers, "wall_s": round(wall, 1), "points": points,
                     "pass_points_per_s": round(points / wall), "stage_seconds": round(sum(d["seconds"] for d in done), 1)})
        print(json.dumps(rows[-1]), flush=True)
    if len(rows) > 1:
        print(f"speed-up {rows[0]['workers']} -> {rows[-1]['workers']} workers: {rows[0]['wall_s'] / rows[-1]['wall_s']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
