"""Stage bodies: read inputs from the store, call ``tasks``, write outputs to the store, return a
small reference. Prefect wraps these in ``flows.reconstruct``; they hold no numerics of their own.

A reference is a plain dict: ``{"stage", "key", "path", "outputs": {name: sha256}, "cached"}``.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
import socket
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog import audit
from data_catalog.atomic import atomic_write_text
from data_catalog.hashing import sha256_file, sha256_tree
from data_catalog.passes import PassFormatError, read_pass
from data_catalog.stages import RECORD_NAME, StageStore, cache_key, load_arrays, save_arrays
from schemas.manifest import PassEntry, SampleManifest
from schemas.provenance import StageRecord
from schemas.reconstruction import ReconstructionConfig

# Imported here, in the main thread: open3d, pymeshlab and OpenCV first imported inside a
# Prefect worker thread corrupt the heap at interpreter exit (seen: malloc_consolidate abort).
from tasks.denoise import remove_statistical_outliers
from tasks.graph import register_passes
from tasks.ingest import profile_points
from tasks.merge import merge_box_grid
from tasks.refine import refine_poses, surface_sample
from tasks.registration import RegistrationError
from tasks.segment import keep_specimen_components
from tasks.surface import estimate_normals, screened_poisson, write_mesh
from tasks.targets import detect_targets

__all__ = ["Ref", "pass_hash", "cloud_stage", "targets_stage", "register_stage", "refine_stage", "merge_stage",
           "segment_stage", "surface_stage", "export_stage", "STAGE_MODULES"]

Ref = dict[str, Any]

STAGE_MODULES = {
    "cloud": ("tasks.ingest", "tasks.denoise"),
    "targets": ("tasks.ingest", "tasks.targets"),
    "register": ("tasks.matching", "tasks.registration", "tasks.graph"),
    "refine": ("tasks.refine",),
    "merge": ("tasks.merge",),
    "segment": ("tasks.segment",),
    "surface": ("tasks.surface",),
    "export": ("tasks.surface",),
}


def _code_version(stage: str, body: Callable) -> str:
    """Hash of the stage's task modules and of its body: changed code recomputes the stage."""
    import importlib

    digest = hashlib.sha256(inspect.getsource(body).encode())
    for name in STAGE_MODULES[stage]:
        digest.update(inspect.getsource(importlib.import_module(name)).encode())
    return digest.hexdigest()[:16]


def pass_hash(sample_dir: Path, entry: PassEntry) -> str:
    """The pass file's content hash; checked against the manifest's when it carries one."""
    path = Path(sample_dir) / entry.file
    if not path.exists():
        raise PassFormatError(f"pass {entry.pass_id}: pass file {path} does not exist")
    actual = sha256_tree(path)
    if entry.content_sha256 is not None and actual != entry.content_sha256:
        raise ValueError(f"pass {entry.pass_id}: {entry.file} does not match the manifest's content_sha256 "
                         f"(file changed or truncated)")
    return actual


def _run_ids() -> dict[str, str | None]:
    """The Prefect flow run and task run this stage runs in (None outside Prefect)."""
    try:
        from prefect.runtime import flow_run, task_run

        return {"flow_run_id": str(flow_run.id) if flow_run.id else None,
                "task_run_id": str(task_run.id) if task_run.id else None, "pid": os.getpid()}
    except Exception:  # noqa: BLE001 - provenance is best effort outside a run
        return {"flow_run_id": None, "task_run_id": None, "pid": os.getpid()}


def _artefacts(store: StageStore, stage: str, key: str, outputs: dict[str, str]) -> dict[str, str]:
    """Run-folder-relative path -> sha256 of a stage's outputs, for the audit trail."""
    folder = store.path(stage, key).relative_to(store.root)
    found = {(folder / name).as_posix(): digest for name, digest in outputs.items()}
    found[(folder / RECORD_NAME).as_posix()] = sha256_file(store.root / folder / RECORD_NAME)
    return found


