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
           "check_settings", "wait_for_file", "trail_problems"]

RUN_FOLDER_ENTRIES = {"audit", "stages", "results", "logs"}  # what a run writes into its folder
MAX_TETRAHEDRA = 30_000_000  # gmsh's HXT on 2 cores: the demo's 0.7 M take ~1 min; 30 M, most of an hour
_FILLED = 0.1  # the least of its bounding box a part fills (a T-joint's stem and base: ~0.2)
_TET_VOLUME = 1 / (6 * 2 ** 0.5)  # a regular tetrahedron's volume over its edge cubed


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
    (``_check_model_size``, ``_check_weld_steps``). ValueError naming the field."""
    if manifest.specimen is not None:  # a sample of imported scans declares no part to count from
        _check_model_size(manifest.specimen.bounds_mm(), config)
    _check_weld_steps(manifest.weld_lines(), config)


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

