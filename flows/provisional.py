"""The weld verdict while the scan is still coming in (``reconstruct --follow``): provisional, from
a problem that grows with the scan, published as soon as it is known and never in ``results/``.

Each pass that lands (its stages ``denoise`` and ``targets`` done) is added to what the passes
before it solved, in a thread beside the flow's own work:

- the target registration of the passes landed so far (stage ``registration`` on them, in
  ``provisional/stages``: the common frame is the first pass's, as in the whole run; while the
  setups cannot be matched yet, the first setup's passes alone: a verdict on its weld lines);
- the new passes' poses refined on targets and overlapping surfaces against the passes already
  solved, those held (``tasks.refine.refine_poses(free=...)``: the last pass of a 32-pass scan in
  about 1/14 of the whole problem's time, ``bench/bench_growing_refine.py``); after a verdict, when
  nothing waits and the last such solve's time fits before the next pass is due (its planned
  duration at the pace the passes land), every pass is solved again together, warm (passes only
  ever added alone drift: 82 um worst on demo against 29);
- each pass's points within the weld's reach of its lines (``weld.reach_mm`` and the placement
  tolerance) and inside the part's drawing box, summed per ``merge.cell_mm`` cell once, with the
  pose it had then (``tasks.merge.cell_sums``; no coarse cells, no fixture; summed again only where
  a later solve moves the pass by more than a quarter cell);
- stage ``weld``'s own body on those points: the verdict, published to
  ``provisional/weld_verdict.json`` (marked provisional, with the passes it holds and what each
  part of its step took), an audit entry ``provisional-published``, a Prefect artifact and a line
  on the terminal. A verdict is made after the last pass, after each setup's last pass, and after
  any other pass where the last verdict's time fits before the next pass is due, so that the one
  the lab waits for, after the last pass, does not wait behind a verdict between passes;
- after the last pass's verdict, the provisional mesh: each pass's points in the part's drawing box,
  summed per coarse cell (``merge.cell_mm`` x ``merge.coarse_factor``) from the same read as its
  weld cells as it is added (the last pass's after its verdict; a pass moved since, between steps
  while no pass waits), combined, and stage mesh's screened Poisson two octree levels coarser:
  ``provisional/mesh.ply`` with ``mesh.json`` beside it (marked provisional: the passes, the depth,
  what it took), an audit entry ``provisional-mesh-published``, a Prefect artifact and a line on
  the terminal;
- then the provisional FE model, stress and QA page (``_model``): the whole run's stages export,
  volume, stress, report and qa_report on the grown poses, the weld's cells (with the mesh's coarse
  cells beyond the weld's reach) and the provisional mesh, in ``provisional/stages``; the page as
  ``provisional/report.html`` (marked PROVISIONAL), the deliverables and ``model.json`` beside it,
  an audit entry ``provisional-model-published``, a Prefect artifact and a line on the terminal.

The final results are the whole run's, made as if the scan had been finished when the run started
(the same bytes): the provisional verdict never feeds them, and the run's ``run-finished`` entry
follows an entry ``provisional-superseded``.
"""

from __future__ import annotations

import contextvars
import html
import json
import queue
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog import audit
from data_catalog.atomic import atomic_write_text
from data_catalog.hashing import sha256_file, sha256_tree
from data_catalog.stages import StageStore
from flows.stages import StageContext, StageRef, run_stage, stage
from flows.stages.contracts import block_rows, map_in_order, zarr_array
from flows.stages.merge import BLOCK_WORKERS
from flows.stages.outputs import (CLOUD, MESH, QA_REPORT, REFINE_SUMMARY, REFINED, REGISTRATION, SPECIMEN, STRESS_SUMMARY,
                                  VOLUME_SUMMARY, WELD_GEOMETRY, WELD_TOES, Mesh, RefinedPoses, SpecimenCloud)
from flows.stages.placement import T_common_specimen
from flows.stages.refine import pass_surface_sample, refine_arguments, target_pairs
from schemas.manifest import PassEntry, SampleManifest
from schemas.reconstruction import ReconstructionConfig
from schemas.stage_documents import RefineSummary
from tasks.frames import apply
from tasks.merge import CellSums, cell_sums, combine_cell_sums, transform_measured
from tasks.mesh import SurfaceResult, mesh_report, screened_poisson, write_mesh
from tasks.refine import NothingToRefine, SurfaceSample, refine_poses
from tasks.single_setup import inside_drawing_box
from tasks.volume_mesh import largest_piece
from tasks.weld_zone import weld_zone

MODEL_TIMEOUT_S = 120.0
"""The seconds of CPU time gmsh (each try) and CalculiX (each solve) get in the provisional FE model
(``tasks.volume_mesh.run_limited``: CPU time, so that a busy machine only makes them wait): on the
paper preset its gmsh took ~33 s, its whole volume stage 73 s (bench/README.md)."""

__all__ = ["MESH_NAME", "MESH_RECORD", "MODEL_RECORD", "MODEL_TIMEOUT_S", "PAGE_NAME", "PROVISIONAL", "VERDICT_NAME", "ProvisionalWeld",
           "mark_provisional", "subset_manifest"]

