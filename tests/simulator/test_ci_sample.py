"""The ``ci`` sample: valid files, stickers for every overlap, realistic defects, ground truth
that agrees with the cell's files."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import zarr

from data_catalog.hashing import sha256_tree
from data_catalog.manifests import load_manifest
from data_catalog.passes import read_pass
from data_catalog.truth import read_truth, read_truth_pass
from schemas.truth import Material, PointLabel
from simulator.coverage import spread_off_line_mm
from simulator.preview import project_to_pass
from simulator.scanner import fan_directions
from tasks.frames import apply
from tasks.ingest import profile_points


@pytest.fixture(scope="module")
def manifest(ci_sample):
    return load_manifest(ci_sample)


@pytest.fixture(scope="module")
def truth(ci_sample):
    return read_truth(ci_sample / "truth" / "truth.json")


@pytest.fixture(scope="module")
def truth_passes(ci_sample, manifest):
    return {p.pass_id: read_truth_pass(ci_sample / "truth" / "passes" / f"{p.pass_id}.zarr")
            for _, p in manifest.passes()}


def test_files_validate_against_the_manifest(ci_sample, manifest, ci_config):
    assert [s.name for s in manifest.setups] == ["top", "bottom"]
    assert len(manifest.passes()) == 14
    for _, entry in manifest.passes():
        data = read_pass(ci_sample / entry.file, pass_id=entry.pass_id)
        assert data.shape == (entry.n_profiles, manifest.scanner.points_per_profile)
        assert data.T_world_flange is not None and data.T_world_flange.shape == (entry.n_profiles, 4, 4)
        assert sha256_tree(ci_sample / entry.file) == entry.content_sha256
        assert data.intensity.max() <= 1023
        missing = np.isnan(data.z_mm)
        assert np.array_equal(missing, np.isnan(data.x_mm))
        assert np.all(data.intensity[missing] == 0) and np.all(data.intensity[~missing] > 0)
        assert np.allclose(np.diff(data.timestamp_s), 1 / entry.nominal_motion.profile_rate_hz)


def test_every_overlapping_pair_shares_three_stickers_off_a_line(truth, truth_passes, ci_config):
    specimen = {s.sticker_id: np.array(s.centre_mm) for s in truth.stickers if s.on == "specimen"}
    assert len(truth.overlapping_pairs) >= 10
    setups = {p.pass_id: p.setup for p in truth.passes}
    assert any(setups[a] != setups[b] for a, b in truth.overlapping_pairs), "no pair joins the two setups"
    paired = {pass_id for pair in truth.overlapping_pairs for pass_id in pair}
    assert paired == set(setups), f"passes with no overlapping partner: {set(setups) - paired}"
    for a, b in truth.overlapping_pairs:
        common = truth.common_stickers[f"{a}|{b}"]
        assert len(common) >= 3, (a, b, common)
        assert spread_off_line_mm(np.array([specimen[k] for k in common])) >= ci_config.stickers.min_spread_mm
        for pass_id in (a, b):  # the cell's own data show each common sticker whole
            tp = truth_passes[pass_id]
            for k in common:
                n_valid = np.count_nonzero((tp.sticker_id == k) & (tp.label == PointLabel.VALID))
                assert n_valid >= 50, (pass_id, k, n_valid)


def _rates(truth_passes, material):
    seen = drop = out = 0
    for tp in truth_passes.values():
        on = tp.material == material
        labels = tp.label[on]
        n_valid, n_drop, n_out = (np.count_nonzero(labels == v) for v in
                                  (PointLabel.VALID, PointLabel.DROPOUT, PointLabel.OUTLIER))
        seen += n_valid + n_drop + n_out
        drop += n_drop
        out += n_out
    return seen, drop, out


def _within(count, n, p, sigmas=5.0):
    return abs(count - n * p) <= sigmas * np.sqrt(n * p * (1 - p)) + 1


def test_dropouts_and_outliers_at_the_stated_rates(truth_passes, ci_config):
    sc = ci_config.scanner
    seen, drop, out = _rates(truth_passes, Material.STEEL)
    assert seen > 500_000
    assert _within(drop, seen, sc.dropout_rate), drop / seen
    assert _within(out, seen - drop, sc.outlier_rate), out / (seen - drop)


def _true_hits_specimen_frame(ci_sample, truth, tp, setup, fan, mask):
    """Cast the laser rays of the masked pixels against the true scene; hit points, specimen frame."""
    T_ws = np.array(truth.T_world_specimen[setup])
    scene = o3d.t.geometry.RaycastingScene()
    for name, T in (("specimen.ply", T_ws), ("fixture.ply", np.eye(4))):
        mesh = o3d.io.read_triangle_mesh(str(ci_sample / "truth" / name)).transform(T)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    rows, cols = np.nonzero(mask)
    R, o = tp.T_world_sensor[rows, :3, :3], tp.T_world_sensor[rows, :3, 3]
    d = np.einsum("kij,kj->ki", R, fan[cols])
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))
    t = hit["t_hit"].numpy()
    return apply(np.linalg.inv(T_ws), o + t[:, None] * d)


def test_shadows_fall_behind_the_weld_cap_and_the_plate_edges(ci_sample, truth, truth_passes, ci_config):
    fan = fan_directions(ci_config.scanner.points_per_profile, ci_config.scanner.x_spacing_mm,
                         ci_config.scanner.reference_distance_mm)
    spec = ci_config.specimen
    total = shadows = on_specimen = 0
    for p in truth.passes:
        tp = truth_passes[p.pass_id]
        shadow = tp.label == PointLabel.SHADOW
        total += tp.label.size
        shadows += np.count_nonzero(shadow)
        on = shadow & np.isin(tp.material, (Material.STEEL, Material.STICKER))
        on_specimen += np.count_nonzero(on)
        if on.any():  # shadows on the specimen lie at the weld
            hits = _true_hits_specimen_frame(ci_sample, truth, tp, p.setup, fan, on)
            assert np.all(np.abs(hits[:, 0]) < 12), hits[np.abs(hits[:, 0]) >= 12]
        off = shadow & (tp.material == Material.FIXTURE)
        hits = _true_hits_specimen_frame(ci_sample, truth, tp, p.setup, fan, off)
        # shadows on the fixture lie beside the specimen, not far out on the base plate
        beside = np.abs(np.abs(hits[:, 1]) - spec.grip_width_mm / 2) < spec.thickness_mm * 3 + 20
        beside |= np.abs(hits[:, 0]) > spec.length_mm / 2 - 5
        beside |= np.abs(hits[:, 1]) < spec.grip_width_mm / 2 + 25
        assert beside.mean() > 0.99
    assert on_specimen >= 20, on_specimen
    assert 0.01 < shadows / total < 0.2, shadows / total


def test_true_sticker_centres_land_on_sticker_pixels(ci_sample, manifest, truth, truth_passes, ci_config):
    sc = ci_config.scanner
    checked = 0
    whole = {}  # pass -> stickers it sees whole, per the truth
    for key, ids in truth.common_stickers.items():
        for pass_id in key.split("|"):
            whole.setdefault(pass_id, set()).update(ids)
    for setup, entry in manifest.passes():
        tp = truth_passes[entry.pass_id]
        data = read_pass(ci_sample / entry.file)
        T_ws = np.array(truth.T_world_specimen[setup])
        steel = np.median(data.intensity[(tp.material == Material.STEEL) & (tp.label == PointLabel.VALID)])
        for s in truth.stickers:
            if s.on != "specimen":
                continue
            if s.sticker_id not in whole.get(entry.pass_id, ()):
                continue
            top = np.array(s.centre_mm) + 0.1 * np.array(s.normal)
            uv = project_to_pass(apply(T_ws, top)[None], tp.T_world_sensor, sc.x_spacing_mm,
                                 sc.reference_distance_mm, sc.points_per_profile)[0]
            row, col = int(round(uv[0])), int(round(uv[1]))
            assert tp.sticker_id[row, col] == s.sticker_id, (entry.pass_id, s.sticker_id, uv)
            around = data.intensity[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2]
            around = around[around > 0]  # skip a random dropout at the centre
            assert np.median(around) > 1.5 * steel, (entry.pass_id, s.sticker_id, around)
            checked += 1
    assert checked > 50


def test_reported_points_lie_on_the_true_surface(ci_sample, manifest, truth, truth_passes, ci_config):
    mesh = o3d.io.read_triangle_mesh(str(ci_sample / "truth" / "specimen.ply"))
    fan = fan_directions(ci_config.scanner.points_per_profile, ci_config.scanner.x_spacing_mm,
                         ci_config.scanner.reference_distance_mm)
    for setup, entry in manifest.passes()[:3]:
        data = read_pass(ci_sample / entry.file)
        tp = truth_passes[entry.pass_id]
        T_spec_world = np.linalg.inv(np.array(truth.T_world_specimen[setup]))
        world = profile_points(data.x_mm, data.z_mm, tp.T_world_sensor)
        on_steel = tp.material == Material.STEEL
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        for label in (PointLabel.VALID, PointLabel.OUTLIER):
            pts = apply(T_spec_world, world[(tp.label == label) & on_steel])
            dist = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
            assert pts.shape[0] > 0
            if label == PointLabel.VALID:
                assert np.quantile(dist, 0.999) < 0.05, np.quantile(dist, 0.999)
                assert np.std(dist) < 0.02
            else:
                assert np.median(dist) > 0.15
        assert np.all(np.abs(data.x_mm[~np.isnan(data.x_mm)] / data.z_mm[~np.isnan(data.z_mm)]) <=
                      np.abs(fan[:, 0] / fan[:, 2]).max() + 1e-6)


def test_true_motion_differs_from_the_logged_by_a_rigid_error(ci_sample, manifest, truth, truth_passes):
    T_flange_sensor = np.array(manifest.scanner.T_flange_sensor)
    for _, entry in manifest.passes():
        logged = read_pass(ci_sample / entry.file).T_world_flange @ T_flange_sensor
        true = truth_passes[entry.pass_id].T_world_sensor
        E = np.array(next(p for p in truth.passes if p.pass_id == entry.pass_id).T_nominal_true)
        residual = np.linalg.norm((E[None] @ logged)[:, :3, 3] - true[:, :3, 3], axis=1)
        assert residual.max() < 0.02  # encoder noise only
        offset = np.linalg.norm(logged[:, :3, 3] - true[:, :3, 3], axis=1)
        assert 0.01 < offset.mean() < 2.0  # tenths of a millimetre of robot error


def test_same_seed_gives_identical_files(ci_sample, tmp_path, ci_config):
    from simulator.run import simulate

    again = tmp_path / "again"
    simulate(ci_config, again)
    for rel in ("manifest.json", "passes", "truth", "preview"):
        assert sha256_tree(again / rel) == sha256_tree(ci_sample / rel), rel


def test_a_cell_without_a_pose_log_writes_the_same_profiles_and_no_log(ci_config, tmp_path):
    """``robot.log_profile_poses: false`` on a two-pass plan of the ci preset: the sample is the
    one with the log, less the log, byte for byte (tests.flows.samples.without_pose_logs, which
    the session's sample without a pose log is made with)."""
    from simulator.run import simulate
    from tests.flows.samples import without_pose_logs

    plan = ci_config.plan.model_copy(update={"setups": ["top"], "vertical_offsets_mm": [-15.0, 15.0],
                                             "side_rolls_deg": [], "width_passes": []})
    runs = {}
    for logged in (True, False):
        config = ci_config.model_copy(update={"plan": plan, "robot": ci_config.robot.model_copy(
            update={"log_profile_poses": logged})})
        simulate(config, tmp_path / str(logged), previews=False)
        runs[logged] = tmp_path / str(logged)
    manifest = load_manifest(runs[False])
    assert [e.has_profile_poses for _, e in manifest.passes()] == [False, False]
    assert not any((runs[False] / e.file / "T_world_flange").exists() for _, e in manifest.passes())
    derived = without_pose_logs(runs[True], tmp_path / "derived")
    assert sha256_tree(derived) == sha256_tree(runs[False])


def test_previews_exist(ci_sample):
    pngs = sorted(p.name for p in (ci_sample / "preview").glob("*.png"))
    assert "footprints_top.png" in pngs and "footprints_bottom.png" in pngs
    assert any(name.endswith("_intensity.png") for name in pngs)


def test_pass_stores_are_chunked_along_profiles(ci_sample, manifest, ci_config):
    _, entry = manifest.passes()[0]
    group = zarr.open_group(str(ci_sample / entry.file), mode="r")
    assert group["z_mm"].chunks == (ci_config.chunk_profiles, ci_config.scanner.points_per_profile)


def test_the_nominal_placement_puts_the_weld_line_within_its_tolerance(manifest, truth):
    """What the manifest says about where the fixture puts the specimen holds for the true
    placement: every point of the true weld centre line (both caps, both setups) lies within the
    stated tolerance of the nominal weld plane (through the manifest's weld lines), along the
    specimen's length."""
    (weld_x,) = {p[0] for line in manifest.weld_lines() for p in line.points_mm}  # lines across it, at one x
    for setup in manifest.setups:
        nominal, true = np.array(setup.T_world_specimen_nominal), np.array(truth.T_world_specimen[setup.name])
        assert 0 < setup.placement_tolerance_mm < 20
        line = np.array([[s.centre_x_mm, s.y_mm, 0.0] for s in truth.weld_sections])
        world = apply(true, line)
        along = (world - nominal[:3, 3]) @ nominal[:3, 0] - weld_x
        assert np.abs(along).max() <= setup.placement_tolerance_mm, (setup.name, np.abs(along).max())
        # and it is a tolerance, not a blanket: the line really strays from the nominal plane
        assert np.abs(along).max() > 0.05