def _run(store: StageStore, *, sample_id: str, stage: str, item: str | None, inputs: dict[str, str],
         parameters: dict[str, Any], body: Callable[[Path], dict[str, Any]], outputs: list[str],
         code_of: Callable) -> Ref:
    """Run a stage body unless the store holds its outputs (verified by hash); either way the
    stage's provenance goes into the sample's audit trail."""
    code_version = _code_version(stage, code_of)
    key = cache_key(stage if item is None else f"{stage}/{item}", inputs, parameters, code_version)
    ids = _run_ids()
    found, problem = store.verified(stage, key)
    if problem is not None:
        audit.append(store.root, "stage-recomputed", stage=stage, item=item, cache_key=key,
                     reason=f"cached outputs failed their hash check: {problem}; set aside and recomputed", **ids)
    if found is not None:
        audit.append(store.root, "stage", stage=stage, item=item, cache_key=key, cached=True,
                     record=found.model_dump(mode="json"), artefacts=_artefacts(store, stage, key, found.outputs),
                     **ids)
        return {"stage": stage, "key": key, "path": str(store.path(stage, key)), "outputs": found.outputs,
                "cached": True, "metrics": found.metrics}
    build = store.build_dir(stage)
    started = datetime.now(UTC)
    t0 = time.perf_counter()
    metrics = body(build)
    metrics["seconds"] = round(time.perf_counter() - t0, 3)
    record = StageRecord(sample_id=sample_id, stage=stage, item=item, cache_key=key, inputs=inputs,
                         outputs={name: "" for name in outputs}, parameters=parameters,
                         code_version=code_version, host=socket.gethostname(),
                         started=started, finished=datetime.now(UTC), metrics=metrics,
                         flow_run_id=ids["flow_run_id"])
    final = store.commit(build, record)
    committed = store.lookup(stage, key)
    audit.append(store.root, "stage", stage=stage, item=item, cache_key=key, cached=False,
                 record=committed.model_dump(mode="json"), artefacts=_artefacts(store, stage, key, committed.outputs),
                 **ids)
    return {"stage": stage, "key": key, "path": str(final), "outputs": committed.outputs, "cached": False,
            "metrics": committed.metrics}


def _sensor_poses(data, manifest: SampleManifest, entry: PassEntry) -> np.ndarray:
    """T_world_sensor per profile: the logged flange poses, or else the nominal linear motion."""
    T_flange_sensor = np.asarray(manifest.scanner.T_flange_sensor)
    if data.T_world_flange is not None:
        if not np.isfinite(data.T_world_flange).all():
            raise ValueError(f"pass {entry.pass_id}: T_world_flange holds NaN or inf")
        return data.T_world_flange @ T_flange_sensor
    motion = entry.nominal_motion
    s = data.timestamp_s * motion.speed_mm_s
    T = np.repeat(np.asarray(motion.T_world_flange_start)[None], len(s), axis=0)
    T[:, :3, 3] += s[:, None] * np.asarray(motion.direction_world)[None]
    return T @ T_flange_sensor


def _pass_points(sample_dir: Path, manifest: SampleManifest, entry: PassEntry):
    """The pass, its sensor poses (n, 4, 4) and its organized points (n, m, 3), coarse world frame."""
    data = read_pass(Path(sample_dir) / entry.file, pass_id=entry.pass_id)
    T = _sensor_poses(data, manifest, entry)
    return data, T, profile_points(data.x_mm, data.z_mm, T)


def cloud_stage(store: StageStore, sample_dir: Path, manifest: SampleManifest, entry: PassEntry,
                config: ReconstructionConfig) -> Ref:
    """Ingest one pass (coarse alignment by the robot's poses) and remove its outliers."""

    def body(out: Path) -> dict[str, Any]:
        _, T, points = _pass_points(sample_dir, manifest, entry)
        result = remove_statistical_outliers(points, **config.denoise.model_dump())
        kept = np.where(result.keep[..., None], points, np.nan).astype(np.float32)
        save_arrays(out / "cloud.zarr", points=kept, sensor_origins=T[:, :3, 3])
        n_in = int(np.isfinite(points).all(axis=-1).sum())
        return {"points_in": n_in, "points_out": int(result.keep.sum()), "removed": result.n_removed,
                "threshold_mm": result.threshold_mm}

    return _run(store, sample_id=manifest.sample_id, stage="cloud", item=entry.pass_id,
                inputs={"pass": pass_hash(sample_dir, entry)}, parameters=config.denoise.model_dump(),
                body=body, outputs=["cloud.zarr"], code_of=cloud_stage)


