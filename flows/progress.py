"""Progress of a reconstruction, read from its audit trail while it runs.

The stages append to ``OUT/audit/trail.jsonl`` as they finish, from this process or from Dask
worker processes, so the display watches that file instead of hooking into Python calls. On a
terminal it is a rich progress display, one bar per stage; elsewhere (CI, log files) one plain
line per finished pass or stage. Entries written before the display started are ignored.

A scan followed as it comes in (``plan``: ``tasks.pass_coverage.PlanCoverage``) also says, as each
pass is in (its denoise stage done), what the next pass of the plan will add to the weld lines,
predicted from its sweep and the drawing.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from data_catalog.audit import TRAIL

if TYPE_CHECKING:  # the display itself loads no processing code
    from tasks.pass_coverage import PlanCoverage

__all__ = ["TrailProgress", "plan_text", "adds_text"]


def _stretches(stretches) -> str:
    return ", ".join(f"{a:.0f}-{b:.0f}" if b > a else f"{a:.0f}" for a, b in stretches)


def adds_text(plan: PlanCoverage, index: int, landed: set[int]) -> str:
    """What pass ``index`` of ``plan`` (``tasks.pass_coverage.PlanCoverage``) will add to the
    weld lines after the passes ``landed``: "line top 8-52 mm (new: 25-52)"."""
    adds = plan.adds(index, landed)
    if not adds:
        return "no weld line in its sweep"
    return "; ".join(f"line {name} {_stretches(mine)} mm (" + (f"new: {_stretches(new)}" if new else "seen before") + ")"
                     for name, mine, new in adds)


def plan_text(plan: PlanCoverage) -> list[str]:
    """The plan's predicted weld coverage, a line per weld line, and what no pass reaches."""
    if not plan.predicted:
        return [f"what each pass will add cannot be predicted: {plan.reason}"]
    lines = []
    for line in plan.lines:
        count = int(line.seen.any(axis=1).sum())
        reached = _stretches(line.reached()) or "nothing"
        lines.append(f"the plan reaches weld line {line.name} ({line.along_mm[-1]:.0f} mm) at {reached} mm "
                     f"with {count} of {len(plan.pass_ids)} passes (predicted from the sweeps and the drawing)")
    for name, stretches in plan.unreached():
        lines.append(f"no pass of the plan reaches weld line {name} at {_stretches(stretches)} mm")
    return lines



@dataclass
class _Count:
    expected: int
    done: int = 0
    cached: int = 0
    seconds: float = 0.0
    failed: list[str] = field(default_factory=list)


