"""Replay a finished sample as a scan in progress: the manifest first, then each pass store when
the robot would have finished it, into a new folder that ``weldrecon reconstruct --follow`` can
follow. Then, given the run folder, how long after the last pass each stage ended and each
provisional verdict, mesh and QA page (with the FE model
and the stress) was published.

    .venv/bin/python bench/replay_scan.py SAMPLE_DIR LIVE_DIR [--pace N]
    .venv/bin/python bench/replay_scan.py --lag LIVE_DIR RUN_DIR

Unlike ``weldrecon simulate --pace``, nothing is rendered: the replay costs no CPU, so the
reconstruction has the machine to itself, as beside a real cell. A pass lands as a cell writes
it: copied under a hidden name, then renamed. ``--pace N``: N times the robot's speed (default 1).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def replay(sample: Path, live: Path, pace: float) -> None:
    from data_catalog.manifests import MANIFEST_NAME, load_manifest

    manifest = load_manifest(sample)
    live.mkdir(parents=True)
    (live / "passes").mkdir()
    shutil.copy2(sample / MANIFEST_NAME, live / MANIFEST_NAME)
    start, scanned = time.monotonic(), 0.0
    landed: dict[str, float] = {}
    for _, entry in manifest.passes():
        hidden = live / "passes" / f".{Path(entry.file).name}.partial"
        shutil.copytree(sample / entry.file, hidden)
        scanned += entry.duration_s
        time.sleep(max(0.0, start + scanned / pace - time.monotonic()))
        os.rename(hidden, live / entry.file)
        landed[entry.pass_id] = time.time()
        print(f"{time.monotonic() - start:8.1f} s  {entry.pass_id} landed", flush=True)
    _landings(live).write_text(json.dumps(landed, indent=1) + "\n")


def _landings(live: Path) -> Path:
    """Where the replay records when each pass landed: beside the live folder, not in it."""
    return live.with_name(live.name + ".landed.json")


def lag(live: Path, run: Path) -> dict:
    from data_catalog.audit import read_trail

    times = json.loads(_landings(live).read_text())
    landed, first = max(times.values()), min(times.values())
    stages = {e["stage"]: datetime.fromisoformat(e["record"]["finished"]).timestamp()
              for e in read_trail(run) if e.get("kind") == "stage" and "record" in e}
    provisional = [(e["after_pass"], e["passes"], e.get("verdict"), datetime.fromisoformat(e["time"]).timestamp())
                   for e in read_trail(run) if e.get("kind") == "provisional-published"]
    meshes = [(e["after_pass"], e["passes"], e.get("vertices"), datetime.fromisoformat(e["time"]).timestamp())
              for e in read_trail(run) if e.get("kind") == "provisional-mesh-published"]
    models = [(e["after_pass"], e["passes"], e.get("tetrahedra"), e.get("hot_spot_factor"),
               datetime.fromisoformat(e["time"]).timestamp())
              for e in read_trail(run) if e.get("kind") == "provisional-model-published"]
    return {"first_to_last_pass_s": round(landed - first, 1),
            "after_last_pass_s": {name: round(t - landed, 1) for name, t in sorted(stages.items(), key=lambda x: x[1])},
            "provisional_verdicts": [{"after_pass": p, "passes": n, "verdict": v, "after_its_landing_s": round(t - times[p], 1),
                                      "after_last_pass_s": round(t - landed, 1)} for p, n, v, t in provisional],
            "provisional_meshes": [{"after_pass": p, "passes": n, "vertices": v, "after_last_pass_s": round(t - landed, 1)}
                                   for p, n, v, t in meshes],
            "provisional_models": [{"after_pass": p, "passes": n, "tetrahedra": k, "hot_spot_factor": f,
                                    "after_last_pass_s": round(t - landed, 1)} for p, n, k, f, t in models]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lag", action="store_true", help="report how long after the last pass each stage ended")
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("--pace", type=float, default=1.0)
    args = parser.parse_args()
    if args.lag:
        print(json.dumps(lag(args.first, args.second), indent=1))
    else:
        replay(args.first, args.second, args.pace)
    return 0


if __name__ == "__main__":
    sys.exit(main())
