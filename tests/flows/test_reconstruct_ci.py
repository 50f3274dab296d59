"""The real reconstruction flow (Prefect's engine, a temporary local server, real zarr stores,
MeshLab's Poisson) on the ``ci`` sample, checked against the simulator's ground truth."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from data_catalog.truth import read_truth
from flows.stages import STAGES
from flows.stages.outputs import MERGED, MESH, REFINED, REGISTRATION, SPECIMEN
from simulator.evaluate import fit_gauge, pass_misalignment, true_sticker_centres
from tasks.mesh import mesh_report
from tests.flows.samples import as_published

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


@pytest.fixture(scope="module")
def run(ci_run):
    return ci_run


def _specimen_scene(ci_sample):
    mesh = o3d.io.read_triangle_mesh(str(ci_sample / "truth" / "specimen.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def _refined(report):
    return REFINED.read(report["refs"]["refine"])


def _gauge(report, ci_sample):
    """Specimen frame -> reconstruction, fitted on the true stickers and the registered targets."""
    refined = _refined(report)
    positions = refined.track_positions_mm
    return fit_gauge(ci_sample, positions[refined.specimen_track], positions)


def test_the_flow_ends_with_a_watertight_stl_and_a_report(run):
    out, report = run
    stl = Path(report["outputs"][f"{report['sample_id']}.stl"]["path"])
    assert stl.is_file() and stl.stat().st_size > 10_000
    mesh = o3d.io.read_triangle_mesh(str(stl))
    assert len(mesh.triangles) == report["mesh"]["triangles"]
    assert report["mesh"]["watertight"] and report["mesh"]["consistently_oriented"]
    saved = json.loads((out / "results" / "report.json").read_text())
    assert saved["sample_id"] == "sim-ci-0011"
    assert set(saved["stages"]) == {s.name for s in STAGES} - {"report", "qa_report"}  # every stage before the report
    assert json.loads((out / "results" / "config.json").read_text()) == saved["config"]  # published with them
    assert not (out / "config.json").exists()
    weld = saved["weld"]  # the weld measured and judged: its summary in the report
    assert weld["measured"] is True and weld["sections"] >= 70 and weld["verdict"] in ("pass", "fail")
    assert weld["failing"] == len({(f["line"], f["position_mm"]) for f in weld["failing_sections"]})
    assert weld["statistics"]["toe_radius_mm"]["n"] >= 140


def test_the_fe_model_is_one_solid_of_the_meshes_volume_graded_toward_the_weld(run):
    """Stage volume: the published Abaqus and VTU files read back with meshio as one connected,
    positively oriented solid whose volume is the STL's within 0.5 %, with the weld zone's set."""
    import meshio

    from tasks.volume_mesh import signed_volumes

    out, report = run
    sid = report["sample_id"]
    inp = meshio.read(Path(report["outputs"][f"{sid}.inp"]["path"]))
    vtu = meshio.read(Path(report["outputs"][f"{sid}.vtu"]["path"]))
    elements = inp.cells_dict["tetra10"]  # C3D10 by default (volume.element_order 2)
    assert np.array_equal(elements, vtu.cells_dict["tetra10"])
    assert len(elements) == report["volume_mesh"]["solid"]["tetrahedra"] and len(inp.points) == report["volume_mesh"]["model_nodes"]
    assert "*ELEMENT, TYPE=C3D10\n" in Path(report["outputs"][f"{sid}.inp"]["path"]).read_text()
    tets = elements[:, :4]
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))):  # edge nodes at the midpoints
        assert np.allclose(inp.points[elements[:, 4 + k]], (inp.points[tets[:, i]] + inp.points[tets[:, j]]) / 2, atol=1e-6)
    volumes = signed_volumes(inp.points, tets)
    assert np.all(volumes > 0)
    assert abs(volumes.sum() / report["mesh"]["volume_mm3"] - 1) < 0.005
    solid = report["volume_mesh"]["solid"]
    assert solid["components"] == 1 and solid["open_boundary_edges"] == 0 and solid["negative_or_flat"] == 0
    quality = report["volume_mesh"]["quality"]
    # no sliver (measured with gmsh's HXT: worst 14.2 deg / aspect ratio 7.7, 1st percentile of the
    # angle 27.6 deg; Delaunay with Netgen's optimizer before: 6.8 deg / 27.9, ~31 deg)
    assert quality["min_dihedral_deg"]["worst"] > 5 and quality["aspect_ratio"]["worst"] < 50
    assert quality["min_dihedral_deg"]["p1"] > 20
    # within the limits FE programs accept without warnings (issue 26; measured 10.8 deg / 6.8)
    assert quality["below_10_deg"] == 0 and quality["aspect_ratio"]["worst"] <= 10
    assert np.allclose(vtu.cell_data["min_dihedral_deg"][0].min(), quality["min_dihedral_deg"]["worst"], atol=1e-3)
    # the weld zone: a named node set and surface, its elements at the weld's size, finer than the rest
    zone = inp.point_sets["WELD_ZONE_NODES"]
    assert 0 < len(zone) < len(inp.points)
    assert "WELD_ZONE_SURFACE" in Path(report["outputs"][f"{sid}.inp"]["path"]).read_text()
    p = inp.points[tets]
    edge = np.linalg.norm(p[:, [0, 0, 0, 1, 1, 2]] - p[:, [1, 2, 3, 2, 3, 3]], axis=2).mean(axis=1)
    in_zone = vtu.cell_data["weld_zone_boundary"][0].astype(bool)
    weld_size = report["config"]["volume"]["weld_size_mm"]
    assert np.median(edge[in_zone]) < 1.15 * weld_size  # measured 1.47 mm at 1.5 (HXT; 1.58 mm before)
    # measured 2.64 mm against 1.47 mm (HXT fills the inside with smaller elements than Delaunay
    # with Netgen's optimizer did, 3.52 mm against 1.58 mm; 3.40 mm farther than 20 mm from the toes)
    assert np.median(edge[~in_zone]) > 1.6 * np.median(edge[in_zone])
    # finer still at the toes the weld stage measured: both toes of every weld line
    assert report["volume_mesh"]["toe_lines"] == 2 * len(report["weld"]["lines"])
    assert report["volume_mesh"]["toe_points"] >= 2 * report["weld"]["sections"] * 0.9


def test_every_consistency_check_is_stated_and_passes_on_a_clean_sample(run):
    _, report = run
    checks = report["checks"]
    # per pass: profile times and poses, chunk continuity, target residuals; for the sample: the
    # surfaces the two setups share agree as well as one setup's own overlaps do; the part measured is the
    # part declared; the weld measured at every line and judged; the FE model; the stress
    assert len(checks) == 3 * 14 + 5 and {c["result"] for c in checks} == {"ok"}
    [declared] = [c for c in checks if c["check"] == "part as declared"]
    assert abs(declared["measured"]["thickness_mm"] - 20.0) < 0.3  # the ci dog-bone: 20 mm (and 0.1 mm stickers)
    [weld] = [c for c in checks if c["check"] == "weld measured"]
    assert weld["what"].endswith("sections measured at every weld line, judged: pass"), weld
    shared = [c for c in checks if c["check"] == "surfaces the setups share"]
    assert len(shared) == 1 and shared[0]["pass"] == "all" and shared[0]["measured"]["pairs_across"] >= 1
    motion = [c["measured"] for c in checks if c["check"] == "profile times and poses"]
    assert all(m["logged_poses"] and m["rotation_off_orthonormal"] < 1e-6 and m["largest_step_of_allowed"] < 1
               for m in motion)


def test_every_true_specimen_sticker_was_found(run, ci_sample):
    _, report = run
    truth = read_truth(ci_sample / "truth" / "truth.json")
    gauge = _gauge(report, ci_sample)
    true = true_sticker_centres(truth)
    G = gauge.T_recon_specimen
    found = _refined(report).track_positions_mm
    nearest = np.linalg.norm((true @ G[:3, :3].T + G[:3, 3])[:, None] - found[None], axis=-1).min(axis=1)
    assert len(true) == 46
    assert nearest.max() < 0.1, np.round(nearest, 3)  # measured: every one, the farthest 0.06 mm off


def test_registration_recovers_the_true_pass_poses(run, ci_sample):
    _, report = run
    T_common = _refined(report).T_common_pass
    # Misalignment of each pass over all the specimen surface it measured, from truth: where the
    # reconstruction puts each measured point against where that point really is, after the one
    # rigid fit of the whole reconstruction to the specimen.
    m = pass_misalignment(ci_sample, T_common)
    # measured on the ci sample (0.32 mm points, stickers with their 0.1 mm paper edge): worst
    # 33 um, median of the pass medians 10.3 um (fitting the sticker centres without the edge's
    # height: 80 and 42 um; before the simulator modelled the edge: 18 and 4-8 um); the paper
    # saw < 50 um between overlapping scans
    assert m.max_mm.max() < 0.040, dict(zip(m.pass_ids, np.round(1000 * m.max_mm)))
    assert np.median(m.median_mm) < 0.013, dict(zip(m.pass_ids, np.round(1000 * m.median_mm)))
    # the same with the frame fixed by the targets instead (measured 38 um; 80 um without the
    # edge's height): no error hides in where the targets put the whole
    by_targets = pass_misalignment(ci_sample, T_common, _gauge(report, ci_sample))
    assert by_targets.max_mm.max() < 0.045


def test_refinement_beats_targets_alone(run, ci_sample):
    _, report = run
    targets_only = REGISTRATION.open(report["refs"]["registration"]).T_common_pass
    before = pass_misalignment(ci_sample, targets_only)
    after = pass_misalignment(ci_sample, _refined(report).T_common_pass)
    # measured: worst 39 um on targets alone, 18 um refined
    assert after.max_mm.max() < 0.7 * before.max_mm.max(), (before.max_mm.max(), after.max_mm.max())
    assert np.median(after.median_mm) < np.median(before.median_mm)
    assert report["stages"]["refine"]["surface_pairs"] >= 20


def test_the_fixture_is_gone_and_the_specimen_is_whole(run, ci_sample):
    out, report = run
    G = _gauge(report, ci_sample).T_recon_specimen
    points = SPECIMEN.open(report["refs"]["segment"]).points
    G_inv = np.linalg.inv(G)
    in_specimen = points @ G_inv[:3, :3].T + G_inv[:3, 3]
    dist = _specimen_scene(ci_sample).compute_distance(o3d.core.Tensor(in_specimen.astype(np.float32))).numpy()
    assert np.quantile(dist, 0.999) < 0.5  # nothing of the fixture (blocks, base plate) is left
    z = in_specimen[:, 2]
    assert (z > 5).sum() > 1000 and (z < -5).sum() > 1000  # both setups: top and bottom faces
    merged = MERGED.open(report["refs"]["merge"]).points
    assert len(points) < 0.7 * len(merged)  # the fixture was a real share of the merged cloud


def test_the_mesh_lies_on_the_true_surface(run, ci_sample):
    out, report = run
    G = _gauge(report, ci_sample).T_recon_specimen
    mesh = MESH.read(report["refs"]["mesh"])
    G_inv = np.linalg.inv(G)
    v = mesh.vertices @ G_inv[:3, :3].T + G_inv[:3, 3]
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
    from flows.stages import needed_for

    out, first = run
    again = as_published(reconstruct_sample(str(ci_sample), str(out), CI_CONFIG))
    assert all(again["cached"].values())
    assert again["stage_keys"] == first["stage_keys"]
    deeper = tmp_path / "deeper.yaml"
    deeper.write_text(Path(CI_CONFIG).read_text().replace("poisson_depth: 8", "poisson_depth: 7"))
    # up to the export (that the FE model, the report and the QA page after it are made again when
    # the mesh changes: tests/flows/test_resilience_audit.py, the rerun after a kill while meshing)
    changed = reconstruct_sample(str(ci_sample), str(out), str(deeper), stop_after="export")
    assert {k for k, v in changed.cached.items() if not v} == {"mesh", "export"}
    assert set(changed.cached) == {s.name for s in needed_for("export")}


def test_the_weld_zone_stays_fine(run, ci_sample):
    """The manifest's nominal placement puts the weld lines in the common frame: every merged
    point within 15 mm of them (placed on the specimen by its true stickers) is a fine cell, flat
    or not; the flat plate beyond the zone and its tolerance is coarse."""
    from data_catalog.manifests import load_manifest
    from tasks.weld_zone import PolylineZone

    out, report = run
    metrics = report["stages"]["merge"]
    lines = load_manifest(ci_sample).weld_lines()
    assert len(metrics["weld_zones"]) == len(lines) and metrics["weld_zone_points_out"] > 0  # one per line (the weld frame's)
    reach = max(z["radius_mm"] for z in metrics["weld_zones"])
    G_inv = np.linalg.inv(_gauge(report, ci_sample).T_recon_specimen)
    merged = MERGED.read(report["refs"]["merge"])
    specimen = merged.points @ G_inv[:3, :3].T + G_inv[:3, 3]
    distance = np.min([PolylineZone(tuple(line.points_mm), 0.0).distance_mm(specimen) for line in lines], axis=0)
    near = distance <= 15.0 - 0.5  # minus a coarse cell: a coarse cell is in the zone when its mean is
    assert near.sum() > 1000 and merged.fine[near].all()
    beyond = distance > reach + 1.0
    assert (~merged.fine[beyond]).sum() > 0.3 * beyond.sum()


def test_the_fe_models_named_weld_zone_is_the_qa_pages_face_for_face(run, ci_sample):
    """Two setups (top and bottom): every boundary face of the FE model is in WELD_ZONE_SURFACE
    exactly when the QA page's weld zone (placement.model_weld_zone, faces by centroid) holds it;
    the zone spans both faces of the part (both weld caps)."""
    import meshio

    from data_catalog.manifests import load_manifest
    from flows.preflight import load_config
    from flows.stages.placement import model_weld_zone, weld_frame
    from tasks.volume_mesh import VolumeMesh, boundary_faces

    out, report = run
    inp = meshio.read(Path(report["outputs"][f"{report['sample_id']}.inp"]["path"]))
    points, tets = inp.points, inp.cells_dict["tetra10"][:, :4]  # the corners
    element, face = boundary_faces(tets)
    triangles = VolumeMesh(points, tets, element, face, np.zeros(len(element), bool)).boundary_triangles()
    named = np.zeros(len(element), bool)
    for number in (1, 2, 3, 4):
        members = np.concatenate(inp.cell_sets.get(f"WELD_ZONE_S{number}", [np.zeros(0, np.int64)]))
        named |= (face == number) & np.isin(element, members)
    manifest = load_manifest(ci_sample)
    zone = model_weld_zone(manifest, _refined(report).T_common_pass, load_config(CI_CONFIG))
    qa = zone.faces_in(points, triangles)
    assert named.sum() > 500 and np.array_equal(qa, named)
    assert len(manifest.setups) == 2
    normals = np.cross(points[triangles[:, 1]] - points[triangles[:, 0]], points[triangles[:, 2]] - points[triangles[:, 0]])
    up = normals[named] @ weld_frame(manifest, _refined(report).T_common_pass)[:3, 2]  # the specimen's z: both caps
    assert (up > 0).sum() > 100 and (up < 0).sum() > 100
