"""The commands that use the simulator, and the only code of ``flows`` that may import it
(tests/test_layering.py): ``simulate`` (the simulator's own command line), ``demo`` (simulates
the demo sample, then reconstructs it) and ``export-cell`` (a sample written as a cell's logs,
for trying ``import`` on known data)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["add_simulate", "add_demo", "add_export_cell", "add_plan"]

_DEMO_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "configs" / "demo.yaml"


def add_simulate(sub) -> None:
    sim = sub.add_parser("simulate", help="simulate a scanning cell's output for one sample")
    sim.add_argument("out_dir", metavar="OUT_DIR", help="new folder for the sample (must not exist)")
    sim.add_argument("--preset", help="ci, demo, paper, tjoint, tjoint-single or cruciform (default: demo)")
    sim.add_argument("--plan", metavar="PLAN_DIR", help="scan a plan made by `weldrecon plan` (its part, passes and "
                     "sticker map) instead of a preset's")
    sim.add_argument("--config", metavar="FILE", help="YAML file of fields that override the preset")
    sim.add_argument("--seed", type=int, help="override the preset's seed")
    sim.add_argument("--sample-id", help="override the preset's sample id")
    sim.add_argument("--no-preview", action="store_true", help="skip the PNG pictures")
    sim.add_argument("--pace", metavar="realtime|xN", help="write the manifest first, then each pass when the robot "
                     "would have finished it, at its speed (realtime) or N times faster (xN): for --follow")
    sim.set_defaults(func=_cmd_simulate)


def add_plan(sub) -> None:
    plan = sub.add_parser("plan", help="plan the passes and stickers of a scan from the part's drawing")
    plan.add_argument("part", metavar="PART", help="the part: a simulator preset's (demo, paper, ci, ...), or a sample's "
                      "manifest.json (or its folder): the dog-bone, T-joint or cruciform, stickers and scanner it describes")
    plan.add_argument("--out", required=True, metavar="PLAN_DIR", help="new folder for the plan (must not exist)")
    plan.add_argument("--config", metavar="FILE", help="YAML file of fields that override the part's (as simulate's)")
    plan.add_argument("--requirements", metavar="FILE", help="YAML file of the plan's requirements "
                      "(schemas/scan_plan.py, PlanRequirements): coverage, placement tolerance, the robot's reach")
    plan.add_argument("--positioner", action="store_true", help="the cell's positioner turns the part between its "
                      "setups (about its length, through its mid-plane; the part config's positioner: to give the "
                      "calibrated axis) instead of a hand")
    plan.set_defaults(func=_cmd_plan)


def add_demo(sub) -> None:
    demo = sub.add_parser("demo", help="simulate the demo sample (once) and reconstruct it")
    demo.add_argument("--out", default="out/demo", help="folder for the sample and its reconstruction")
    demo.set_defaults(func=_cmd_demo)


def add_export_cell(sub) -> None:
    exp = sub.add_parser("export-cell", help="write a sample (with flange poses per profile) as cell logs + CELL.yaml")
    exp.add_argument("sample_dir", metavar="SAMPLE", help="folder with manifest.json and the passes")
    exp.add_argument("out_dir", metavar="OUT_DIR", help="new folder for CELL.yaml and the logs (must not exist)")
    exp.add_argument("--layout", choices=("xzi", "z_grid"), default="xzi", help="profile layout (default xzi)")
    exp.add_argument("--delimiter", choices=("csv", "whitespace"), default="csv")
    exp.add_argument("--gzip", action="store_true", help="gzip the profile files")
    exp.add_argument("--orientation", default="quaternion", help="rotation convention of the pose log: quaternion, "
                     "rotation-vector, kuka-abc, fanuc-wpr or euler-<AXES>-<intrinsic|extrinsic> (default quaternion)")
    exp.add_argument("--quaternion-order", choices=("wxyz", "xyzw"), default="wxyz")
    exp.add_argument("--angle-unit", choices=("deg", "rad"), help="for rotation-vector and euler-*")
    exp.add_argument("--units", choices=("mm", "m"), default="mm", help="length unit of both files (default mm)")
    exp.add_argument("--time-unit", choices=("s", "ms"), default="s")
    exp.add_argument("--no-return", default="nan", metavar="nan|empty|NUMBER", help="marker of a missing return")
    exp.add_argument("--intensity-bits", type=int, default=10, help="bit depth of the written intensities (default 10)")
    exp.add_argument("--pose-every", type=int, default=3, metavar="N", help="a pose for every N-th profile (default 3)")
    exp.add_argument("--time-offset", type=float, default=0.0, metavar="S",
                     help="the robot's clock minus the scanner's, s (default 0)")
    exp.set_defaults(func=_cmd_export_cell)


def _describe(error) -> str:
    """A pydantic ``ValidationError`` as one indented line per wrong field."""
    return "\n".join(f"  {'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in error.errors())


def _deep_merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _deep_merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return out


def _simulation_config(args: argparse.Namespace):
    from pydantic import ValidationError

    from data_catalog.textfiles import read_yaml_mapping
    from schemas.simulation import SimulationConfig
    from simulator.presets import preset_config

    base = preset_config(args.preset or "demo").model_dump()
    if args.config is not None:
        base = _deep_merge(base, read_yaml_mapping(args.config, "simulation config"))
    if args.seed is not None:
        base["seed"] = args.seed
    if args.sample_id is not None:
        base["sample_id"] = args.sample_id
    try:
        return SimulationConfig.model_validate(base)
    except ValidationError as exc:
        source = args.config or f"preset {args.preset or 'demo'}"
        raise ValueError(f"{source}: invalid simulation config:\n{_describe(exc)}") from None


def _pace(text: str) -> float:
    """``realtime`` (the robot's own speed) or ``xN`` (N times faster) as a speed-up factor."""
    if text == "realtime":
        return 1.0
    try:
        factor = float(text[1:]) if text.startswith("x") else float("nan")
    except ValueError:
        factor = float("nan")
    if not factor > 0:
        raise ValueError(f"--pace {text!r}: expected realtime or xN with N > 0 (x10: ten times the robot's speed)")
    return factor


def _cmd_plan(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from simulator.plan_files import write_plan_folder
    from simulator.planner import PlanRefused, plan_scan

    from data_catalog.atomic import check_can_create
    from data_catalog.textfiles import read_yaml_mapping
    from schemas.scan_plan import PlanRequirements

    if Path(args.part).exists():  # a sample's manifest (or its folder): the part it describes
        from pydantic import ValidationError as _Invalid

        from data_catalog.manifests import load_manifest
        from simulator.planner import part_from_manifest

        try:
            config = part_from_manifest(load_manifest(Path(args.part)), source=args.part)
        except PlanRefused as exc:
            raise ValueError(str(exc)) from None
        if args.config is not None:
            try:
                config = type(config).model_validate(_deep_merge(config.model_dump(),
                                                                 read_yaml_mapping(args.config, "part config")))
            except _Invalid as exc:
                raise ValueError(f"{args.config}: invalid part config:\n{_describe(exc)}") from None
    else:
        config = _simulation_config(argparse.Namespace(preset=args.part, config=args.config, seed=None, sample_id=None))
    if args.positioner and config.positioner is None:
        from schemas.simulation import PositionerConfig

        config = config.model_copy(update={"positioner": PositionerConfig()})
    out = Path(args.out)
    if out.exists():
        raise ValueError(f"--out {out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"--out {out}")
    fields = read_yaml_mapping(args.requirements, "plan requirements") if args.requirements else {}
    try:
        requirements = PlanRequirements.model_validate(fields)
    except ValidationError as exc:
        raise ValueError(f"{args.requirements}: invalid plan requirements:\n{_describe(exc)}") from None
    started = time.perf_counter()

    def progress(message: str) -> None:
        print(f"[{time.perf_counter() - started:7.1f} s] {message}", file=sys.stderr, flush=True)

    progress(f"planning the scan of {config.sample_id!r} (part {args.part})")
    try:
        plan = plan_scan(config, requirements, progress=progress)
    except PlanRefused as exc:
        for problem in exc.problems:
            print(f"weldrecon plan: refused: {problem}", file=sys.stderr)
        print(f"weldrecon plan: no plan written to {out}", file=sys.stderr)
        return 2
    write_plan_folder(plan, out)
    print(f"{out}: {len(plan.passes)} passes, {plan.scan_time_s:.0f} s ({plan.scan_time_s / 60:.1f} min) of scanning, "
          f"{len(plan.stickers)} stickers; the plan page: {out / 'plan.html'}")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from simulator.plan_files import read_plan
    from simulator.run import plan_config, simulate

    from data_catalog.atomic import check_can_create

    plan = None
    if args.plan is not None:
        if args.preset is not None or args.config is not None:
            raise ValueError("--plan gives the part, its scanner and its passes: leave out --preset and --config")
        plan = read_plan(Path(args.plan))
        config = plan_config(plan, seed=args.seed, sample_id=args.sample_id)
    else:
        config = _simulation_config(args)
    out = Path(args.out_dir)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_DIR {out}")
    started = time.perf_counter()

    def progress(message: str) -> None:
        print(f"[{time.perf_counter() - started:7.1f} s] {message}", file=sys.stderr, flush=True)

    pace = _pace(args.pace) if args.pace is not None else None
    progress(f"simulating preset {config.preset!r} (seed {config.seed}) into {out}")
    summary = simulate(config, out, progress=progress, previews=not args.no_preview, pace=pace, plan=plan)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_points:,} points "
          f"({summary.n_valid_points:,} returns), {summary.n_stickers_specimen} stickers on the specimen, "
          f"{summary.n_stickers_fixture} on the fixture, {summary.seconds:.1f} s")
    if not args.no_preview:
        print(f"pictures: {summary.out_dir / 'preview'}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from simulator.presets import preset_config
    from simulator.run import simulate

    from data_catalog.atomic import check_can_create
    from flows.cli.reconstruct import run_reconstruct

    root = Path(args.out)
    check_can_create(root, f"--out {root}")
    sample = root / "sample"
    if not sample.exists():
        started = time.perf_counter()
        print(f"simulating the demo sample into {sample} ...", file=sys.stderr, flush=True)
        summary = simulate(preset_config("demo"), sample)
        print(f"  {summary.n_passes} passes, {summary.n_points:,} points, {time.perf_counter() - started:.0f} s",
              file=sys.stderr)
    args = argparse.Namespace(sample_dir=str(sample), out=str(root / "reconstruction"),
                              config=str(_DEMO_CONFIG) if _DEMO_CONFIG.is_file() else None)
    print("reconstructing ...", file=sys.stderr, flush=True)
    return run_reconstruct(args)


def _no_return(text: str) -> str | float:
    """``--no-return``: nan, empty or a number."""
    if text in ("nan", "empty"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--no-return {text!r}: expected nan, empty or a number (such as 0 or -9999)") from None


def _cmd_export_cell(args: argparse.Namespace) -> int:
    from simulator.export_cell import export_cell

    from data_catalog.atomic import check_can_create

    out = Path(args.out_dir)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_DIR {out}")
    summary = export_cell(args.sample_dir, out, layout=args.layout, delimiter=args.delimiter, compress=args.gzip,
                          orientation=args.orientation, quaternion_order=args.quaternion_order,
                          angle_unit=args.angle_unit, units=args.units, time_unit=args.time_unit,
                          no_return=_no_return(args.no_return), intensity_bits=args.intensity_bits,
                          pose_every=args.pose_every, time_offset_s=args.time_offset)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_profiles:,} profiles, {summary.n_poses:,} poses; "
          f"weldrecon import {summary.out_dir / 'CELL.yaml'} SAMPLE")
    return 0