PROVISIONAL = "provisional"  # the run folder's subfolder
VERDICT_NAME = "weld_verdict.json"
MESH_NAME = "mesh.ply"  # the provisional surface, and what it is made of beside it
MESH_RECORD = "mesh.json"
PAGE_NAME = "report.html"  # the provisional QA page, the FE model and stress files beside it
MODEL_RECORD = "model.json"
MODEL_STAGES = ("export", "volume", "stress", "report", "qa_report")  # the whole run's, on the provisional inputs
_BOX_MARGIN_MM = 2.0  # the drawing box grown beyond the placement tolerance (as stage segment)


def _mesh_cell_mm(config: ReconstructionConfig) -> float:
    """The provisional mesh's cells: stage merge's coarse cells (where the surface is flat)."""
    return float(config.merge.cell_mm * config.merge.coarse_factor)


def _artifact(title: str, key: str, rows: list[tuple[str, Any]]) -> None:
    """A Prefect markdown artifact of the flow run: ``title`` over a table of ``rows``, marked as
    made while the scan came in. A convenience: the files and the trail hold what it shows."""
    try:
        from prefect.artifacts import create_markdown_artifact

        table = "\n".join(f"| {k} | {v} |" for k, v in rows)
        create_markdown_artifact(markdown=f"## {title}\n\n| | |\n|---|---|\n{table}\n", key=key,
                                 description="provisional: made while the scan came in")
    except Exception:  # noqa: BLE001 - never in the way of the run
        pass


def mark_provisional(page: str, words: str) -> str:
    """A QA page marked provisional: its title begins PROVISIONAL and a banner saying ``words``
    opens its body (the stage draws the page as the final one; the mark is the provisional
    thread's, so it cannot reach a final page)."""
    title, body = "<title>", "<body>\n"
    if title not in page or body not in page:
        raise ValueError("the QA page has no <title> or <body> to mark provisional (not made by this version?)")
    banner = (f'<p class="bad" id="provisional" style="border:2px solid #a31f1f;padding:0.6em">PROVISIONAL: '
              f'{html.escape(words)}.</p>\n')
    return page.replace(title, title + "PROVISIONAL ", 1).replace(body, body + banner, 1)


def _folder_ref(name: str, folder: Path, key: str, metrics: dict[str, Any]) -> StageRef:
    """A stage ref for outputs the provisional thread wrote itself into ``folder`` (every entry in
    it an output, hashed as a stage's), to run the whole run's later stages on."""
    outputs = {p.name: sha256_tree(p) for p in sorted(Path(folder).iterdir()) if not p.name.startswith(".")}
    return StageRef(stage=name, item=None, key=key, path=str(folder), outputs=outputs, cached=False, metrics=metrics)


def subset_manifest(manifest: SampleManifest, pass_ids: set[str]) -> SampleManifest:
    """``manifest`` with only the passes ``pass_ids`` (setups left without a pass dropped)."""
    setups = [s.model_copy(update={"passes": [p for p in s.passes if p.pass_id in pass_ids]}) for s in manifest.setups]
    return manifest.model_copy(update={"setups": [s for s in setups if s.passes]})


