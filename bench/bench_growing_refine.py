"""The pose refinement grown with the scan (issue 29) against the refine stage's whole problem, on
one sample's real stage outputs (its denoised passes, its target registration), in one process.

    .venv/bin/python bench/bench_growing_refine.py SAMPLE_DIR STORE_DIR [--config CONFIG.yaml] [--json OUT.json]

STORE_DIR is a run folder (or an empty one; ``$WELDRECON_STAGE_CACHE`` is used when set): the
stages up to ``refine`` are made there first as the flow makes them. Then, with the refine stage's
own settings and surface samples (``flows.stages.refine``):

- ``whole``: ``tasks.refine.refine_poses`` on every pass from the target poses: the refine stage;
- ``last added``: the problem of every pass but the last solved the same way, then the last pass
  added alone (``free=[last]``, the others held, ``warm``): what the verdict needs once the last
  pass lands, the rest solved while the robot scanned it;
- ``pass by pass``: each pass added alone to the passes before it, in the robot's order, never
  solved together; then ``+ joint, warm``: every pass freed once, warm, from there.

Per variant: seconds and iterations, and with the simulator's truth (``truth/`` in SAMPLE_DIR) the
passes' misalignment (``simulator.evaluate.pass_misalignment``: worst pass, median of the passes'
medians) and how far each pass's points lie from where ``whole`` puts them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_catalog.manifests import load_manifest  # noqa: E402 - after the path is set
from data_catalog.stages import StageStore  # noqa: E402
from flows.preflight import load_config  # noqa: E402
from flows.stages import run_in_process  # noqa: E402
from flows.stages.outputs import REGISTRATION  # noqa: E402
from flows.stages.refine import pass_surface_sample, refine_arguments, target_pairs  # noqa: E402
from tasks.frames import apply  # noqa: E402
from tasks.refine import NothingToRefine, refine_poses  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sample", type=Path)
    parser.add_argument("store", type=Path)
    parser.add_argument("--config", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    manifest = load_manifest(args.sample)
    config = load_config(args.config)
    refs = run_in_process(store=StageStore(args.store), sample_dir=args.sample, manifest=manifest, config=config,
                          upto="refine")
    rc = config.refine
    reg = REGISTRATION.read(refs["registration"])
    E, A, B, sigma = target_pairs(reg, rc)
    t0 = time.perf_counter()
    samples = [pass_surface_sample(manifest, entry, ref, rc) for (_, entry), ref in zip(manifest.passes(), refs["denoise"])]
    sampling_s = time.perf_counter() - t0
    sigma = np.broadcast_to(np.asarray(sigma, np.float64), (len(E),)).copy()  # each pair's, subset with it
    kw = refine_arguments(rc)
    n, last = len(samples), len(samples) - 1
    names = [entry.pass_id for _, entry in manifest.passes()]
    rows = []

    def timed(name, fn):
        t = time.perf_counter()
        T, iterations = fn()
        rows.append({"variant": name, "seconds": time.perf_counter() - t, "iterations": iterations, "T": T})
        return T

    def whole():
        r = refine_poses(samples, reg.T_common_pass, E, A, B, **kw, target_sigma_mm=sigma)
        return r.T_common_pass, len(r.step_mm)

    T_whole = timed("whole", whole)
    before = ~(E == last).any(axis=1)
    first = refine_poses(samples[:last], reg.T_common_pass[:last], E[before], A[before], B[before], **kw,
                         target_sigma_mm=sigma[before])

    def last_added():
        held = np.concatenate([first.T_common_pass, reg.T_common_pass[last:]])
        r = refine_poses(samples, held, E, A, B, **kw, target_sigma_mm=sigma, free=[last], warm=True)
        return r.T_common_pass, len(r.step_mm)

    timed("last added", last_added)
    grown = reg.T_common_pass.copy()
    left_at_targets = []

    def pass_by_pass():
        iterations = 0
        for k in range(1, n):
            sel = (E <= k).all(axis=1)
            try:
                r = refine_poses(samples[:k + 1], grown[:k + 1], E[sel], A[sel], B[sel], **kw, target_sigma_mm=sigma[sel],
                                 free=[k], warm=True)
            except NothingToRefine:  # nothing shared with the passes before it yet: its target pose stays
                left_at_targets.append(names[k])
                continue
            grown[k] = r.T_common_pass[k]
            iterations += len(r.step_mm)
        return grown.copy(), iterations

    timed("pass by pass", pass_by_pass)

    def joint():
        r = refine_poses(samples, grown, E, A, B, **kw, target_sigma_mm=sigma, warm=True)
        return r.T_common_pass, len(r.step_mm)

    timed("pass by pass + joint, warm", joint)
    truth = (args.sample / "truth").is_dir()
    if truth:
        from simulator.evaluate import pass_misalignment
    print(f"{manifest.sample_id}: {n} passes; the surface samples {sampling_s:.1f} s (once, shared); "
          f"the first {last} passes solved together in {len(first.step_mm)} iterations")
    if left_at_targets:
        print(f"pass by pass: {len(left_at_targets)} pass(es) shared nothing with the passes before them: {left_at_targets}")
    print("| variant | seconds | ratio to whole | iterations | worst pass um | median of pass medians um | "
          "farthest from whole um |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        T = row.pop("T")
        row["from_whole_um"] = 1000 * max(float(np.abs(apply(T[k], s.points_mm) - apply(T_whole[k], s.points_mm)).max(initial=0))
                                          for k, s in enumerate(samples))
        if truth:
            m = pass_misalignment(args.sample, T)
            row["worst_um"], row["median_um"] = 1000 * float(m.max_mm.max()), 1000 * float(np.median(m.median_mm))
        print(f"| {row['variant']} | {row['seconds']:.1f} | {row['seconds'] / rows[0]['seconds']:.2f} | {row['iterations']} | "
              f"{row.get('worst_um', float('nan')):.1f} | {row.get('median_um', float('nan')):.1f} | {row['from_whole_um']:.1f} |")
    if args.json:
        args.json.write_text(json.dumps({"sample": manifest.sample_id, "passes": n, "sampling_s": sampling_s,
                                         "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
