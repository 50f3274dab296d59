"""The ``tjoint`` presets: a closed T-joint with two convex fillet welds, stickers on base, stem,
walls and table, a manifest that describes a t-joint, the true toe lines, and the same files for
the same seed."""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.truth import read_true_toes, read_truth, read_truth_pass
from schemas.simulation import TrueMeshConfig, TJointConfig, WeldConfig
from simulator.presets import preset_config
from simulator.specimen import Face
from simulator.tjoint import build_tjoint, plan_tjoint_passes, tjoint_sticker_candidates

MESH = TrueMeshConfig(plate_dx_mm=2.0, weld_dx_mm=0.2, toe_dx_mm=0.1, wall_rows=5)


@pytest.fixture(scope="module")
def part():
    return build_tjoint(TJointConfig(along_weld_dx_mm=1.0), WeldConfig(), MESH, np.random.default_rng(3))


def assert_closed_and_oriented(mesh) -> None:
    """Every directed edge of the triangles once (consistently oriented) and its reverse too (closed)."""
    t = mesh.triangles.astype(np.int64)
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    n = len(mesh.vertices)
    keys = directed[:, 0] * n + directed[:, 1]
    assert len(np.unique(keys)) == len(keys)  # every directed edge once: consistently oriented ...
    assert np.isin(directed[:, 1] * n + directed[:, 0], keys).all()  # ... and its reverse too: closed


def test_the_part_is_one_closed_t_joint_of_the_drawing_size(part):
    assert_closed_and_oriented(part.mesh)
    lo, hi = part.mesh.vertices.min(axis=0), part.mesh.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [-130, -60, -6], atol=1e-9)
    np.testing.assert_allclose(hi, [130, 60, 66], atol=1e-9)
    plates = 260 * 120 * 12 + 10 * 60 * 120
    fillets = part.mesh.signed_volume_mm3() - plates  # two fillets of legs 6..8 mm, convex
    assert 2 * 120 * 0.5 * 6 * 6 < fillets < 2 * 120 * (0.5 * 8 * 8 + 1.2 * 8 * 1.42), fillets


def test_the_toes_lie_on_the_surface_where_the_legs_end(part):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(part.mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(part.mesh.triangles.astype(np.uint32)))
    assert len(part.toes) == 4
    for toe in part.toes:
        p = np.array(toe.points_mm)
        assert np.abs(scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()).max() < 0.02
        side = 1 if toe.weld == "fillet-pos" else -1
        if toe.plate == "base":  # on the base plate, a leg (6-8 mm) from the stem, lifted by the rounding (<= 0.5 mm)
            assert np.all((side * p[:, 0] > 5 + 5.5) & (side * p[:, 0] < 5 + 8.5)) and np.all(np.abs(p[:, 2] - 6) < 0.5)
        else:  # on the stem, a leg up from the base plate
            assert np.all(np.abs(side * p[:, 0] - 5) < 0.5) and np.all((p[:, 2] > 6 + 5.5) & (p[:, 2] < 6 + 8.5))


def test_sticker_candidates_avoid_the_welds_and_cover_the_walls_when_asked(part):
    config = preset_config("tjoint")
    c = tjoint_sticker_candidates(part, config)
    faces = set(np.unique(c.faces).tolist())
    assert faces == {Face.TOP, Face.BOTTOM, Face.STEM_NEG, Face.STEM_POS, Face.SIDE_NEG, Face.SIDE_POS,
                     Face.END_NEG, Face.END_POS}
    top = c.centres[c.faces == Face.TOP]
    assert np.abs(top[:, 0]).min() > 5 + 8 + 1.5 + 2  # clear of the fillets
    no_walls = tjoint_sticker_candidates(
        dataclasses.replace(part, config=part.config.model_copy(update={"wall_stickers": False})), config)
    assert not np.isin(no_walls.faces, (Face.SIDE_NEG, Face.SIDE_POS, Face.END_NEG, Face.END_POS)).any()


def test_the_plans_have_17_and_10_passes():
    for preset, setups, n in (("tjoint", ("top", "bottom"), 17), ("tjoint-single", ("top",), 10)):
        config = preset_config(preset)
        assert tuple(config.plan.setups) == setups
        assert len(plan_tjoint_passes(config, z_top_mm=92.0, setups=setups)) == n


def test_the_same_seed_draws_the_same_part(part):
    again = build_tjoint(TJointConfig(along_weld_dx_mm=1.0), WeldConfig(), MESH, np.random.default_rng(3))
    assert np.array_equal(again.mesh.vertices, part.mesh.vertices)
    assert np.array_equal(again.mesh.triangles, part.mesh.triangles)
    other = build_tjoint(TJointConfig(along_weld_dx_mm=1.0), WeldConfig(), MESH, np.random.default_rng(4))
    assert not np.array_equal(other.mesh.vertices, part.mesh.vertices)


def test_the_sample_describes_a_t_joint_and_its_truth(tjoint_sample):
    manifest = load_manifest(tjoint_sample)
    assert manifest.specimen.kind == "t-joint" and manifest.weld.joint == "double fillet"
    assert [line.name for line in manifest.weld_lines()] == ["fillet-neg", "fillet-pos"]
    assert [s.name for s in manifest.setups] == ["top", "bottom"] and len(manifest.passes()) == 17
    truth = read_truth(tjoint_sample / "truth" / "truth.json")
    toes = read_true_toes(tjoint_sample / "truth" / "toes.json")
    assert len(toes.toes) == 4 and toes.sample_id == manifest.sample_id
    on = {}
    for s in truth.stickers:
        on.setdefault(s.face, 0)
        on[s.face] += 1
    assert on["fixture"] == 8 and on["top"] >= 10 and on["bottom"] >= 10
    assert on["stem_neg"] >= 2 and on["stem_pos"] >= 2
    walls = {s.sticker_id for s in truth.stickers if s.face in ("side_neg", "side_pos", "end_neg", "end_pos")}
    assert len(walls) >= 20
    seen = {"top": set(), "bottom": set()}
    for p in truth.passes:
        tp = read_truth_pass(tjoint_sample / "truth" / "passes" / f"{p.pass_id}.zarr")
        seen[p.setup] |= set(np.unique(tp.sticker_id[tp.sticker_id >= 0]).tolist())
    both = seen["top"] & seen["bottom"]
    assert len(both & walls) >= 10  # the walls: what both setups see of the part
    specimen_ids = {s.sticker_id for s in truth.stickers if s.on == "specimen"}
    assert both & specimen_ids <= walls  # nothing else of the part is seen from both
