"""The FE stages' time and memory, the code of two commits side by side: each stage's body run again
in a fresh process on a finished run's inputs, its wall time and the peak resident memory of the
process and of its largest child (gmsh, CalculiX).

    python bench/bench_fe_stages.py RUN STAGE [STAGE ...] --sample DIR [--repo DIR] [--config FILE]

``RUN``: a run folder made by the code in ``--repo`` (default: this checkout), whose stages
``STAGE`` needs are there (``stages/<stage>/<key>/``; the newest folder of each); the stage's
outputs go to a temporary folder (``--keep DIR``: to ``DIR/<stage>``). One JSON line per stage: seconds, peak RSS (MB) of this
process and of its largest child. The issue-26 comparison: the FE model stage of cdd4c41 (a
worktree of it, with its own run of the sample) against this checkout's ``volume`` and ``stress``,
one after the other on the same machine (bench/README.md, "The FE stages against cdd4c41")."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

_DRIVER = r'''
import json, resource, sys, tempfile, time
from pathlib import Path
run, name, config_path, keep = Path(sys.argv[1]), sys.argv[2], sys.argv[3] or None, sys.argv[5]
from data_catalog.manifests import load_manifest
from flows.preflight import load_config
from flows.stages import STAGES
from flows.stages.contracts import StageRef
from flows.stages.runner import StageContext

stage = next(s for s in STAGES if s.name == name)
sample = Path(sys.argv[4])

def ref(needed):
    folders = sorted((run / "stages" / needed).iterdir(), key=lambda p: p.stat().st_mtime)
    folder = folders[-1]
    return StageRef(stage=needed, item=None, key=folder.name, path=str(folder),
                    outputs={p.name: "" for p in folder.iterdir()}, cached=True)

manifest = load_manifest(sample)
config = load_config(config_path)
settings = getattr(config, stage.settings) if isinstance(stage.settings, str) and stage.settings != "*" else config
with tempfile.TemporaryDirectory() as scratch:
    out = Path(keep) / name if keep else Path(scratch)
    out.mkdir(parents=True, exist_ok=True)
    ctx = StageContext(out=out, sample_dir=sample, manifest=manifest, config=config, settings=settings,
                       entry=None, inputs={n: ref(n) for n in stage.needs})
    start = time.perf_counter()
    metrics = stage.body(ctx)
    seconds = time.perf_counter() - start
print(json.dumps({"stage": name, "seconds": round(seconds, 1),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024,
                  "largest_child_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss // 1024,
                  "metrics": {k: v for k, v in (metrics or {}).items() if isinstance(v, (int, float, str))}}))
'''


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("stages", nargs="+")
    parser.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--config", default="")
    parser.add_argument("--keep", type=Path, help="write each stage's outputs to DIR/<stage> (default: thrown away)")
    parser.add_argument("--sample", required=True, type=Path, help="the sample folder the run reconstructed")
    args = parser.parse_args()
    env = {**os.environ, "PYTHONPATH": str(args.repo.resolve())}
    for name in args.stages:
        done = subprocess.run([sys.executable, "-c", _DRIVER, str(args.run.resolve()), name, args.config,
                               str(args.sample.resolve()), str(args.keep.resolve()) if args.keep else ""],
                              cwd=args.repo, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"{name}: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else 'failed'}")
        line = json.loads(done.stdout.strip().splitlines()[-1])
        line["repo"] = str(args.repo)
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