def _joined(parts: list[CellSums]) -> CellSums:
    """Partial sums one after the other, in order (``combine_cell_sums`` adds equal keys)."""
    if not parts:
        return CellSums(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    return CellSums(*(np.concatenate([getattr(s, f) for s in parts]) for f in ("keys", "counts", "point_sums", "normal_sums")))


@dataclass
class _Landed:
    entry: PassEntry
    denoise: Any  # a future of its StageRef
    targets: Any


@dataclass
class _State:
    order: list[str] = field(default_factory=list)  # the passes landed, the robot's order
    denoise: dict[str, StageRef] = field(default_factory=dict)
    targets: dict[str, StageRef] = field(default_factory=dict)
    samples: dict[str, SurfaceSample] = field(default_factory=dict)
    T: dict[str, np.ndarray] = field(default_factory=dict)  # the grown poses, common frame
    sums: dict[str, CellSums] = field(default_factory=dict)  # each pass's cells in the weld's reach
    coarse: dict[str, CellSums] = field(default_factory=dict)  # each pass's cells of the whole part (the mesh's)
    joint_after: int = 0  # passes landed at the last joint solve
    joint_seconds: float = 0.0  # what it took
    add_seconds: float = 0.0  # what the last passes' adding took
    verdict_seconds: float = 0.0  # what the last verdict took (its points combined, the weld measured)


@dataclass
class _Built:
    """A verdict's stage folder (``provisional/weld/<key>``: the weld stage's outputs, its inputs
    ``refine`` and ``segment`` beside them), its metrics and the weld cells it measured."""

    key: str
    folder: Path
    weld_metrics: dict[str, Any]
    points_mm: np.ndarray  # the weld's reach, per merge.cell_mm cell
    normals: np.ndarray


@dataclass
class _Surface:
    """The provisional mesh and the coarse cells it was made from."""

    points_mm: np.ndarray
    normals: np.ndarray
    result: SurfaceResult
    record: dict[str, Any]


class ProvisionalWeld:
    """The provisional weld verdict of a followed scan (module description). ``landed`` is called
    by the flow for each pass as its per-pass stages are submitted; ``close`` once the last has
    landed, before the whole-sample stages start (the passes landed worked through first). Never
    raises into the flow: a provisional step that fails is logged and the next pass tries again."""

    def __init__(self, *, sample: Path, out: Path, manifest: SampleManifest, config: ReconstructionConfig, log) -> None:
        self.sample, self.out, self.manifest, self.config, self.log = sample, out, manifest, config, log
        self.total = len(manifest.passes())
        self.store = StageStore(out / PROVISIONAL, shared=False)
        self.state = _State()
        self._placed = None  # the part's placement, drawing box and its margin, as the last step had them
        self._zone = None  # the weld's reach, as the last step had it (common frame)
        self._built: _Built | None = None  # the last verdict's stage folder and what it was made of
        self.published: list[dict[str, Any]] = []  # the verdicts published
        self.meshes: list[dict[str, Any]] = []  # the provisional meshes published
        self.models: list[dict[str, Any]] = []  # the provisional FE models, stresses and QA pages published
        self._queue: queue.Queue = queue.Queue()
        self._landed_at: dict[str, float] = {}
        self._stop = threading.Event()
        context = contextvars.copy_context()  # the flow run's: Prefect artifacts from the thread
        self._thread = threading.Thread(target=context.run, args=(self._work,), name="provisional-weld", daemon=True)
        self._thread.start()

    @property
    def measurable(self) -> bool:
        return self.manifest.weld is not None and any(s.T_world_specimen_nominal is not None for s in self.manifest.setups)

    def landed(self, entry: PassEntry, denoise, targets) -> None:
        self._landed_at[entry.pass_id] = time.monotonic()
        self._queue.put(_Landed(entry, denoise, targets))

    def close(self, *, wait: bool = True) -> None:
        """``wait``: the passes landed so far are worked through first (the last pass's verdict and
        the provisional mesh, begun when it landed, end long before a whole run's stages on any real
        scan; the trail then always says which provisional results the final ones supersede).
        Otherwise (the run is being stopped) stop after the step in progress, without waiting for
        it: the thread is a daemon, its step's files are written atomically."""
        if not wait:
            self._stop.set()
        self._queue.put(None)
        if wait:
            self._thread.join()

    # --- the worker thread ---------------------------------------------------------------------------------------

    def _work(self) -> None:
        while not self._stop.is_set():
            while self._queue.empty() and not self._stop.is_set() and self._coarse_one():
                pass  # the provisional mesh's cells, a pass at a time, only while no pass waits
            item = self._queue.get()
            if item is None:
                return
            batch, closing = [item], False
            while True:  # every pass landed meanwhile: one step for all of them
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    closing = True
                    break
                batch.append(more)
            try:
                self._step(batch)
            except Exception as exc:  # noqa: BLE001 - provisional: the final run decides, this one only tells early
                self.log.warning("provisional weld verdict after pass %s not made: %s", batch[-1].entry.pass_id, exc)
            if closing:
                return

    def _step(self, batch: list[_Landed]) -> None:
        st, rc = self.state, self.config.refine
        done_before = self._setups_landed()
        for item in batch:
            pid = item.entry.pass_id
            st.denoise[pid], st.targets[pid] = item.denoise.result(), item.targets.result()
            st.samples[pid] = pass_surface_sample(self.manifest, item.entry, st.denoise[pid], rc)
            st.order.append(pid)
        if not self.measurable or self._stop.is_set() or len(st.order) < 2:  # a lone pass: nothing to register
            return
        t0 = time.perf_counter()
        self._phases: dict[str, float] = {}
        last = batch[-1].entry.pass_id
        registered = self._registered(set(st.order), last)
        if registered is None:
            return
        manifest, ids, reg, reg_ref = registered
        t_add = time.perf_counter()
        self._phases["registration"] = t_add - t0
        T = self._grown(ids, reg)
        st.add_seconds = self._phases["poses"] = time.perf_counter() - t_add
        if self._stop.is_set():
            return
        placed = T_common_specimen(manifest, T)
        if not placed:
            return
        t1 = time.perf_counter()
        self._cells(manifest, ids, T, placed[0], coarse=len(ids) < self.total)
        self._phases["cells"] = time.perf_counter() - t1
        final = len(ids) == self.total
        # the lab waits for the last pass's verdict: a verdict between passes only where it does not
        # delay it, and at each setup's end (the first tells what a verdict costs)
        if final or self._setups_landed() > done_before or not self.published or self._fits(st.verdict_seconds):
            t2 = time.perf_counter()
            self._verdict(manifest, ids, reg, T, last, t0)
            st.verdict_seconds = time.perf_counter() - t2
        if final and not self._stop.is_set():  # then the mesh the lab looks at next
            surface = None
            try:
                while self._coarse_one():
                    pass
                surface = self._mesh(ids, last)
            except Exception as exc:  # noqa: BLE001 - provisional: the final mesh follows
                self.log.warning("provisional mesh after pass %s not made: %s", last, exc)
            if surface is not None and self._built is not None and not self._stop.is_set():  # then the model and the page
                try:
                    self._model(manifest, ids, reg_ref, last, surface)
                except Exception as exc:  # noqa: BLE001 - provisional: the final model and page follow
                    self.log.warning("provisional FE model, stress and QA page after pass %s not made: %s", last, exc)
        if final:  # the last verdict of the scan: its memory to the final run
            self.state = _State(order=st.order)
        elif len(ids) - st.joint_after >= 4 and self._fits(
                st.joint_seconds * len(ids) / st.joint_after if st.joint_after else 10.0 * st.add_seconds):
            self._joint(ids, reg)

    def _setups_landed(self) -> int:
        landed = set(self.state.order)
        return sum(all(p.pass_id in landed for p in s.passes) for s in self.manifest.setups)

    def _registered(self, landed: set[str], last: str):
        """(manifest, pass ids, registration, its stage ref) of the landed passes; while the setups cannot be
        matched yet, of the first setup's passes alone (a verdict on its weld lines); None: neither."""
        st = self.state
        first = {p.pass_id for p in self.manifest.setups[0].passes} & landed
        tries = [landed] + ([first] if len(first) >= 2 and first != landed else [])
        for k, passes in enumerate(tries):
            manifest = subset_manifest(self.manifest, passes)
            ids = [e.pass_id for _, e in manifest.passes()]
            try:
                ref = run_stage(stage("registration"), store=self.store, sample_dir=self.sample, manifest=manifest,
                                config=self.config, inputs={"targets": [st.targets[p] for p in ids]})
            except Exception as exc:  # noqa: BLE001 - e.g. the second setup not matched yet: wait for more passes
                self.log.info("provisional registration after pass %s (%d of %d landed) %s: %s", last, len(ids),
                              self.total, "waits" if k == len(tries) - 1 else "falls back to the first setup",
                              str(exc).splitlines()[0])
                continue
            return manifest, ids, REGISTRATION.read(ref), ref
        return None

    def _grown(self, ids: list[str], reg, *, joint: bool = False) -> np.ndarray:
        """The landed passes' poses: those solved before held, the new ones added to them;
        ``joint``: every pass solved again together, warm, from there."""
        st, rc = self.state, self.config.refine
        T = np.array([st.T.get(p, reg.T_common_pass[k]) for k, p in enumerate(ids)])
        new = [k for k, p in enumerate(ids) if p not in st.T and k > 0]
        E, A, B, sigma = target_pairs(reg, rc)
        kw = dict(refine_arguments(rc), target_sigma_mm=sigma)
        samples = [st.samples[p] for p in ids]
        if rc.enabled:
            try:
                if new:
                    T = refine_poses(samples, T, E, A, B, **kw, free=new).T_common_pass
                if joint:
                    T = refine_poses(samples, T, E, A, B, **kw, warm=True).T_common_pass
            except NothingToRefine:  # nothing shared yet: the target poses stand
                pass
        for k, p in enumerate(ids):
            if p in st.T and len(samples[k].points_mm):
                moved = np.abs(apply(T[k], samples[k].points_mm) - apply(st.T[p], samples[k].points_mm)).max()
                if moved > 0.25 * self.config.merge.cell_mm:  # its cells again (a few um: kept as they are)
                    st.sums.pop(p, None)
                    st.coarse.pop(p, None)
            st.T[p] = T[k]
        return T

    def _fits(self, cost_s: float) -> bool:
        """Whether work of ``cost_s`` seconds ends before the next pass is due: nothing waits, and
        it fits (with half again) in what is left of the next pass's scan at the pace the passes land
        (the plan's durations)."""
        st = self.state
        if not self._queue.empty() or len(st.order) < 2:
            return False
        plan = {e.pass_id: e for _, e in self.manifest.passes()}
        order = [e.pass_id for _, e in self.manifest.passes()]
        a, b = st.order[-2], st.order[-1]
        if order.index(b) + 1 >= len(order):
            return False
        planned = max(plan[b].duration_s, 1e-3)
        pace = max(self._landed_at[b] - self._landed_at[a], 0.0) / planned  # seconds per planned second
        due = self._landed_at[b] + pace * plan[order[order.index(b) + 1]].duration_s
        return time.monotonic() + 1.5 * cost_s < due

    def _joint(self, ids: list[str], reg) -> None:
        st = self.state
        t0 = time.perf_counter()
        self._grown(ids, reg, joint=True)
        st.joint_after, st.joint_seconds = len(ids), time.perf_counter() - t0

    def _cells(self, manifest: SampleManifest, ids: list[str], T: np.ndarray, placed, *, coarse: bool) -> None:
        """Each landed pass's cells within the weld's reach, where it has none yet (new, or moved);
        ``coarse``: its cells for the provisional mesh too, from the same read (not in the last
        pass's step: its verdict first, then those)."""
        st, config = self.state, self.config
        setup, T_part = placed
        tolerance = float(setup.placement_tolerance_mm)
        zone = weld_zone([apply(T_part, np.asarray(line.points_mm, np.float64)) for line in manifest.weld_lines()],
                         config.weld.reach_mm + tolerance)
        grow = np.full(3, tolerance + _BOX_MARGIN_MM)
        bounds = manifest.specimen.bounds_mm() if manifest.specimen is not None else None
        self._placed, self._zone = (T_part, bounds, grow), zone
        for k, p in enumerate(ids):
            if p not in st.sums:
                want = coarse and p not in st.coarse
                st.sums[p], found = self._sums(st.denoise[p], T[k], T_part, bounds, grow, zone=zone, coarse=want)
                if want:
                    st.coarse[p] = found

    def _coarse_one(self) -> bool:
        """One landed pass's cells for the provisional mesh (all its points in the drawing box, per
        coarse cell, with its pose now), the first in the robot's order that has none; False: none
        left (or no pose or placement yet). Never on the way of a verdict: between steps while no
        pass waits, and after the last verdict."""
        st, placed = self.state, self._placed
        todo = [p for p in st.order if p in st.T and p not in st.coarse]
        if placed is None or not todo:
            return False
        p = todo[0]
        try:
            st.coarse[p] = self._sums(st.denoise[p], st.T[p], *placed, zone=None, coarse=True)[1]
        except Exception as exc:  # noqa: BLE001 - provisional: the mesh goes without this pass
            self.log.warning("provisional mesh: pass %s left out: %s", p, exc)
            st.coarse[p] = _joined([])
        return True

    def _verdict(self, manifest: SampleManifest, ids: list[str], reg, T: np.ndarray, last: str, t0: float) -> None:
        st, config = self.state, self.config
        t1 = time.perf_counter()
        parts = [st.sums[p] for p in ids if len(st.sums[p].keys)]
        if not parts:
            return
        merged = combine_cell_sums(_joined(parts), cell_mm=config.merge.cell_mm)
        normals = np.nan_to_num(merged.normals)
        n = len(merged.points_mm)
        key = f"after-{len(ids):03d}-{last}"
        build = self.store.root / "weld" / key
        build.mkdir(parents=True, exist_ok=True)
        inputs = {}
        for name, file, value in (
                ("refine", REFINED, RefinedPoses(T_common_pass=T, track_positions_mm=reg.track_positions_mm,
                                                 specimen_track=reg.specimen_track,
                                                 target_residual_mm=np.zeros(0))),
                ("segment", SPECIMEN, SpecimenCloud(points=merged.points_mm, normals=normals.astype(np.float32),
                                                    fine=np.ones(n, bool), measured=np.ones(n, bool)))):
            folder = build / name
            folder.mkdir(exist_ok=True)
            file.write(folder, value)
            inputs[name] = StageRef(stage=name, item=None, key=key, path=str(folder), outputs={file.name: ""}, cached=False)
        t2 = time.perf_counter()
        self._phases["combine"] = t2 - t1
        context = StageContext(out=build, sample_dir=self.sample, manifest=manifest, config=config,
                               settings=config.weld, entry=None, inputs=inputs)
        metrics = stage("weld").body_for(manifest)(context)
        self._phases["weld"] = time.perf_counter() - t2
        self._built = _Built(key=key, folder=build, weld_metrics=dict(metrics), points_mm=merged.points_mm,
                             normals=normals.astype(np.float32))
        weld = WELD_GEOMETRY.read_path(build / WELD_GEOMETRY.name)
        seconds = time.perf_counter() - t0
        document = {"provisional": True, "sample_id": self.manifest.sample_id, "after_pass": last,
                    "passes": len(ids), "of_passes": self.total, "points": n,
                    "poses": "grown with the scan (flows.provisional): not the final refinement",
                    "seconds": {"step": round(seconds, 1), **{k: round(v, 1) for k, v in self._phases.items()}},
                    "weld": json.loads(weld.model_dump_json())}
        path = self.out / PROVISIONAL / VERDICT_NAME
        atomic_write_text(path, json.dumps(document, indent=1) + "\n")
        summary = weld.summary
        verdict = getattr(summary, "verdict", None) if summary is not None else None
        entry = audit.append(self.out, "provisional-published", sample_id=self.manifest.sample_id, after_pass=last,
                             passes=len(ids), of_passes=self.total, verdict=verdict,
                             artefacts={f"{PROVISIONAL}/{VERDICT_NAME}": sha256_file(path)})
        self.published.append({"after_pass": last, "passes": len(ids), "verdict": verdict, "seq": entry["seq"],
                               "time": time.time()})
        self.log.info("provisional weld verdict after pass %s (%d of %d passes): %s (%.1f s) - provisional, "
                      "the final verdict follows the whole run", last, len(ids), self.total, verdict, seconds)
        self._verdict_artifact(document, verdict)

    def _mesh(self, ids: list[str], last: str) -> _Surface | None:
        """The provisional surface: screened Poisson (stage mesh's settings, two octree levels
        coarser) on every landed pass's points in the part's drawing box, summed per coarse cell with
        the grown poses; ``provisional/mesh.ply`` and ``mesh.json`` beside it (marked provisional),
        an audit entry ``provisional-mesh-published``, a Prefect artifact and a terminal line."""
        st, config = self.state, self.config
        t0 = time.perf_counter()
        parts = [st.coarse[p] for p in ids if p in st.coarse and len(st.coarse[p].keys)]
        if not parts:
            return None
        merged = combine_cell_sums(_joined(parts), cell_mm=_mesh_cell_mm(config))
        normals = np.nan_to_num(merged.normals)
        ok = np.linalg.norm(normals, axis=1) > 0
        m = config.mesh
        depth = max(m.poisson_depth - 2, 6)
        surface = screened_poisson(merged.points_mm[ok], normals[ok].astype(np.float64), depth=depth,
                                   samples_per_node=m.samples_per_node, point_weight=m.point_weight,
                                   scale=m.poisson_scale)
        folder = self.out / PROVISIONAL
        folder.mkdir(parents=True, exist_ok=True)
        partial = folder / f".{MESH_NAME}.partial.ply"
        write_mesh(partial, surface.vertices, surface.triangles)
        partial.replace(folder / MESH_NAME)
        r = surface.report
        seconds = time.perf_counter() - t0
        document = {"provisional": True, "sample_id": self.manifest.sample_id, "after_pass": last,
                    "passes": len(ids), "of_passes": self.total, "points": int(ok.sum()),
                    "cell_mm": _mesh_cell_mm(config), "poisson_depth": depth,
                    "poses": "grown with the scan (flows.provisional): not the final refinement",
                    "vertices": r.n_vertices, "triangles": r.n_triangles, "watertight": r.watertight,
                    "volume_mm3": r.volume_mm3, "seconds": round(seconds, 1)}
        atomic_write_text(folder / MESH_RECORD, json.dumps(document, indent=1) + "\n")
        entry = audit.append(self.out, "provisional-mesh-published", sample_id=self.manifest.sample_id, after_pass=last,
                             passes=len(ids), of_passes=self.total, vertices=r.n_vertices, watertight=r.watertight,
                             artefacts={f"{PROVISIONAL}/{name}": sha256_file(folder / name)
                                        for name in (MESH_NAME, MESH_RECORD)})
        self.meshes.append({"after_pass": last, "passes": len(ids), "seq": entry["seq"], "time": time.time()})
        self.log.info("provisional mesh after pass %s (%d of %d passes): %d vertices, %s (%.1f s) - provisional, "
                      "the final mesh follows the whole run", last, len(ids), self.total, r.n_vertices,
                      "watertight" if r.watertight else "not watertight", seconds)
        _artifact("Provisional mesh", f"provisional-mesh-{len(ids):03d}",
                  [("PROVISIONAL", "the final mesh follows the whole run"),
                   ("after pass", f"{last} ({len(ids)} of {self.total})"), ("vertices", r.n_vertices),
                   ("watertight", r.watertight), ("octree depth", depth)])
        return _Surface(points_mm=merged.points_mm[ok], normals=normals[ok].astype(np.float32), result=surface,
                        record=document)

    def _model(self, manifest: SampleManifest, ids: list[str], reg_ref: StageRef, last: str, surface: _Surface) -> None:
        """The provisional FE model, stress and QA page: the whole run's stages ``export``,
        ``volume``, ``stress``, ``report`` and ``qa_report`` (``MODEL_STAGES``, in
        ``provisional/stages``) on what the last verdict and the provisional mesh were made of: the
        grown poses (``refine``, no surface pairs), the weld cells with the mesh's coarse cells
        beyond the weld's reach (``segment``: the part the page draws), the verdict's weld and the
        provisional surface (``mesh``); no merge (the page says so). The volume and the stress on
        two threads. Published as ``provisional/report.html`` (marked PROVISIONAL, its audit
        section the trail as it stands), the deliverables beside it under their results/ names and
        ``model.json``; an audit entry ``provisional-model-published``, a Prefect artifact and a
        terminal line."""
        from concurrent.futures import ThreadPoolExecutor

        from flows.reconstruct import audit_status
        from flows.stages.qa_audit import fill_audit
        from flows.stages.report import deliverables

        st, built, config = self.state, self._built, self.config
        # worth having only before the final model, which waits for it: gmsh and CalculiX get
        # MODEL_TIMEOUT_S of CPU time each, and a remesh that stalls keeps the surface's own triangles (gmsh's
        # patch classification stalled for 9 minutes on one provisional mesh of the demo)
        config = config.model_copy(update={
            "volume": config.volume.model_copy(update={"timeout_s": min(config.volume.timeout_s, MODEL_TIMEOUT_S),
                                                       "keep_surface_after_timeout": True}),
            "stress": config.stress.model_copy(update={"timeout_s": min(config.stress.timeout_s, MODEL_TIMEOUT_S)})})
        t0 = time.perf_counter()
        key = built.key
        folder = self.store.root / "model" / key
        if folder.exists():
            shutil.rmtree(folder)
        note = "provisional: made while the scan came in (flows.provisional)"
        # refine: the grown poses the verdict used, no surface pairs summarised
        REFINE_SUMMARY.write(built.folder / "refine", RefineSummary(method="grown with the scan (provisional)",
                                                                    surface_pairs=[], step_mm=[]))
        refine = _folder_ref("refine", built.folder / "refine", key, {"provisional": note,
                                                                       "registration_method": {p: "targets" for p in ids}})
        # segment: the weld's cells, and beyond the weld's reach the mesh's coarse cells
        beyond = ~self._zone.contains(surface.points_mm) if self._zone is not None else np.ones(len(surface.points_mm), bool)
        n_fine, n_coarse = len(built.points_mm), int(beyond.sum())
        SPECIMEN.write(folder / "segment", SpecimenCloud(
            points=np.concatenate([built.points_mm, surface.points_mm[beyond]]),
            normals=np.concatenate([built.normals, surface.normals[beyond]]),
            fine=np.concatenate([np.ones(n_fine, bool), np.zeros(n_coarse, bool)]),
            measured=np.ones(n_fine + n_coarse, bool)))
        segment = _folder_ref("segment", folder / "segment", key, {"provisional": note, "points": n_fine + n_coarse,
                                                                   "fine_points": n_fine})
        # the FE model's surface: the part, the provisional mesh's largest piece
        vertices, triangles, pieces = largest_piece(surface.result.vertices, surface.result.triangles)
        MESH.write(folder / "mesh", Mesh(vertices=vertices, triangles=triangles))
        r = mesh_report(vertices, triangles)
        mesh = _folder_ref("mesh", folder / "mesh", key, {
            "provisional": note + f"; the largest of the provisional mesh's {pieces} pieces",
            "pieces_left_out": max(pieces - 1, 0), "poisson_depth": surface.record["poisson_depth"],
            "cell_mm": surface.record["cell_mm"], "points": surface.record["points"], "vertices": r.n_vertices,
            "triangles": r.n_triangles, "watertight": r.watertight, "consistently_oriented": r.consistently_oriented,
            "boundary_edges": r.n_boundary_edges, "non_manifold_edges": r.n_non_manifold_edges,
            "volume_mm3": r.volume_mm3, "surface_area_mm2": r.surface_area_mm2})
        (folder / "merge").mkdir(parents=True, exist_ok=True)
        merge = _folder_ref("merge", folder / "merge", key, {"provisional": note + "; no merged cloud (the weld's and "
                                                                                 "the mesh's cells instead)"})
        weld = StageRef(stage="weld", item=None, key=key, path=str(built.folder),
                        outputs={f.name: sha256_tree(built.folder / f.name) for f in (WELD_GEOMETRY, WELD_TOES)},
                        cached=False, metrics=built.weld_metrics)
        refs: dict[str, Any] = {"denoise": [st.denoise[p] for p in ids], "targets": [st.targets[p] for p in ids],
                                "registration": reg_ref, "refine": refine, "merge": merge, "segment": segment,
                                "weld": weld, "mesh": mesh}
        seconds: dict[str, float] = {}

        def run(name: str) -> StageRef:
            t = time.perf_counter()
            s = stage(name)
            ref = run_stage(s, store=self.store, sample_dir=self.sample, manifest=manifest, config=config,
                            inputs={n: refs[n] for n in s.needs})
            seconds[name] = round(time.perf_counter() - t, 1)
            return ref

        with ThreadPoolExecutor(2, thread_name_prefix="provisional-model") as pool:  # the model beside the stress
            futures = {name: pool.submit(run, name) for name in ("stress", "volume")}
            refs["export"] = run("export")
            refs.update({name: f.result() for name, f in futures.items()})
        for name in ("report", "qa_report"):
            refs[name] = run(name)
        if self._stop.is_set():
            return
        # published beside the verdict and the mesh: the page marked, the deliverables under their results/ names
        out = self.out / PROVISIONAL
        files = {name: refs[src].file(source) for name, (src, source) in deliverables(self.manifest.sample_id).items()
                 if source in refs[src].outputs}
        for name, source in files.items():
            partial = out / f".{name}.partial"
            shutil.copyfile(source, partial)
            partial.replace(out / name)
        volume, stress = VOLUME_SUMMARY.read(refs["volume"]), STRESS_SUMMARY.read(refs["stress"])
        hot = stress.hot_spot if stress.made else None
        words = (f"made after pass {last} ({len(ids)} of {self.total} passes), from the scan as it came in: the grown "
                 "poses (not the final refinement), the weld's cells and the provisional mesh (two octree levels "
                 "under the final one); the final page follows the whole run and replaces this one")
        page = refs["qa_report"].file(QA_REPORT.name).read_text(encoding="utf-8")
        atomic_write_text(out / PAGE_NAME, fill_audit(mark_provisional(page, words), audit_status(self.out)))
        took = round(time.perf_counter() - t0, 1)
        document = {"provisional": True, "sample_id": self.manifest.sample_id, "after_pass": last,
                    "passes": len(ids), "of_passes": self.total,
                    "poses": "grown with the scan (flows.provisional): not the final refinement",
                    "fe_model": {"made": volume.made, "why": volume.why, "mesh_pieces_left_out": max(pieces - 1, 0),
                                 "tetrahedra": volume.solid.tetrahedra if volume.made and volume.solid else None,
                                 "element_type": volume.element_type},
                    "stress": {"made": stress.made, "why": stress.why, "sections": len(stress.sections),
                               "hot_spot": json.loads(hot.model_dump_json()) if hot is not None else None},
                    "files": sorted([*files, PAGE_NAME]),
                    "stages": {name: str(Path(ref.path).relative_to(self.out)) for name, ref in refs.items()
                               if name in MODEL_STAGES},
                    "seconds": {"step": took, **seconds}}
        atomic_write_text(out / MODEL_RECORD, json.dumps(document, indent=1) + "\n")
        entry = audit.append(self.out, "provisional-model-published", sample_id=self.manifest.sample_id,
                             after_pass=last, passes=len(ids), of_passes=self.total, fe_model=volume.made,
                             tetrahedra=document["fe_model"]["tetrahedra"], stress=stress.made,
                             hot_spot_factor=hot.factor if hot is not None else None,
                             artefacts={f"{PROVISIONAL}/{name}": sha256_file(out / name)
                                        for name in sorted([*files, PAGE_NAME, MODEL_RECORD])})
        self.models.append({"after_pass": last, "passes": len(ids), "seq": entry["seq"], "time": time.time()})
        self.log.info("provisional FE model, stress and QA page after pass %s (%d of %d passes): %s, %s (%.1f s) - "
                      "provisional, the final page follows the whole run", last, len(ids), self.total,
                      f"{document['fe_model']['tetrahedra']} tetrahedra" if volume.made else "no FE model",
                      f"hot spot factor {hot.factor:.2f}" if hot is not None else "no hot spot", took)
        _artifact("Provisional FE model, stress and QA page", f"provisional-model-{len(ids):03d}",
                  [("PROVISIONAL", "the final model, stress and page follow the whole run"),
                   ("after pass", f"{last} ({len(ids)} of {self.total})"),
                   ("FE model", document["fe_model"]["tetrahedra"] if volume.made else f"not made: {volume.why}"),
                   ("hot spot factor", f"{hot.factor:.2f}" if hot is not None else "-"),
                   ("QA page", f"{PROVISIONAL}/{PAGE_NAME}")])

    def _sums(self, ref: StageRef, T: np.ndarray, T_part: np.ndarray, bounds, grow, *, zone,
              coarse: bool) -> tuple[CellSums, CellSums | None]:
        """A pass's points within the weld's reach (``zone``; None: none wanted) and the part's
        drawing box, summed per cell; and (``coarse``) all its points in the drawing box summed per
        coarse cell (the provisional mesh's), from the same read."""
        points, normals = zarr_array(ref, CLOUD, "points"), zarr_array(ref, CLOUD, "normals")
        n, m = points.shape[:2]
        step = block_rows(m, chunk_profiles=points.chunks[0])

        def block(start: int) -> tuple[CellSums | None, CellSums | None]:
            p, q = transform_measured(points[start:start + step], normals[start:start + step], T)
            keep = np.ones(len(p), bool)
            if bounds is not None:
                keep = inside_drawing_box(p, T_frame_part=T_part, part_bounds_mm=bounds, grow_lo_mm=grow,
                                          grow_hi_mm=grow)
            rough = cell_sums(p[keep], q[keep], cell_mm=_mesh_cell_mm(self.config)) if coarse and keep.any() else None
            fine = None
            if zone is not None:
                keep &= zone.contains(p)
                if keep.any():
                    fine = cell_sums(p[keep], q[keep], cell_mm=self.config.merge.cell_mm)
            return fine, rough

        # the blocks read and summed on two threads, joined in their order: the same sums as a loop
        found = list(map_in_order(block, range(0, n, step), workers=BLOCK_WORKERS))
        fine = [f for f, _ in found if f is not None]
        rough = [r for _, r in found if r is not None]
        return _joined(fine), (_joined(rough) if coarse else None)

    def _verdict_artifact(self, document: dict[str, Any], verdict) -> None:
        summary = document["weld"].get("summary") or {}
        _artifact("Provisional weld verdict", f"provisional-weld-{document['passes']:03d}",
                  [("PROVISIONAL", "the final verdict follows the whole run"),
                   ("after pass", f"{document['after_pass']} ({document['passes']} of {document['of_passes']})"),
                   ("verdict", verdict), ("sections", summary.get("sections")), ("failing", summary.get("failing"))])
