"""The real reconstruction flow (Prefect's engine, a temporary local server, real zarr stores,
MeshLab's Poisson) on the ``ci`` sample, checked against the simulator's ground truth."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.stages import load_arrays
from data_catalog.truth import read_truth
from tasks.matching import kabsch, match_rotation_invariant
from tasks.surface import mesh_report

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


@pytest.fixture(scope="module")
def run(ci_sample, tmp_path_factory):
    from flows.reconstruct import reconstruct_sample

    out = tmp_path_factory.mktemp("recon") / "run"
    report = reconstruct_sample(str(ci_sample), str(out), CI_CONFIG)
    return out, report


def _stage_path(report, out, stage):
    return Path(report["stage_paths"][stage])


def _specimen_scene(ci_sample):
    mesh = o3d.io.read_triangle_mesh(str(ci_sample / "truth" / "specimen.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _gauge(report, out, ci_sample, truth):
    """The rigid transform from the specimen frame to the reconstruction's frame, fitted on the
    true sticker centres against the registered specimen targets."""
    reg = load_arrays(_stage_path(report, out, "register") / "registration.zarr")
    found = reg["track_positions_mm"][reg["specimen_track"]]
    true = np.array([np.array(s.centre_mm) + 0.1 * np.array(s.normal) for s in truth.stickers if s.on == "specimen"])
    T = match_rotation_invariant(found, true).T_a_b  # rough, then pair by nearest and refit
    for _ in range(3):
        moved = true @ T[:3, :3].T + T[:3, 3]
        d = np.linalg.norm(found[:, None] - moved[None], axis=-1)
        k = d.argmin(axis=1)
        ok = d.min(axis=1) < 1.0
        T = kabsch(true[k[ok]], found[ok])
    return T, int(ok.sum())


def test_the_flow_ends_with_a_watertight_stl_and_a_report(run):
    out, report = run
    stl = Path(report["outputs"][f"{report['sample_id']}.stl"]["path"])
    assert stl.is_file() and stl.stat().st_size > 10_000
    mesh = o3d.io.read_triangle_mesh(str(stl))
    assert len(mesh.triangles) == report["mesh"]["triangles"]
    assert report["mesh"]["watertight"] and report["mesh"]["consistently_oriented"]
    saved = json.loads((out / "results" / "report.json").read_text())
    assert saved["sample_id"] == "sim-ci-0011"
    assert set(saved["stages"]) == {"cloud", "targets", "register", "merge", "segment", "mesh", "export"}
    assert (out / "config.json").is_file()


def test_registration_recovers_the_true_pass_poses(run, ci_sample):
    out, report = run
    truth = read_truth(ci_sample / "truth" / "truth.json")
    manifest = load_manifest(ci_sample)
    G, n_used = _gauge(report, out, ci_sample, truth)
    assert n_used >= 10
    T_common = load_arrays(_stage_path(report, out, "register") / "registration.zarr")["T_common_pass"]
    from data_catalog.passes import read_pass
    from data_catalog.truth import read_truth_pass
    from tasks.ingest import profile_points

    worst = []
    for k, (setup, entry) in enumerate(manifest.passes()):
        data = read_pass(ci_sample / entry.file)
        tp = read_truth_pass(ci_sample / "truth" / "passes" / f"{entry.pass_id}.zarr")
        coarse = profile_points(data.x_mm, data.z_mm, data.T_world_flange @ np.array(manifest.scanner.T_flange_sensor))
        on_specimen = np.isin(tp.material, (1, 2, 3)) & (tp.label == 0)
        p = coarse[on_specimen][::10]
        E = np.array(next(t.T_nominal_true for t in truth.passes if t.pass_id == entry.pass_id))
        S = np.linalg.inv(np.array(truth.T_world_specimen[setup]))
        true_spec = p @ (S @ E)[:3, :3].T + (S @ E)[:3, 3]  # where these points really are (specimen frame)
        ours = p @ T_common[k][:3, :3].T + T_common[k][:3, 3]
        expected = true_spec @ G[:3, :3].T + G[:3, 3]
        worst.append(np.linalg.norm(ours - expected, axis=1).max())
    # Largest misalignment of any pass anywhere on the specimen surface it measured. The paper saw
    # < 50 um; at the ci preset's 0.32 mm points the figure is (measured) about 0.15 mm.
    assert max(worst) < 0.25, [round(1000 * w) for w in worst]
    assert np.median(worst) < 0.12, [round(1000 * w) for w in worst]


def test_the_fixture_is_gone_and_the_specimen_is_whole(run, ci_sample):
    out, report = run
    truth = read_truth(ci_sample / "truth" / "truth.json")
    G, _ = _gauge(report, out, ci_sample, truth)
    points = load_arrays(_stage_path(report, out, "segment") / "specimen.zarr", "points")["points"]
    G_inv = np.linalg.inv(G)
    in_specimen = points @ G_inv[:3, :3].T + G_inv[:3, 3]
    dist = _specimen_scene(ci_sample).compute_distance(o3d.core.Tensor(in_specimen.astype(np.float32))).numpy()
    assert np.quantile(dist, 0.999) < 0.5  # nothing of the fixture (blocks, base plate) is left
    z = in_specimen[:, 2]
    assert (z > 5).sum() > 1000 and (z < -5).sum() > 1000  # both setups: top and bottom faces
    merged = load_arrays(_stage_path(report, out, "merge") / "merged.zarr", "points")["points"]
    assert len(points) < 0.7 * len(merged)  # the fixture was a real share of the merged cloud


def test_the_mesh_lies_on_the_true_surface(run, ci_sample):
    out, report = run
    truth = read_truth(ci_sample / "truth" / "truth.json")
    G, _ = _gauge(report, out, ci_sample, truth)
    mesh = load_arrays(_stage_path(report, out, "mesh") / "mesh.zarr")
    G_inv = np.linalg.inv(G)
    v = mesh["vertices"] @ G_inv[:3, :3].T + G_inv[:3, 3]
    dist = _specimen_scene(ci_sample).compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy()
    length = 240.0
    scanned = np.abs(v[:, 0]) < length / 2 - 2  # the ends were never scanned: Poisson closes them freely
    # depth 8 over 240 mm: cells of about 1.2 mm; measured median 0.07 mm
    assert np.median(dist[scanned]) < 0.1, np.median(dist[scanned])
    assert np.quantile(dist[scanned], 0.95) < 0.3, np.quantile(dist[scanned], 0.95)
    true_mesh = o3d.io.read_triangle_mesh(str(ci_sample / "truth" / "specimen.ply"))
    true_volume = mesh_report(np.asarray(true_mesh.vertices), np.asarray(true_mesh.triangles)).volume_mm3
    # measured +6.5 %: Poisson closes the never-scanned end faces with a bulge
    assert abs(report["mesh"]["volume_mm3"] - true_volume) / true_volume < 0.10


def test_a_rerun_executes_no_stage_and_a_new_depth_only_meshing(run, ci_sample, tmp_path):
    from flows.reconstruct import reconstruct_sample

    out, first = run
    again = reconstruct_sample(str(ci_sample), str(out), CI_CONFIG)
    assert all(again["cached"].values())
    assert again["stage_keys"] == first["stage_keys"]
    deeper = tmp_path / "deeper.yaml"
    deeper.write_text(Path(CI_CONFIG).read_text().replace("poisson_depth: 8", "poisson_depth: 7"))
    changed = reconstruct_sample(str(ci_sample), str(out), str(deeper))
    assert {k for k, v in changed["cached"].items() if not v} == {"mesh", "export"}
