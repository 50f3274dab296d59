"""What a reconstruction checks before any work, light enough to import before Prefect and the
compute stack: a bad ``--out``, settings file, sample or Dask address is refused in well under
a second instead of after the ~4 s those imports take. ``flows.reconstruct`` runs the same checks
again inside the flow (for callers that start it directly)."""

from __future__ import annotations

import time
from pathlib import Path

from data_catalog import audit
from data_catalog.atomic import check_can_create
from data_catalog.manifests import MANIFEST_NAME
from data_catalog.textfiles import read_yaml_model
from schemas.reconstruction import ReconstructionConfig

__all__ = ["RUN_FOLDER_ENTRIES", "load_config", "check_out_dir", "check_run_folder", "check_dask_scheduler",
           "check_settings", "check_memory", "memory_needed_bytes", "memory_available", "NotEnoughMemory",
           "wait_for_file", "trail_problems"]

RUN_FOLDER_ENTRIES = {"audit", "stages", "results", "logs"}  # what a run writes into its folder
MAX_TETRAHEDRA = 30_000_000  # gmsh's HXT on 2 cores: the demo's 0.7 M take ~1 min; 30 M, most of an hour
_FILLED = 0.1  # the least of its bounding box a part fills (a T-joint's stem and base: ~0.2)
_TET_VOLUME = 1 / (6 * 2 ** 0.5)  # a regular tetrahedron's volume over its edge cubed


# The least memory a run takes, by its surface mesh's octree depth (mesh.poisson_depth), a floor
# under every run measured (peak RSS of its largest process, /usr/bin/time -v): depth 8, the ci
# six-pass subset, 0.84 GB; depth 10, the demo, 2.33 GB; depth 12, the tjoint preset 4.6 GB and the
# paper preset 8.0 GB. The floor, 0.5 GB at depth 8 and below, x1.5 a level above it (1.1 GB at 10,
# 2.5 GB at 12), stays under each of them: a run refused for it could not have finished.
MEMORY_FLOOR_BYTES = 500 * 2 ** 20
MEMORY_PER_LEVEL = 1.5
MEMORY_FLOOR_DEPTH = 8
_NO_LIMIT = 2 ** 60  # cgroup v1's "unlimited" is 2^63 - 4096 rounded to a page


class NotEnoughMemory(RuntimeError):
    """The machine (or the memory cgroup the run is in) has less memory free than the run needs."""


def load_config(path: str | Path | None) -> ReconstructionConfig:
    """The reconstruction config: defaults, overridden by a YAML file's fields."""
    if path is None:
        return ReconstructionConfig()
    return read_yaml_model(path, ReconstructionConfig, "reconstruction config")


def check_out_dir(sample: Path, out: Path) -> None:
    """Refuse a run folder that would write into the run's own inputs (the sample folder itself,
    or anything inside its pass stores, ground truth or manifest), one that is a file or cannot
    be written, and an existing folder of someone else's files. ValueError naming the folder."""
    sample, out = Path(sample).resolve(), Path(out).resolve()
    inputs = [sample / "passes", sample / "truth", sample / MANIFEST_NAME]
    if out == sample or any(out == p or p in out.parents for p in inputs):
        raise ValueError(f"--out {out}: inside the sample {sample}'s own inputs (its passes, truth or "
                         "manifest); a run must not write into what it reads: give a folder outside them")
    if out.is_dir() and not (out / audit.TRAIL).is_file():
        foreign = sorted(p.name for p in out.iterdir() if p.name not in RUN_FOLDER_ENTRIES and not p.name.startswith("."))
        if foreign:
            raise ValueError(f"--out {out}: holds {len(foreign)} thing(s) that are not a weldrecon run's "
                             f"({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}) and no audit trail; "
                             "give a new or empty folder, or an earlier run's folder")
    check_can_create(out, f"--out {out}", hint="give --out a folder you can write (without --out, the run folder is "
                                               "made beside the sample)")


def trail_problems(out: Path, trail_head: str | None) -> list[str]:
    """What is wrong with the folder's trail before a run appends to it (chain, stage folders and
    results no entry records, the head kept outside it), short of re-hashing the artefacts: a run
    appending to a trail that was cut or edited must not make it verify again. A killed run's
    missing end and a damaged tail (set aside and recorded by the next write) are left out."""
    if not (out / audit.TRAIL).is_file():
        return [f"the trail holds no entry with hash {trail_head[:12]}…, which the catalog recorded (the trail "
                "is gone)"] if trail_head else []
    heads = {trail_head: "the catalog"} if trail_head else None
    return [str(p) for p in audit.verify_trail(out, artefacts=False, heads=heads)
            if p.kind not in ("unreadable", "unfinished-run")]