def targets_stage(store: StageStore, sample_dir: Path, manifest: SampleManifest, entry: PassEntry,
                  config: ReconstructionConfig) -> Ref:
    """Detect the pass's sticker targets (3-D centres, coarse world frame)."""

    def body(out: Path) -> dict[str, Any]:
        data, T, points = _pass_points(sample_dir, manifest, entry)
        found = detect_targets(data.intensity, points, sticker_diameter_mm=manifest.sticker_diameter_mm,
                               sensor_origins_mm=T[:, :3, 3], **config.targets.model_dump())
        k = len(found.targets)
        save_arrays(out / "targets.zarr",
                    centres=np.array([t.centre_mm for t in found.targets]).reshape(k, 3),
                    normals=np.array([t.normal for t in found.targets]).reshape(k, 3),
                    rms_mm=np.array([t.rms_mm for t in found.targets]).reshape(k),
                    rim_coverage=np.array([t.rim_coverage for t in found.targets]).reshape(k),
                    pixel=np.array([t.pixel for t in found.targets]).reshape(k, 2))
        if k == 0:
            raise ValueError(f"pass {entry.pass_id}: no sticker targets found ({found.n_circles} circle candidates, "
                             f"rejected {found.rejected}); the pass cannot be registered")
        return {"targets": k, "circles": found.n_circles, "rejected": found.rejected,
                "median_rms_mm": float(np.median([t.rms_mm for t in found.targets]))}

    return _run(store, sample_id=manifest.sample_id, stage="targets", item=entry.pass_id,
                inputs={"pass": pass_hash(sample_dir, entry)}, parameters=config.targets.model_dump(),
                body=body, outputs=["targets.zarr"], code_of=targets_stage)


def register_stage(store: StageStore, manifest: SampleManifest, target_refs: list[Ref],
                   config: ReconstructionConfig) -> Ref:
    """Match targets between passes and solve all pass poses together."""

    passes = manifest.passes()
    names = [e.pass_id for _, e in passes]

    def body(out: Path) -> dict[str, Any]:
        targets = [load_arrays(Path(r["path"]) / "targets.zarr", "centres")["centres"] for r in target_refs]
        rc = config.registration
        try:
            reg = register_passes(targets, [s for s, _ in passes], names=names, min_common=rc.min_common_targets,
                                  max_offset_mm=rc.max_offset_mm, tolerance_mm=rc.tolerance_mm)
        except RegistrationError as exc:
            weak = [f"{names[p.pass_a]}|{names[p.pass_b]} ({p.n_common})" for p in exc.weak_pairs]
            raise RegistrationError(f"{exc}; overlapping pass pairs with fewer than {rc.min_common_targets} common "
                                    f"targets: {', '.join(weak) or 'none'}", exc.unregistered) from None
        members = np.array([(k, p) for k, track in enumerate(reg.tracks) for p, _ in track], dtype=np.int64)
        centres = np.array([targets[p][t] for track in reg.tracks for p, t in track], dtype=np.float64)
        save_arrays(out / "registration.zarr", T_common_pass=reg.T_common_pass, residual_mm=reg.result.residual_mm,
                    inlier=reg.result.inlier, edge_passes=reg.graph.edge_passes, points_a=reg.graph.points_a,
                    points_b=reg.graph.points_b, track_positions_mm=reg.track_positions_mm,
                    specimen_track=reg.specimen_track, track_members=members.reshape(-1, 2),
                    track_centres_mm=centres.reshape(-1, 3))
        res = reg.result.residual_mm[reg.result.inlier]
        summary = {
            "pairs": [{"a": names[p.pass_a], "b": names[p.pass_b], "common_targets": p.n_common} for p in reg.pairs],
            "pairs_below_min_common": [{"a": names[p.pass_a], "b": names[p.pass_b], "common_targets": p.n_common}
                                       for p in reg.weak_pairs],
            "pass_rms_mm": {n: (None if not np.isfinite(v) else float(v)) for n, v in zip(names, reg.result.pass_rms_mm)},
        }
        atomic_write_text(out / "registration.json", json.dumps(summary, indent=1) + "\n")
        return {"target_pairs": int(reg.result.inlier.sum()), "outlier_pairs": int((~reg.result.inlier).sum()),
                "residual_median_mm": float(np.median(res)), "residual_max_mm": float(res.max()),
                "specimen_targets": int(reg.specimen_track.sum()), "weak_pairs": len(reg.weak_pairs)}

    inputs = {f"targets/{n}": r["outputs"]["targets.zarr"] for n, r in zip(names, target_refs)}
    return _run(store, sample_id=manifest.sample_id, stage="register", item=None, inputs=inputs,
                parameters=config.registration.model_dump(), body=body,
                outputs=["registration.zarr", "registration.json"], code_of=register_stage)