class TrailProgress:
    """``with TrailProgress(out_dir, [("denoise", 32), ("registration", 1), ...]):`` shows each
    stage's finished / expected count, how many were reused from the cache, and the time its
    work took, until the block ends; then one line per stage that failed."""

    def __init__(self, out_dir: Path, expected: list[tuple[str, int]], *, stream: TextIO = sys.stderr,
                 interval_s: float = 0.5, plan: PlanCoverage | None = None) -> None:
        self._path = Path(out_dir) / TRAIL
        self._counts = {name: _Count(n) for name, n in expected}
        self._stream, self._interval = stream, interval_s
        self._tty = bool(getattr(stream, "isatty", lambda: False)())
        self._offset = 0
        self._partial = b""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = 0.0
        self._rich: Any = None
        self._bars: dict[str, Any] = {}
        self._untrusted = 0  # stages set aside because the folder's trail did not verify
        self._plan = plan if plan is not None and plan.predicted else None
        self._landed: set[int] = set()

    def __enter__(self) -> "TrailProgress":
        self._offset = self._path.stat().st_size if self._path.is_file() else 0
        self._started = time.perf_counter()
        if self._tty:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._rich = Progress(TextColumn("{task.description:<13}"), BarColumn(), MofNCompleteColumn(),
                                  TextColumn("{task.fields[note]}"), TimeElapsedColumn(),
                                  console=Console(file=self._stream), transient=False)
            self._bars = {name: self._rich.add_task(name, total=c.expected, note="") for name, c in self._counts.items()}
            self._rich.start()
        if self._plan is not None:
            self._say(f"next: pass {self._plan.pass_ids[0]} (1 of {len(self._plan.pass_ids)}) adds "
                      f"{adds_text(self._plan, 0, set())}", final=True)
        self._thread = threading.Thread(target=self._watch, name="trail-progress", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._poll()
        if self._rich is not None:
            self._rich.stop()
        if self._untrusted:
            self._say(f"{self._untrusted} stage(s) of the folder set aside as untrusted and made again", final=True)
        for name, c in self._counts.items():
            if c.failed:
                failed = list(dict.fromkeys(c.failed))  # a retried item failed more than once: named once
                self._say(f"{name} {c.done}/{c.expected} done, FAILED: {', '.join(failed)}", final=True)

    def _watch(self) -> None:
        while not self._stop.wait(self._interval):
            self._poll()

    def _poll(self) -> None:
        try:
            with open(self._path, "rb") as handle:
                handle.seek(self._offset)
                chunk = handle.read()
        except OSError:
            return
        self._offset += len(chunk)
        lines = (self._partial + chunk).split(b"\n")
        self._partial = lines.pop()  # an unfinished last line waits for the rest
        for line in lines:
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if not isinstance(entry, dict):
                continue
            try:
                self._show(entry)
            except (TypeError, ValueError, AttributeError, KeyError):
                continue  # valid JSON, but not an entry of the shape the audit writes: skipped

    def _show(self, entry: dict[str, Any]) -> None:
        if entry.get("kind") == "provisional-published":  # the weld verdict while the scan comes in (flows.provisional)
            self._say(f"PROVISIONAL weld verdict after pass {entry['after_pass']} ({entry['passes']} of "
                      f"{entry['of_passes']} passes): {entry.get('verdict')} (provisional/weld_verdict.json; "
                      "the final verdict follows the whole run)", final=True)
            return
        if entry.get("kind") == "provisional-mesh-published":  # the surface while the final run goes on
            closed = "watertight" if entry.get("watertight") else "not watertight"
            self._say(f"PROVISIONAL mesh after pass {entry['after_pass']} ({entry['passes']} of {entry['of_passes']} "
                      f"passes): {entry['vertices']:,} vertices, {closed} (provisional/mesh.ply; the final mesh follows "
                      "the whole run)", final=True)
            return
        if entry.get("kind") == "provisional-model-published":  # the FE model, stress and page while the final run goes on
            model = f"FE model of {entry['tetrahedra']:,} tetrahedra" if entry.get("fe_model") else "no FE model"
            factor = entry.get("hot_spot_factor")
            stress = f"hot spot factor {factor:.2f}" if factor is not None else "no stress hot spot"
            self._say(f"PROVISIONAL QA page after pass {entry['after_pass']} ({entry['passes']} of {entry['of_passes']} "
                      f"passes): {model}, {stress} (provisional/report.html; the final page follows the whole run)",
                      final=True)
            return
        count = self._counts.get(entry.get("stage"))
        if count is None:
            return
        item = None if entry.get("item") is None else str(entry["item"])
        if entry.get("kind") == "stage-failed":
            count.failed.append(item or str(entry["stage"]))
            self._say(f"{entry['stage']}{' ' + item if item else ''} FAILED: {entry.get('error', '')}")
            return
        if entry.get("kind") == "stage-recomputed":  # what the run did about damage or tampering: said here
            if entry.get("cause") == "untrusted-folder":  # every stage of the folder: said once
                if not self._untrusted:
                    self._say("the folder's audit trail did not verify when the run started: each of its stages is "
                              "set aside (.untrusted-*) and recomputed or copied from the stage cache; "
                              "`weldrecon audit verify` lists them", final=True)
                self._untrusted += 1
                return
            self._say(f"{entry['stage']}{' ' + item if item else ''}: {entry.get('reason', 'recomputed')}", final=True)
            return
        if entry.get("kind") != "stage":
            return
        cached = bool(entry.get("cached"))
        seconds = 0.0 if cached else float(((entry.get("record") or {}).get("metrics") or {}).get("seconds", 0.0))
        count.done += 1
        count.cached += cached
        count.seconds += seconds
        took = "cached" if cached else f"{seconds:.1f} s"
        if self._rich is not None:
            self._rich.update(self._bars[entry["stage"]], completed=count.done,
                              note=f"{count.cached} cached" if count.cached else f"{count.seconds:.1f} s")
        elif item is not None:
            self._say(f"{entry['stage']} {count.done}/{count.expected} {item} {took}")
        else:
            self._say(f"{entry['stage']} done {took}")
        if self._plan is not None and entry["stage"] == "denoise" and item in self._plan.pass_ids:
            self._next_pass(self._plan.pass_ids.index(item))

    def _next_pass(self, landed: int) -> None:
        """Pass ``landed`` is in: what the next pass of the plan will add (passes land in the plan's order)."""
        self._landed.add(landed)
        ids = self._plan.pass_ids
        waiting = [k for k in range(len(ids)) if k not in self._landed]
        if not waiting:
            self._say(f"all {len(ids)} passes in: the whole-sample stages follow", final=True)
            return
        k = waiting[0]
        self._say(f"next: pass {ids[k]} ({k + 1} of {len(ids)}) adds {adds_text(self._plan, k, self._landed)}",
                  final=True)

    def _say(self, text: str, *, final: bool = False) -> None:
        if self._rich is not None and not final:
            self._rich.console.print(text)
            return
        print(f"[{time.perf_counter() - self._started:7.1f} s] {text}", file=self._stream, flush=True)
