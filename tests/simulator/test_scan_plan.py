"""``weldrecon plan``: a plan of the ci coupon that meets its requirements, its folder's files,
its scan in the simulated cell (the guarantee checked against the truth), and the plans it
refuses, naming the face or pass pair; a T-joint's plan likewise, its fillets' toes measured
from two directions."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.truth import read_truth
from schemas.manifest import Setup
from schemas.scan_plan import PlanRequirements, ReachModel, ScanPlan
from simulator.coverage import spread_off_line_mm
from simulator.plan_files import PLAN_NAME, PlanFolderError, read_plan, write_plan_folder
from simulator.planner import PlanRefused, plan_scan
from simulator.presets import preset_config
from simulator.robot import plan_passes
from simulator.run import plan_config, simulate
from tests.flows.cli import weldrecon


@pytest.fixture(scope="module")
def ci_plan() -> ScanPlan:
    return plan_scan(preset_config("ci"), PlanRequirements())


@pytest.fixture(scope="module")
def plan_dir(ci_plan, tmp_path_factory):
    return write_plan_folder(ci_plan, tmp_path_factory.mktemp("plan") / "ci-plan")


@pytest.fixture(scope="module")
def planned_sample(plan_dir, tmp_path_factory):
    plan = read_plan(plan_dir)
    return simulate(plan_config(plan, sample_id="sim-ci-plan"), tmp_path_factory.mktemp("planned") / "sample",
                    previews=False, plan=plan).out_dir


def _hand_plan_seconds(config) -> float:
    hand = plan_passes(config.plan, config.specimen, config.robot,
                       z_top_mm=config.fixture.block_size_mm[2] + config.specimen.thickness_mm,
                       standoff_mm=config.scanner.reference_distance_mm, setups=tuple(config.plan.setups))
    return sum(p.duration_s for p in hand)


def test_the_plan_meets_its_requirements_and_is_faster_than_the_hand_made_one(ci_plan):
    req, stickers = ci_plan.requirements, ci_plan.part.stickers
    assert all(t.both_sides >= req.toe_coverage for t in ci_plan.toes) and len(ci_plan.toes) == 4
    assert {f.face for f in ci_plan.faces} >= {"top", "bottom", "side_neg", "side_pos", "end_neg", "end_pos"}
    assert all(f.seen >= req.face_coverage for f in ci_plan.faces)
    by_id = {s.sticker_id: np.array(s.centre_mm) for s in ci_plan.stickers}
    assert ci_plan.overlaps
    for o in ci_plan.overlaps:  # every overlap holds three whole stickers off a line, recomputed here
        assert len(o.sticker_ids) >= stickers.min_common
        assert spread_off_line_mm(np.array([by_id[k] for k in o.sticker_ids])) >= stickers.min_spread_mm
    # every pass is tied into its setup
    for setup in req.setups:
        ids = {p.pass_id for p in ci_plan.passes if p.setup == setup}
        reached = {next(iter(sorted(ids)))}
        grown = True
        while grown:
            grown = False
            for o in ci_plan.overlaps:
                if (o.pass_a in reached) != (o.pass_b in reached) and {o.pass_a, o.pass_b} <= ids:
                    reached |= {o.pass_a, o.pass_b}
                    grown = True
        assert reached == ids
    (link,) = ci_plan.setup_links
    assert len(link.sticker_ids) >= req.min_setup_stickers and link.spread_mm >= stickers.min_spread_mm
    assert ci_plan.scan_time_s == pytest.approx(sum(p.duration_s for p in ci_plan.passes))
    assert ci_plan.scan_time_s < _hand_plan_seconds(preset_config("ci"))


def test_the_plan_is_the_same_bytes_when_made_again(ci_plan):
    again = plan_scan(preset_config("ci"), PlanRequirements())
    assert again.model_dump_json() == ci_plan.model_dump_json()


def test_the_plan_folder_holds_the_program_the_manifest_setups_and_1_to_1_sticker_maps(ci_plan, plan_dir):
    assert read_plan(plan_dir) == ci_plan
    setups = [Setup.model_validate(s) for s in json.loads((plan_dir / "manifest_setups.json").read_text())["setups"]]
    assert [s.name for s in setups] == ci_plan.requirements.setups
    assert sum(len(s.passes) for s in setups) == len(ci_plan.passes)
    rows = list(csv.DictReader((plan_dir / "robot_program.csv").open()))
    assert len(rows) == 2 * len(ci_plan.passes)
    for p in ci_plan.passes:  # start and end TCPs: the start pose, then the pass's length along its travel
        start, end = (np.array([float(r[k]) for k in ("x_mm", "y_mm", "z_mm")]) for r in rows
                      if r["pass_id"] == p.pass_id)
        assert np.allclose(start, np.asarray(p.T_world_sensor_start)[:3, 3], atol=1e-3)
        assert np.linalg.norm(end - start) == pytest.approx(p.length_mm, abs=1e-3)
    program = json.loads((plan_dir / "robot_program.json").read_text())
    assert [q["pass_id"] for q in program["passes"]] == [p.pass_id for p in ci_plan.passes]
    length = ci_plan.part.specimen.length_mm
    faces_with_stickers = {s.face for s in ci_plan.stickers}
    for face in faces_with_stickers:
        svg = (plan_dir / f"stickers-{face}.svg").read_text()
        width_mm = float(re.search(r'width="([0-9.]+)mm"', svg).group(1))
        view_w = float(re.search(r'viewBox="0 0 ([0-9.]+) ', svg).group(1))
        assert width_mm == pytest.approx(view_w, abs=0.1)  # one user unit is one millimetre: prints 1:1
        assert width_mm >= length
        assert svg.count("<circle") == sum(1 for s in ci_plan.stickers if s.face == face)
    page = (plan_dir / "plan.html").read_text()
    assert f"{ci_plan.scan_time_s:.0f} s" in page and 'aria-label="overlap graph"' in page


def test_the_simulated_scan_of_the_plan_keeps_the_plans_promise(ci_plan, planned_sample):
    truth = read_truth(planned_sample / "truth" / "truth.json")
    manifest = load_manifest(planned_sample)
    assert [p.pass_id for _, p in manifest.passes()] == [p.pass_id for p in ci_plan.passes]
    assert sum(1 for s in truth.stickers if s.on == "specimen") == len(ci_plan.stickers)
    for o in ci_plan.overlaps:  # what the plan promised, every sticker seen whole by both passes
        seen = set(truth.common_stickers[f"{o.pass_a}|{o.pass_b}"])
        assert set(o.sticker_ids) <= seen, (o.pass_a, o.pass_b)
    # the part was put within the plan's tolerance
    tol = ci_plan.requirements.placement_tolerance_mm
    for setup, T in truth.T_world_specimen.items():
        assert np.all(np.abs(np.asarray(T)[:2, 3]) <= tol + 1e-9)


def test_a_face_the_robot_cannot_reach_is_refused_by_name():
    req = PlanRequirements(reach=ReachModel(max_tilt_deg=20.0))
    with pytest.raises(PlanRefused) as refused:
        plan_scan(preset_config("ci"), req)
    assert any(p.startswith("faces side_neg and side_pos:") and "20 deg" in p for p in refused.value.problems)


@pytest.mark.parametrize("diameter, expected", [
    (8.0, r"passes [a-z]+-[A-Z]\d\d and [a-z]+-[A-Z]\d\d overlap but leave no room for sticker 3 of 3"),
    (12.0, r"passes along the weld \(W\) and the face rows \(F\) .* 11.9 mm are needed for 3 stickers of 12 mm"),
])
def test_a_part_too_small_for_three_stickers_per_overlap_is_refused_naming_the_passes(diameter, expected):
    config = preset_config("ci")
    config = config.model_copy(update={"stickers": config.stickers.model_copy(update={"diameter_mm": diameter})})
    with pytest.raises(PlanRefused) as refused:
        plan_scan(config, PlanRequirements())
    assert any(re.search(expected, p) for p in refused.value.problems), refused.value.problems


def test_the_command_line_writes_a_plan_and_refuses_one_line_per_problem(tmp_path):
    requirements = tmp_path / "req.yaml"
    requirements.write_text("reach:\n  max_tilt_deg: 20\n")
    done = weldrecon("plan", "ci", "--out", str(tmp_path / "refused"), "--requirements", str(requirements))
    assert done.returncode == 2 and not (tmp_path / "refused").exists()
    lines = done.stderr.strip().splitlines()
    assert lines[-1] == f"weldrecon plan: no plan written to {tmp_path / 'refused'}"
    assert all(line.startswith("weldrecon plan: refused: ") for line in lines[:-1] if not line.startswith("["))
    requirements.write_text("toe_coverage: 2\n")
    done = weldrecon("plan", "ci", "--out", str(tmp_path / "bad"), "--requirements", str(requirements))
    assert done.returncode == 2 and "toe_coverage" in done.stderr and not (tmp_path / "bad").exists()


def test_simulate_names_the_field_of_a_broken_plan(plan_dir, tmp_path):
    broken = tmp_path / "broken"
    broken.mkdir()
    doc = json.loads((plan_dir / PLAN_NAME).read_text())
    doc["passes"][0]["speed_mm_s"] = -1
    (broken / PLAN_NAME).write_text(json.dumps(doc))
    with pytest.raises(PlanFolderError, match=r"plan.json: field passes.0.speed_mm_s"):
        read_plan(broken)
    done = weldrecon("simulate", str(tmp_path / "out"), "--plan", str(broken))
    assert done.returncode == 2 and "passes.0.speed_mm_s" in done.stderr and not (tmp_path / "out").exists()
    done = weldrecon("simulate", str(tmp_path / "out"), "--plan", str(tmp_path / "nowhere"))
    assert done.returncode == 2 and "no plan.json" in done.stderr
    done = weldrecon("simulate", str(tmp_path / "out"), "--plan", str(plan_dir), "--preset", "ci")
    assert done.returncode == 2 and "leave out --preset" in done.stderr


def test_toes_are_seen_from_both_sides_only_by_passes_leaning_across_them(ci_plan):
    """Known answers: rows straight down (the plan's own face rows, alone) light no toe from either
    side; its two sweeps along the weld, pitched either way, light every toe from both."""
    from simulator.planner import evaluate_passes, planned_passes

    passes = {p.pass_id: p for p in planned_passes(ci_plan)}
    purpose = {p.pass_id: p.purpose for p in ci_plan.passes}
    rows = [p for k, p in passes.items() if purpose[k] == "face"]
    welds = [p for k, p in passes.items() if purpose[k] == "weld"]
    alone = evaluate_passes(ci_plan.part, ci_plan.requirements, rows, stickers=False)
    assert all(t.plate_side == 0 and t.weld_side == 0 for t in alone.toes)
    assert any(p.startswith("toe top-neg: 0.0 %") for p in alone.problems)
    swept = evaluate_passes(ci_plan.part, ci_plan.requirements, welds, stickers=False)
    assert all(t.both_sides == 1.0 for t in swept.toes)
    one_way = evaluate_passes(ci_plan.part, ci_plan.requirements, [p for p in welds if p.setup == "top"][:1],
                              stickers=False)
    top = {t.toe: t for t in one_way.toes}
    # one sweep pitched one way: one top toe from over its plate, the other from over the weld
    assert {(top["top-neg"].plate_side, top["top-neg"].weld_side), (top["top-pos"].plate_side,
                                                                     top["top-pos"].weld_side)} == {(1.0, 0.0), (0.0, 1.0)}


def test_a_samples_manifest_is_a_part_to_plan(ci_sample, tmp_path):
    """PART may be a sample (its manifest): the plan is of the dog-bone, stickers and scanner it
    describes; a manifest of a part the planner has no passes for is refused naming the file."""
    manifest = load_manifest(ci_sample)
    # a manifest does not say what welds to expect: the coupon's narrower caps (the ci preset's
    # ranges) given with --config, as a lab would for its own parts
    config = tmp_path / "part.yaml"
    config.write_text("weld:\n  cap_height_mm: [1.5, 3.0]\n  cap_width_mm: [10.0, 13.0]\n"
                      "  flank_angle_deg: [30.0, 60.0]\n")
    done = weldrecon("plan", str(ci_sample), "--out", str(tmp_path / "plan"), "--config", str(config))
    assert done.returncode == 0, done.stderr
    plan = read_plan(tmp_path / "plan")
    assert plan.part.specimen.length_mm == manifest.specimen.length_mm
    assert plan.part.scanner.points_per_profile == manifest.scanner.points_per_profile
    assert plan.part.stickers.diameter_mm == manifest.sticker_diameter_mm
    assert all(t.both_sides >= plan.requirements.toe_coverage for t in plan.toes)
    tjoint = tmp_path / "tjoint.json"
    doc = json.loads((ci_sample / "manifest.json").read_text())
    doc["specimen"] = {"kind": "plate", "length_mm": 200.0, "width_mm": 100.0, "thickness_mm": 10.0}
    tjoint.write_text(json.dumps(doc))
    done = weldrecon("plan", str(tjoint), "--out", str(tmp_path / "refused"))
    assert done.returncode == 2 and not (tmp_path / "refused").exists()
    assert f"{tjoint}: part: plate is not planned yet" in done.stderr


# --- a T-joint ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tjoint_plan() -> ScanPlan:
    return plan_scan(preset_config("tjoint"), PlanRequirements())


def _hand_tjoint_passes(config):
    from simulator.tjoint import plan_tjoint_passes

    return plan_tjoint_passes(config, z_top_mm=config.fixture.block_size_mm[2] + config.tjoint.base_thickness_mm,
                              setups=tuple(config.plan.setups))


def test_a_t_joint_plan_sees_every_face_and_both_toes_of_each_fillet_from_two_directions(tjoint_plan):
    req, stickers = tjoint_plan.requirements, tjoint_plan.part.stickers
    assert {t.toe for t in tjoint_plan.toes} == {f"fillet-{s}-{p}" for s in ("neg", "pos") for p in ("base", "stem")}
    assert all(t.rule == "two directions" and t.both_sides >= req.toe_coverage for t in tjoint_plan.toes)
    assert {f.face for f in tjoint_plan.faces} == {"top", "bottom", "side_neg", "side_pos", "end_neg", "end_pos",
                                                    "stem_neg", "stem_pos", "stem_top", "weld"}
    assert all(f.seen >= req.face_coverage for f in tjoint_plan.faces)
    by_id = {s.sticker_id: np.array(s.centre_mm) for s in tjoint_plan.stickers}
    for o in tjoint_plan.overlaps:
        assert len(o.sticker_ids) >= stickers.min_common
        assert spread_off_line_mm(np.array([by_id[k] for k in o.sticker_ids])) >= stickers.min_spread_mm
    # the setups share stickers on the base plate's walls only (the only faces both see), one
    # every wall_sticker_pitch_mm (20 mm) along the walls the passes of both setups see whole: 8 or
    # more on each of the two 260 mm long walls (measured: 9 and 10)
    (link,) = tjoint_plan.setup_links
    faces = {s.sticker_id: s.face for s in tjoint_plan.stickers}
    assert {faces[k] for k in link.sticker_ids} <= {"side_neg", "side_pos", "end_neg", "end_pos"}
    assert len(link.sticker_ids) >= max(req.min_setup_stickers, 16)
    # no sticker in a weld's keep-out: on the base beyond it, on the stem above it
    keep = tjoint_plan.no_sticker_x_mm[1]
    x0 = tjoint_plan.part.tjoint.stem_thickness_mm / 2
    z0 = tjoint_plan.part.tjoint.base_thickness_mm / 2
    for s in tjoint_plan.stickers:
        if s.face == "top":
            assert abs(s.centre_mm[0]) > keep + stickers.diameter_mm / 2 - 1e-6
        if s.face.startswith("stem_"):
            assert s.centre_mm[2] > z0 + keep - x0 + stickers.diameter_mm / 2 - 1e-6
    hand = _hand_tjoint_passes(preset_config("tjoint"))
    assert tjoint_plan.scan_time_s < sum(p.duration_s for p in hand)


def test_a_t_joint_plans_folder_and_its_simulated_scan_keep_the_promise(tjoint_plan, tmp_path):
    folder = write_plan_folder(tjoint_plan, tmp_path / "plan")
    setups = json.loads((folder / "manifest_setups.json").read_text())["setups"]
    assert [s["name"] for s in setups] == ["top", "bottom"] and "stem up" in setups[0]["description"]
    for face in {s.face for s in tjoint_plan.stickers}:
        svg = (folder / f"stickers-{face}.svg").read_text()
        assert svg.count("<circle") == sum(1 for s in tjoint_plan.stickers if s.face == face)
        w, h = (float(v) for v in re.search(r'viewBox="0 0 ([\d.]+) ([\d.]+)"', svg).groups())
        assert f'width="{w:.1f}mm" height="{h:.1f}mm"' in svg  # 1 unit = 1 mm
    # the top face from above, 15 mm of paper around it: a mark where the sticker goes
    tj = tjoint_plan.part.tjoint
    top = next(s for s in tjoint_plan.stickers if s.face == "top")
    svg = (folder / "stickers-top.svg").read_text()
    x, y = top.centre_mm[0] + tj.base_length_mm / 2 + 15.0, 15.0 + tj.base_width_mm / 2 - top.centre_mm[1]
    assert f'<circle cx="{x:.3f}" cy="{y:.3f}"' in svg
    plan = read_plan(folder)
    sample = simulate(plan_config(plan, sample_id="sim-tjoint-plan"), tmp_path / "sample", previews=False,
                      plan=plan).out_dir
    truth = read_truth(sample / "truth" / "truth.json")
    assert sum(1 for s in truth.stickers if s.on == "specimen") == len(plan.stickers)
    for o in plan.overlaps:
        assert set(o.sticker_ids) <= set(truth.common_stickers[f"{o.pass_a}|{o.pass_b}"]), (o.pass_a, o.pass_b)
    manifest = load_manifest(sample)
    assert manifest.specimen.kind == "t-joint"
    assert [p.pass_id for _, p in manifest.passes()] == [p.pass_id for p in plan.passes]


def test_a_fillets_toes_are_measured_from_two_directions_only_by_passes_that_give_them(tjoint_plan):
    """Known answers on the T-joint: the rows over the base (their views straight down across the
    toes, tilted along them) alone see its base toes from one direction and its stem toes (the
    stem's face edge-on) not at all; the two passes
    along one fillet, rolled 40 and 65 deg toward it, measure its stem toe from two directions and
    its base toe from one (at the base toe the 65 deg pass is past the 60 deg incidence limit),
    and the other fillet's toes from none; with the rows on their side, the base toe from two."""
    from simulator.planner import evaluate_passes, planned_passes

    passes = planned_passes(tjoint_plan)
    info = {p.pass_id: p for p in tjoint_plan.passes}
    rows = [p for p in passes if info[p.pass_id].purpose == "face" and p.setup == "top"
            and abs(info[p.pass_id].roll_deg) < 1e-6]
    alone = {t.toe: t for t in evaluate_passes(tjoint_plan.part, tjoint_plan.requirements, rows, stickers=False).toes}
    for side in ("neg", "pos"):
        assert alone[f"fillet-{side}-base"].plate_side > 0.9 and alone[f"fillet-{side}-base"].both_sides == 0
        assert alone[f"fillet-{side}-stem"].both_sides == 0
    # the passes along the fillet at +x: rolled toward -x (their views lean that way)
    fillet_pos = [p for p in passes if info[p.pass_id].purpose == "weld" and p.setup == "top"
                  and p.T_world_sensor_start[0, 2] < 0]
    assert sorted(abs(info[p.pass_id].roll_deg) for p in fillet_pos) == [40.0, 65.0]

    def toes(chosen):
        return {t.toe: t for t in evaluate_passes(tjoint_plan.part, tjoint_plan.requirements, chosen,
                                                  stickers=False).toes}

    two = toes(fillet_pos)
    assert two["fillet-pos-stem"].both_sides == 1.0
    assert two["fillet-pos-base"].plate_side == 1.0 and two["fillet-pos-base"].both_sides == 0
    assert two["fillet-neg-base"].both_sides == 0 and two["fillet-neg-stem"].both_sides == 0
    with_rows = toes(fillet_pos + [p for p in rows if p.T_world_sensor_start[0, 3] > 0])
    assert with_rows["fillet-pos-base"].both_sides == 1.0
    shallow = [p for p in fillet_pos if abs(info[p.pass_id].roll_deg) == 40.0]
    one = toes(shallow)
    assert one["fillet-pos-stem"].plate_side == 1.0 and one["fillet-pos-stem"].both_sides == 0


def test_a_t_joint_the_robot_cannot_lean_to_is_refused_naming_its_fillets():
    with pytest.raises(PlanRefused) as refused:
        plan_scan(preset_config("tjoint"), PlanRequirements(reach=ReachModel(max_tilt_deg=30.0)))
    assert any(p.startswith("the fillets' toes: the steeper of the passes along them lean 60 to 65 deg")
               for p in refused.value.problems)


def test_a_t_joint_or_cruciform_manifest_is_a_part_to_plan(tmp_path):
    """A manifest's T-joint (or cruciform) is planned as drawn: its plates' figures, its scanner,
    stickers and speed; a stem off the base plate's middle is refused naming the field."""
    from simulator.planner import part_from_manifest
    from simulator.run import _manifest

    for preset in ("tjoint", "cruciform"):
        config = preset_config(preset)
        manifest = _manifest(config, _hand_tjoint_passes(config), {})
        part = part_from_manifest(manifest, source="manifest.json")
        for name in ("stems", "base_length_mm", "base_width_mm", "base_thickness_mm", "stem_height_mm",
                     "stem_thickness_mm"):
            assert getattr(part.tjoint, name) == getattr(config.tjoint, name), name
        assert part.scanner.points_per_profile == config.scanner.points_per_profile
        assert part.robot.profile_spacing_mm == pytest.approx(config.robot.profile_spacing_mm)
        assert part.stickers.diameter_mm == config.stickers.diameter_mm
        assert part.fixture.block_size_mm[2] > config.tjoint.stem_height_mm  # turned over, the stem hangs free
    off = manifest.model_copy(update={"specimen": manifest.specimen.model_copy(update={"stem_x_mm": 20.0})})
    with pytest.raises(PlanRefused, match=r"manifest.json: specimen: the planner draws the stem .* \(stem_x_mm 0\); this part's is at 20 mm"):
        part_from_manifest(off, source="manifest.json")


def test_a_positioner_plan_turns_the_part_by_the_positioner_in_its_setups_and_its_scan(ci_plan, tmp_path):
    """``weldrecon plan --positioner``: the same passes and stickers; the bottom setup is the top
    turned by the positioner (the manifest's setups say so), and the plan's simulated scan turns
    the part about the positioner's true axis, not by hand."""
    from schemas.simulation import PositionerConfig
    from simulator.plan_files import manifest_setups

    plan = ci_plan.model_copy(update={"part": ci_plan.part.model_copy(update={"positioner": PositionerConfig()})})
    top, bottom = manifest_setups(plan)
    assert top.positioner is None and bottom.positioner.from_setup == "top" and bottom.positioner.angle_deg == 180
    assert "positioner" in bottom.description
    sample = simulate(plan_config(plan, sample_id="sim-ci-plan-turned"), tmp_path / "sample", previews=False,
                      plan=plan).out_dir
    truth = read_truth(sample / "truth" / "truth.json")
    assert truth.positioner is not None and truth.positioner.setup == "bottom"
    assert load_manifest(sample).setups[1].positioner == bottom.positioner
    done = weldrecon("plan", "ci", "--positioner", "--out", str(tmp_path / "plan"), "--requirements",
                     str(_write(tmp_path / "r.yaml", "reach:\n  max_tilt_deg: 20\n")))
    assert done.returncode == 2  # refused as without the positioner: it does not reach the walls either


def _write(path, text):
    path.write_text(text)
    return path