def refine_stage(store: StageStore, manifest: SampleManifest, cloud_refs: list[Ref], register_ref: Ref,
                 config: ReconstructionConfig) -> Ref:
    """Refine every pass pose on the targets and the overlapping surfaces together (or, when
    disabled, keep the target registration's poses)."""

    names = [e.pass_id for _, e in manifest.passes()]
    rc = config.refine

    def body(out: Path) -> dict[str, Any]:
        reg = load_arrays(Path(register_ref["path"]) / "registration.zarr")
        T_targets = reg["T_common_pass"]
        inlier = reg["inlier"].astype(bool)
        pairs, counts, steps, samples = {}, {}, [], []
        T = T_targets
        target_res = reg["residual_mm"][inlier]
        if rc.enabled:
            samples = [surface_sample(load_arrays(Path(r["path"]) / "cloud.zarr", "points")["points"],
                                      spacing_mm=rc.sample_spacing_mm, normal_radius_mm=rc.neighbour_mm,
                                      neighbours=rc.normal_neighbours, max_plane_rms_mm=rc.max_plane_rms_mm)
                       for r in cloud_refs]
            options = rc.model_dump(exclude={"enabled", "sample_spacing_mm"})
            result = refine_poses(samples, T_targets, reg["edge_passes"][inlier], reg["points_a"][inlier],
                                  reg["points_b"][inlier], **options)
            T, pairs, counts, steps = result.T_common_pass, result.pair_rms_mm, result.pair_count, result.step_mm
            target_res = result.target_residual_mm
        # each physical target where the refined poses put it: the mean of its observations
        track, pass_of = reg["track_members"][:, 0], reg["track_members"][:, 1]
        seen = np.einsum("nij,nj->ni", T[pass_of, :3, :3], reg["track_centres_mm"]) + T[pass_of, :3, 3]
        n_tracks = len(reg["track_positions_mm"])
        counts_per_track = np.bincount(track, minlength=n_tracks)[:, None]
        positions = np.stack([np.bincount(track, seen[:, i], minlength=n_tracks) for i in range(3)], axis=1)
        positions /= np.maximum(counts_per_track, 1)
        moved = max((float(np.abs(np.einsum("ij,nj->ni", (T[k] - T_targets[k])[:3, :3], s.points_mm)
                                  + (T[k] - T_targets[k])[:3, 3]).max(initial=0.0)) for k, s in enumerate(samples)),
                    default=0.0)
        save_arrays(out / "refined.zarr", T_common_pass=T, track_positions_mm=positions,
                    specimen_track=reg["specimen_track"], target_residual_mm=np.asarray(target_res, dtype=np.float64))
        summary = {"surface_pairs": [{"a": names[a], "b": names[b], "points": counts[(a, b)],
                                      "rms_mm": pairs[(a, b)]} for a, b in sorted(pairs)],
                   "step_mm": steps}
        atomic_write_text(out / "refine.json", json.dumps(summary, indent=1) + "\n")
        surface_rms = list(pairs.values())
        return {"enabled": rc.enabled, "iterations": len(steps), "last_step_mm": steps[-1] if steps else 0.0,
                "surface_pairs": len(pairs), "surface_points": int(sum(counts.values())),
                "largest_pose_change_mm": moved,
                "surface_rms_median_mm": float(np.median(surface_rms)) if surface_rms else None,
                "target_residual_median_mm": float(np.median(target_res)) if len(target_res) else None,
                "target_residual_max_mm": float(np.max(target_res)) if len(target_res) else None}

    inputs = {f"cloud/{n}": r["outputs"]["cloud.zarr"] for n, r in zip(names, cloud_refs)}
    inputs["registration"] = register_ref["outputs"]["registration.zarr"]
    return _run(store, sample_id=manifest.sample_id, stage="refine", item=None, inputs=inputs,
                parameters=rc.model_dump(), body=body, outputs=["refined.zarr", "refine.json"], code_of=refine_stage)


def merge_stage(store: StageStore, manifest: SampleManifest, cloud_refs: list[Ref], refine_ref: Ref,
                config: ReconstructionConfig) -> Ref:
    """Bring every pass into the common frame and merge them with the box-grid filter."""

    names = [e.pass_id for _, e in manifest.passes()]

    def body(out: Path) -> dict[str, Any]:
        T_all = load_arrays(Path(refine_ref["path"]) / "refined.zarr", "T_common_pass")["T_common_pass"]
        points, sensors = [], []
        for ref, T in zip(cloud_refs, T_all):
            cloud = load_arrays(Path(ref["path"]) / "cloud.zarr", "points", "sensor_origins")
            grid = cloud["points"].astype(np.float64)
            valid = np.isfinite(grid).all(axis=-1)
            rows = np.nonzero(valid)[0]
            p = grid[valid]
            points.append(p @ T[:3, :3].T + T[:3, 3])
            sensors.append(cloud["sensor_origins"][rows] @ T[:3, :3].T + T[:3, 3])
        result = merge_box_grid(np.concatenate(points), cell_mm=config.merge.cell_mm,
                                sensor_positions_mm=np.concatenate(sensors))
        save_arrays(out / "merged.zarr", points=result.points_mm, sensor_positions=result.sensor_positions_mm,
                    counts=result.counts)
        return {"points_in": int(sum(len(p) for p in points)), "points_out": result.n_points}

    inputs = {f"cloud/{n}": r["outputs"]["cloud.zarr"] for n, r in zip(names, cloud_refs)}
    inputs["refined"] = refine_ref["outputs"]["refined.zarr"]
    return _run(store, sample_id=manifest.sample_id, stage="merge", item=None, inputs=inputs,
                parameters=config.merge.model_dump(), body=body, outputs=["merged.zarr"], code_of=merge_stage)


