"""The ``cruciform`` preset (``TJointConfig.stems`` "both"): a closed cruciform joint, its lower
stem and fillets the upper ones' picture turned half a turn, four fillets' truth, stickers on both
stems, two stem-up setups, a manifest that describes a cruciform; and a T-joint's files unchanged
by the option (its config written without it)."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.truth import read_fillet_truth, read_true_toes, read_truth, read_truth_pass
from schemas.simulation import SimulationConfig, TJointConfig, TrueMeshConfig, WeldConfig
from simulator.presets import preset_config
from simulator.specimen import Face
from simulator.tjoint import TJoint, build_tjoint, constant_fillet, plan_tjoint_passes, tjoint_sticker_candidates
from tests.simulator.test_tjoint import assert_closed_and_oriented

MESH = TrueMeshConfig(plate_dx_mm=2.0, weld_dx_mm=0.2, toe_dx_mm=0.1, wall_rows=5)
CRUCIFORM = TJointConfig(along_weld_dx_mm=1.0, stems="both")


@pytest.fixture(scope="module")
def part():
    return build_tjoint(CRUCIFORM, WeldConfig(), MESH, np.random.default_rng(3))


def test_the_part_is_one_closed_cruciform_of_the_drawing_size(part):
    assert_closed_and_oriented(part.mesh)
    lo, hi = part.mesh.vertices.min(axis=0), part.mesh.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [-130, -60, -66], atol=1e-9)
    np.testing.assert_allclose(hi, [130, 60, 66], atol=1e-9)
    plates = 260 * 120 * 12 + 2 * 10 * 60 * 120
    fillets = part.mesh.signed_volume_mm3() - plates  # four fillets of legs 6..8 mm, convex
    assert 4 * 120 * 0.5 * 6 * 6 < fillets < 4 * 120 * (0.5 * 8 * 8 + 1.2 * 8 * 1.42), fillets
    names = {Face.NAMES[f] for f in np.unique(part.mesh.face_id)}
    assert {"stem_top", "stem_bottom", "bottom", "weld"} <= names
    end = part.mesh.face_id == Face.STEM_BOTTOM  # the lower stem's end: at z = -66, facing down
    v = part.mesh.vertices[part.mesh.triangles[end]]
    assert np.allclose(v[..., 2], -66) and (np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, 2] < 0).all()


def test_the_upper_fillets_are_the_t_joints_of_the_same_seed(part):
    """The upper fillets are drawn first: a T-joint from the same random stream has the same ones."""
    tee = build_tjoint(TJointConfig(along_weld_dx_mm=1.0), WeldConfig(), MESH, np.random.default_rng(3))
    ours = {s.weld: s for s in part.fillet_truth(step_mm=10.0).sections if s.y_mm == 0.0}
    theirs = {s.weld: s for s in tee.fillet_truth(step_mm=10.0).sections if s.y_mm == 0.0}
    assert sorted(ours) == ["fillet-bottom-neg", "fillet-bottom-pos", "fillet-top-neg", "fillet-top-pos"]
    assert ours["fillet-top-neg"].model_copy(update={"weld": "fillet-neg"}) == theirs["fillet-neg"]
    assert ours["fillet-top-pos"].model_copy(update={"weld": "fillet-pos"}) == theirs["fillet-pos"]
    assert ours["fillet-bottom-pos"].leg_base_mm != ours["fillet-top-pos"].leg_base_mm  # drawn anew


def test_the_toes_lie_on_the_surface_where_the_legs_end_on_both_faces(part):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(part.mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(part.mesh.triangles.astype(np.uint32)))
    assert len(part.toes) == 8
    for toe in part.toes:
        p = np.array(toe.points_mm)
        assert np.abs(scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()).max() < 0.02
        side = 1 if toe.weld.endswith("-pos") else -1
        face = 1 if "-top-" in toe.weld else -1
        x, z = side * p[:, 0], face * p[:, 2]  # in the upper x > 0 fillet's frame
        if toe.plate == "base":  # on the base plate, a leg (6-8 mm) from the stem, lifted by the rounding (<= 0.5 mm)
            assert np.all((x > 5 + 5.5) & (x < 5 + 8.5)) and np.all(np.abs(z - 6) < 0.5), toe.name
        else:  # on the stem, a leg out from the base plate's face
            assert np.all(np.abs(x - 5) < 0.5) and np.all((z > 6 + 5.5) & (z < 6 + 8.5)), toe.name


def test_a_section_of_equal_fillets_is_the_t_joints_turned_onto_its_other_face():
    """Four equal constant fillets: the outline is symmetric about both plates' mid-planes, and it
    encloses the T-joint's section plus its stem and fillets once more (shoelace areas)."""
    f = constant_fillet(leg_base=7.0, leg_stem=6.5, convexity=0.8, toe_radius_base=1.0, toe_radius_stem=0.6)
    tj = TJointConfig()
    tee = TJoint(config=tj, mesh=None, toes=[], fillets={1: f, -1: f})
    cross = TJoint(config=tj.model_copy(update={"stems": "both"}), mesh=None, toes=[], fillets={1: f, -1: f},
                   fillets_below={1: f, -1: f})
    spacing = 0.02
    loop, outward = cross.section(0.0, spacing)
    # every point's mirror images (x -> -x, z -> -z) lie on the outline
    from scipy.spatial import cKDTree
    tree = cKDTree(loop)
    for flip in ([-1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]):
        assert tree.query(loop * flip)[0].max() < spacing
    assert np.linalg.norm(np.diff(loop, axis=0), axis=1).min() > 0  # no point twice in a row

    def area(p):
        return 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))

    t_loop, _ = tee.section(0.0, spacing)
    plate = 260.0 * 12.0
    assert area(loop) > 0 and area(t_loop) > 0  # counter-clockwise
    assert abs((area(loop) - area(t_loop)) - (area(t_loop) - plate)) < 0.05, (area(loop), area(t_loop))
    # outward normals: down under the lower stem's end, up over the upper one's
    ends = np.abs(loop[:, 0]) < 4  # away from the stems' corners
    assert (outward[ends & (loop[:, 1] < -65.99), 1] < -0.999).sum() > 300
    assert (outward[ends & (loop[:, 1] > 65.99), 1] > 0.999).sum() > 300