def check_run_folder(out: Path, sample_id: str) -> None:
    """Refuse a run folder that holds another sample's runs (its audit trail's run-started entries
    name another sample id): a renamed sample, or a reused ``--out``, would replace that sample's
    published results and mix two samples in one trail. ValueError naming both."""
    try:
        entries = audit.read_trail(out)
    except FileNotFoundError:
        return
    others = sorted({str(e["sample_id"]) for e in entries if e.get("kind") == "run-started" and e.get("sample_id")}
                    - {sample_id})
    if others:
        raise ValueError(f"--out {out}: holds the runs of sample {', '.join(others)} (its audit trail), not of "
                         f"{sample_id}; a run folder belongs to one sample (was the sample renamed, or its folder "
                         "reused?): give another --out")


def check_dask_scheduler(address: str, timeout_s: float = 5.0) -> None:
    """A Dask scheduler address (``tcp://host:port`` or ``host:port``) that answers; ValueError
    naming it and why not (before any work, instead of a client's traceback after a long wait)."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        host, port = parts.hostname, parts.port or 8786
    except ValueError as exc:  # a port that is not a number
        raise ValueError(f"dask {address!r}: not a scheduler address ({exc}); expected tcp://host:port or local:N") from None
    if parts.scheme != "tcp" or not host:
        raise ValueError(f"dask {address!r}: not a scheduler address; expected tcp://host:port or local:N")
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise ValueError(f"dask {address!r}: no Dask scheduler answers at {host}:{port} ({exc.strerror or exc}); "
                         "start one (dask scheduler) or give local:N for worker processes here") from None
    why = _dask_identity(f"tcp://{host}:{port}", timeout_s)
    if why is not None:  # something listens there, but not a scheduler: a client would hang or read garbage
        raise ValueError(f"dask {address!r}: something answers at {host}:{port}, but not a Dask scheduler ({why}); "
                         "expected the address of one (dask scheduler prints it) or local:N")


def _dask_identity(address: str, timeout_s: float) -> str | None:
    """None when a Dask scheduler at ``address`` answers its handshake and an identity request
    within ``timeout_s`` (each step), else why not, in words. A server of another protocol is
    never read as Dask's (its first bytes, taken for a frame length, asked for exabytes)."""
    import asyncio
    import concurrent.futures

    from distributed.comm import connect

    async def probe():
        comm = await asyncio.wait_for(connect(address, timeout=timeout_s), timeout_s + 1)
        try:
            await asyncio.wait_for(comm.write({"op": "identity", "reply": True}), timeout_s)
            return await asyncio.wait_for(comm.read(), timeout_s)
        finally:
            comm.abort()

    try:  # in a thread of its own: the caller may be inside a running event loop (a flow)
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            reply = pool.submit(asyncio.run, probe()).result()
    except (TimeoutError, asyncio.TimeoutError):
        return f"no Dask handshake within {timeout_s:g} s"
    except (MemoryError, OverflowError, ValueError):
        return "its reply is not Dask's protocol"
    except Exception as exc:  # distributed's CommClosedError and the like: the other side hung up
        return f"{type(exc).__name__}: {exc}"[:200]
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        return f"it says it is {reply.get('type') if isinstance(reply, dict) else type(reply).__name__}, not a Scheduler"
    return None


def wait_for_file(path: Path, *, timeout_s: float, what: str, ready=None, poll_s: float = 0.5) -> None:
    """Wait until ``path`` exists (and ``ready(path)`` holds, when given); TimeoutError naming
    ``what`` after ``timeout_s`` seconds."""
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and (ready is None or ready(path))):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: {path} did not appear (complete) within {timeout_s:g} s")
        time.sleep(poll_s)


def check_settings(manifest, config: ReconstructionConfig) -> None:
    """Refuse, before any work, settings the sample (``manifest``) cannot be run with
    (``_check_model_size``, ``_check_weld_steps``: ValueError naming the field) and a run the
    machine cannot hold (``check_memory``: NotEnoughMemory)."""
    if manifest.specimen is not None:  # a sample of imported scans declares no part to count from
        _check_model_size(manifest.specimen.bounds_mm(), config)
    _check_weld_steps(manifest.weld_lines(), config)
    check_memory(config)


def memory_needed_bytes(config: ReconstructionConfig) -> int:
    """The least memory a run with these settings takes (``MEMORY_FLOOR_BYTES``, by the octree depth)."""
    levels = max(0, config.mesh.poisson_depth - MEMORY_FLOOR_DEPTH)
    return int(MEMORY_FLOOR_BYTES * MEMORY_PER_LEVEL ** levels)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return _NO_LIMIT if text == "max" else int(text) if text.isdigit() else None