def segment_stage(store: StageStore, manifest: SampleManifest, merge_ref: Ref, refine_ref: Ref,
                  config: ReconstructionConfig) -> Ref:
    """Keep the connected components that carry the specimen's targets; the fixture goes."""

    def body(out: Path) -> dict[str, Any]:
        merged = load_arrays(Path(merge_ref["path"]) / "merged.zarr")
        reg = load_arrays(Path(refine_ref["path"]) / "refined.zarr", "track_positions_mm", "specimen_track")
        anchors = reg["track_positions_mm"][reg["specimen_track"]]
        if len(anchors) == 0:
            raise ValueError("no target was seen in more than one setup: the specimen cannot be told from the fixture")
        result = keep_specimen_components(merged["points"], link_mm=config.segment.link_mm, target_points_mm=anchors)
        keep = result.keep
        save_arrays(out / "specimen.zarr", points=merged["points"][keep], sensor_positions=merged["sensor_positions"][keep])
        return {"points_in": int(len(keep)), "points_out": int(keep.sum()), "components": int(result.n_components),
                "kept_components": int(len(result.kept_labels))}

    inputs = {"merged": merge_ref["outputs"]["merged.zarr"], "refined": refine_ref["outputs"]["refined.zarr"]}
    return _run(store, sample_id=manifest.sample_id, stage="segment", item=None, inputs=inputs,
                parameters=config.segment.model_dump(), body=body, outputs=["specimen.zarr"], code_of=segment_stage)


def surface_stage(store: StageStore, manifest: SampleManifest, segment_ref: Ref, config: ReconstructionConfig) -> Ref:
    """Normals oriented toward the sensors, then MeshLab's screened Poisson reconstruction."""

    sc = config.surface

    def body(out: Path) -> dict[str, Any]:
        cloud = load_arrays(Path(segment_ref["path"]) / "specimen.zarr")
        normals = estimate_normals(cloud["points"], cloud["sensor_positions"], k=sc.normals_k)
        mesh = screened_poisson(cloud["points"], normals, depth=sc.poisson_depth, samples_per_node=sc.samples_per_node,
                                point_weight=sc.point_weight, scale=sc.poisson_scale)
        save_arrays(out / "mesh.zarr", vertices=mesh.vertices, triangles=mesh.triangles)
        r = mesh.report
        return {"points": int(len(cloud["points"])), "vertices": r.n_vertices, "triangles": r.n_triangles,
                "watertight": r.watertight, "consistently_oriented": r.consistently_oriented,
                "boundary_edges": r.n_boundary_edges, "non_manifold_edges": r.n_non_manifold_edges,
                "volume_mm3": r.volume_mm3, "surface_area_mm2": r.surface_area_mm2, "note": mesh.note}

    return _run(store, sample_id=manifest.sample_id, stage="surface", item=None,
                inputs={"specimen": segment_ref["outputs"]["specimen.zarr"]}, parameters=sc.model_dump(),
                body=body, outputs=["mesh.zarr"], code_of=surface_stage)


def export_stage(store: StageStore, manifest: SampleManifest, surface_ref: Ref) -> Ref:
    """Binary STL (for FE software) and PLY of the mesh."""

    def body(out: Path) -> dict[str, Any]:
        mesh = load_arrays(Path(surface_ref["path"]) / "mesh.zarr")
        write_mesh(out / f"{manifest.sample_id}.stl", mesh["vertices"], mesh["triangles"], binary=True)
        write_mesh(out / f"{manifest.sample_id}.ply", mesh["vertices"], mesh["triangles"], binary=True)
        return {"stl_bytes": (out / f"{manifest.sample_id}.stl").stat().st_size}

    return _run(store, sample_id=manifest.sample_id, stage="export", item=None,
                inputs={"mesh": surface_ref["outputs"]["mesh.zarr"]}, parameters={}, body=body,
                outputs=[f"{manifest.sample_id}.stl", f"{manifest.sample_id}.ply"], code_of=export_stage)