def test_sticker_candidates_avoid_all_four_welds_and_cover_both_stems(part):
    c = tjoint_sticker_candidates(part, preset_config("cruciform"))
    for face in (Face.TOP, Face.BOTTOM):
        assert np.abs(c.centres[c.faces == face][:, 0]).min() > 5 + 8 + 1.5 + 2  # clear of the fillets
    stem = c.centres[np.isin(c.faces, (Face.STEM_NEG, Face.STEM_POS))]
    assert (stem[:, 2] > 6 + 8 + 1.5 + 2).sum() == (stem[:, 2] < -(6 + 8 + 1.5 + 2)).sum() > 100
    assert not (np.abs(stem[:, 2]) < 6 + 8 + 1.5 + 2).any()


def test_both_setups_are_scanned_stem_up():
    config = preset_config("cruciform")
    assert tuple(config.plan.setups) == ("top", "bottom") and config.tjoint.stems == "both"
    passes = plan_tjoint_passes(config, z_top_mm=92.0, setups=("top", "bottom"))
    top = [(p.direction, p.length_mm) for p in passes if p.setup == "top"]
    assert len(passes) == 20 and top == [(p.direction, p.length_mm) for p in passes if p.setup == "bottom"]


def test_a_t_joints_config_is_written_as_before_cruciforms():
    tee, cross = preset_config("tjoint"), preset_config("cruciform")
    assert "stems" not in tee.simulation_json() and "tjoint" not in preset_config("ci").simulation_json()
    assert json.loads(cross.simulation_json())["tjoint"]["stems"] == "both"
    for config in (tee, cross):
        assert SimulationConfig.model_validate_json(config.simulation_json()) == config


def test_the_sample_describes_a_cruciform_and_its_truth(cruciform_sample):
    manifest = load_manifest(cruciform_sample)
    assert manifest.specimen.kind == "cruciform" and manifest.weld.joint == "cruciform fillet"
    lines = {line.name: np.array(line.points_mm) for line in manifest.weld_lines()}
    assert list(lines) == ["fillet-top-neg", "fillet-top-pos", "fillet-bottom-neg", "fillet-bottom-pos"]
    for name, points in lines.items():  # the roots: a stem face (x = +-5) on a base face (z = +-6)
        assert np.allclose(points[:, 0], 5 if name.endswith("pos") else -5)
        assert np.allclose(points[:, 2], 6 if "-top-" in name else -6)
    assert [s.name for s in manifest.setups] == ["top", "bottom"] and len(manifest.passes()) == 20
    fillets = read_fillet_truth(cruciform_sample / "truth" / "fillet_weld.json")
    assert {s.weld for s in fillets.sections} == set(lines) and len(fillets.sections) == 4 * 121
    toes = read_true_toes(cruciform_sample / "truth" / "toes.json")
    assert {(t.weld, t.plate) for t in toes.toes} == {(w, p) for w in lines for p in ("base", "stem")}
    truth = read_truth(cruciform_sample / "truth" / "truth.json")
    on: dict = {}
    for s in truth.stickers:
        key = (s.face, s.centre_mm[2] > 0)
        on[key] = on.get(key, 0) + 1
    assert on[("top", True)] >= 10 and on[("bottom", False)] >= 10
    for upper in (True, False):  # on each stem
        assert on.get(("stem_neg", upper), 0) + on.get(("stem_pos", upper), 0) >= 2, on
    walls = {s.sticker_id for s in truth.stickers if s.face in ("side_neg", "side_pos", "end_neg", "end_pos")}
    seen = {"top": set(), "bottom": set()}
    for p in truth.passes:
        tp = read_truth_pass(cruciform_sample / "truth" / "passes" / f"{p.pass_id}.zarr")
        seen[p.setup] |= set(np.unique(tp.sticker_id[tp.sticker_id >= 0]).tolist())
    assert len(seen["top"] & seen["bottom"] & walls) >= 10  # the walls: what both setups see of the part