def _cgroup_memory() -> tuple[int, int, str] | None:
    """(limit, in use, where) of the memory cgroup this process is in (v1 or v2), in bytes, the
    page cache it could drop not counted as in use; None without a limit."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if "memory" in controllers.split(","):  # v1
            base = Path("/sys/fs/cgroup/memory") / path.lstrip("/")
            limit, usage = _read_int(base / "memory.limit_in_bytes"), _read_int(base / "memory.usage_in_bytes")
            cache_key = "total_inactive_file"
        elif controllers == "" and Path("/sys/fs/cgroup/cgroup.controllers").exists():  # v2
            base = Path("/sys/fs/cgroup") / path.lstrip("/")
            limit, usage = _read_int(base / "memory.max"), _read_int(base / "memory.current")
            cache_key = "inactive_file"
        else:
            continue
        if limit is None or usage is None or limit >= _NO_LIMIT:
            return None
        try:
            stat = dict(row.split() for row in (base / "memory.stat").read_text().splitlines() if len(row.split()) == 2)
            usage -= int(stat.get(cache_key, 0))
        except (OSError, ValueError):
            pass
        return limit, max(0, usage), f"the memory cgroup {path}'s limit {limit / 2 ** 30:.1f} GB"
    return None


def memory_available() -> tuple[int, str]:
    """(bytes, where): the memory a run can still take: the machine's available memory
    (/proc/meminfo MemAvailable), or less where the memory cgroup this process is in has less
    left under its limit."""
    available, where = None, "the machine"
    try:
        for row in Path("/proc/meminfo").read_text().splitlines():
            if row.startswith("MemAvailable:"):
                available = int(row.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    group = _cgroup_memory()
    if group is not None:
        limit, used, named = group
        if available is None or limit - used < available:
            available, where = max(0, limit - used), f"{named}, {used / 2 ** 30:.1f} GB of it in use"
    return (available if available is not None else _NO_LIMIT), where


def check_memory(config: ReconstructionConfig) -> None:
    """Refuse, before any work, a run the machine cannot hold: less memory available
    (``memory_available``) than the least a run with these settings takes (``memory_needed_bytes``).
    NotEnoughMemory with both figures."""
    needed = memory_needed_bytes(config)
    available, where = memory_available()
    if available < needed:
        raise NotEnoughMemory(
            f"not enough memory for this run: it needs at least {needed / 2 ** 30:.1f} GB (mesh.poisson_depth "
            f"{config.mesh.poisson_depth}; no run measured at that depth took less), {available / 2 ** 30:.1f} GB is "
            f"available ({where}); give it more memory or a lower mesh.poisson_depth")


def _check_model_size(bounds_mm, config: ReconstructionConfig) -> None:
    """A volume.size_mm that would fill the part with more tetrahedra than ``MAX_TETRAHEDRA``,
    counted low (the part filling a tenth of its bounding box ``bounds_mm``, (min corner, max
    corner) mm, every element at size_mm, the largest it may be), refused: such a run would mesh
    for hours and then not fit in memory."""
    extent = [hi - lo for lo, hi in zip(*bounds_mm)]
    size = config.volume.size_mm
    count = _FILLED * extent[0] * extent[1] * extent[2] / (_TET_VOLUME * size ** 3)
    if count > MAX_TETRAHEDRA:
        box = " x ".join(f"{e:g}" for e in extent)
        raise ValueError(f"volume.size_mm {size:g}: the part ({box} mm) would take at least {count:.2g} tetrahedra "
                         f"at that size; expected a size giving at most {MAX_TETRAHEDRA:,} (the weld and its toes "
                         "are graded finer by weld_size_mm and toe_size_mm on their own)")


def _check_weld_steps(weld_lines, config: ReconstructionConfig) -> None:
    """A weld.section_step_mm that leaves a weld line (``weld_lines``, the manifest's, polylines
    in mm) without a section, refused: longer than the line less its end margins (the run said
    "0 of 0 sections measured, fail"), naming the lines."""
    import numpy as np

    w = config.weld
    short = []
    for line in weld_lines:
        pts = np.asarray(line.points_mm, np.float64)
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
        if w.section_step_mm > length - 2 * w.end_margin_mm:
            short.append(f"{line.name} {length:g} mm")
    if short:
        lines = "s" if len(short) > 1 else ""
        raise ValueError(f"weld.section_step_mm {w.section_step_mm:g}: longer than the weld line{lines} less the end "
                         f"margins (weld.end_margin_mm {w.end_margin_mm:g} at each end): {', '.join(short)}; expected a "
                         "step that gives every line its sections")

