"""`weldrecon batch` on a loaded machine (issue 28): a `weldrecon demo` reconstruction runs beside
it, and the batch, each time into a new workspace, must start and finish without a Prefect
API-server timeout, three times in a row.

    python bench/batch_under_load.py WORK [--rounds 3]

WORK holds the ci sample (simulated once), the samples the batch reconstructs (the tests' six-pass
subset of it, twice, under two ids), the demo's folder and one workspace per round. Prints one line
per round (exit status, seconds, whether the demo was still running when the batch ended, any
"Timed out" line) and the tally; exits 1 when a round failed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
QUICK = REPO / "tests" / "data" / "quick.yaml"
SIX = ["top-L02", "top-L04", "top-L05", "bottom-L02", "bottom-L04", "bottom-L05"]  # tests/conftest.py SIX


def weldrecon(*args) -> list[str]:
    return [sys.executable, "-m", "flows.cli", *map(str, args)]


def samples(work: Path) -> Path:
    """Two copies of the six-pass subset of the ci sample, ids load-a and load-b."""
    from tests.flows.samples import copy_sample

    ci = work / "ci"
    if not ci.is_dir():
        subprocess.run(weldrecon("simulate", "--preset", "ci", "--no-preview", ci), cwd=REPO, check=True,
                       stdout=subprocess.DEVNULL)
    root = work / "samples"
    shutil.rmtree(root, ignore_errors=True)
    for name in ("a", "b"):
        sample = copy_sample(ci, root / name, SIX)
        manifest = json.loads((sample / "manifest.json").read_text())
        manifest["sample_id"] = f"load-{name}"
        (sample / "manifest.json").write_text(json.dumps(manifest))
    return root


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    root = samples(work)
    shutil.rmtree(work / "demo", ignore_errors=True)
    demo_log = open(work / "demo.log", "w")
    demo = subprocess.Popen(weldrecon("demo", "--out", work / "demo"), cwd=REPO, stdout=demo_log,
                            stderr=subprocess.STDOUT)
    time.sleep(20)  # the demo simulating, then reconstructing: the machine busy before the first round
    failed = 0
    try:
        for k in range(1, args.rounds + 1):
            ws = work / f"ws-{k}"
            shutil.rmtree(ws, ignore_errors=True)
            started = time.monotonic()
            done = subprocess.run(weldrecon("batch", "--samples", root, "--workspace", ws, "--config", QUICK),
                                  cwd=REPO, capture_output=True, text=True, timeout=1800)
            seconds = time.monotonic() - started
            timed_out = [line for line in (done.stdout + done.stderr).splitlines() if "Timed out" in line]
            busy = demo.poll() is None
            ok = done.returncode == 0 and not timed_out and "done: load-a, load-b" in done.stdout
            failed += not ok
            print(f"round {k}: exit {done.returncode}, {seconds:.0f} s, demo {'running' if busy else 'finished'} "
                  f"at its end, {'OK' if ok else 'FAILED'}" + (f": {timed_out[0]}" if timed_out else "")
                  + ("" if ok else f"\n{done.stdout[-1500:]}{done.stderr[-1500:]}"), flush=True)
    finally:
        demo.wait()
        demo_log.close()
    print(f"{args.rounds - failed} of {args.rounds} rounds ok beside a demo (exit {demo.returncode})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
