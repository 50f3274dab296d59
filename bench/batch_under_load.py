"""`weldrecon batch` on a loaded machine (issue 28): a `weldrecon demo` reconstruction runs beside
it, and the batch, each time into a new workspace, must start and finish without a Prefect
API-server timeout, three times in a row.

    python bench/batch_under_load.py WORK [--rounds 3]

WORK holds the ci sample (simulated once), the samples the batch reconstructs (the tests' six-pass
subset of it, twice, under two ids), the demos' folders (a new demo starts when the last ends, so
that one runs beside every round) and one workspace per round. Prints one line per round (exit
status, seconds, how much of the time a demo ran beside it, any "Timed out" line) and the tally;
exits 1 when a round failed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
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


class Demos:
    """`weldrecon demo` run again and again beside the rounds (a new one when the last ends), each
    into its own folder under WORK; ``stop`` ends the one running and says how each ended."""

    def __init__(self, work: Path) -> None:
        self.work, self.ended, self._stop = work, [], threading.Event()
        self._proc: subprocess.Popen | None = None
        self._thread = threading.Thread(target=self._loop)

    def _loop(self) -> None:
        k = 0
        while not self._stop.is_set():
            k += 1
            folder = self.work / f"demo-{k}"
            shutil.rmtree(folder, ignore_errors=True)
            with open(self.work / f"demo-{k}.log", "w") as log:
                self._proc = subprocess.Popen(weldrecon("demo", "--out", folder), cwd=REPO, stdout=log,
                                              stderr=subprocess.STDOUT, start_new_session=True)
                rc = self._proc.wait()
            self.ended.append("stopped" if self._stop.is_set() else f"exit {rc}")

    def start(self) -> None:
        self._thread.start()

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self) -> str:
        self._stop.set()
        if self._proc is not None and self._proc.poll() is None:
            os.killpg(self._proc.pid, signal.SIGTERM)
        self._thread.join()
        return ", ".join(self.ended)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    root = samples(work)
    beside = Demos(work)
    beside.start()
    time.sleep(20)  # the demo simulating, then reconstructing: the machine busy before the first round
    failed = 0
    try:
        for k in range(1, args.rounds + 1):
            ws = work / f"ws-{k}"
            shutil.rmtree(ws, ignore_errors=True)
            started = time.monotonic()
            batch = subprocess.Popen(weldrecon("batch", "--samples", root, "--workspace", ws, "--config", QUICK),
                                     cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            samples_busy = []
            while batch.poll() is None:  # once a second: is a demo running beside it?
                samples_busy.append(beside.running())
                time.sleep(1)
            out, err = batch.communicate()
            seconds = time.monotonic() - started
            timed_out = [line for line in (out + err).splitlines() if "Timed out" in line]
            ok = batch.returncode == 0 and not timed_out and "done: load-a, load-b" in out
            failed += not ok
            busy = 100 * sum(samples_busy) / max(1, len(samples_busy))
            print(f"round {k}: exit {batch.returncode}, {seconds:.0f} s, a demo running beside it {busy:.0f} % of the "
                  f"time, {'OK' if ok else 'FAILED'}" + (f": {timed_out[0]}" if timed_out else "")
                  + ("" if ok else f"\n{out[-1500:]}{err[-1500:]}"), flush=True)
    finally:
        demos = beside.stop()
    print(f"demos beside: {demos}")
    print(f"{args.rounds - failed} of {args.rounds} rounds ok")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
