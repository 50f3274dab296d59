"""The ``weldrecon`` command line."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pydantic import ValidationError

__all__ = ["main"]


def _describe(error: ValidationError) -> str:
    return "\n".join(f"  {'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in error.errors())


def _deep_merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _deep_merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return out


def _simulation_config(args: argparse.Namespace):
    import yaml

    from schemas.simulation import SimulationConfig
    from simulator.presets import preset_config

    base = preset_config(args.preset).model_dump()
    if args.config is not None:
        try:
            override = yaml.safe_load(Path(args.config).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ValueError(f"{args.config}: cannot read the simulation config ({exc})") from None
        if not isinstance(override, dict):
            raise ValueError(f"{args.config}: the simulation config must be a mapping of fields")
        base = _deep_merge(base, override)
    if args.seed is not None:
        base["seed"] = args.seed
    if args.sample_id is not None:
        base["sample_id"] = args.sample_id
    try:
        return SimulationConfig.model_validate(base)
    except ValidationError as exc:
        source = args.config or f"preset {args.preset}"
        raise ValueError(f"{source}: invalid simulation config:\n{_describe(exc)}") from None


def _cmd_simulate(args: argparse.Namespace) -> int:
    from simulator.run import simulate

    config = _simulation_config(args)
    out = Path(args.out_dir)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    started = time.perf_counter()

    def progress(message: str) -> None:
        print(f"[{time.perf_counter() - started:7.1f} s] {message}", file=sys.stderr, flush=True)

    progress(f"simulating preset {config.preset!r} (seed {config.seed}) into {out}")
    summary = simulate(config, out, progress=progress, previews=not args.no_preview)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_points:,} points "
          f"({summary.n_valid_points:,} returns), {summary.n_stickers_specimen} stickers on the specimen, "
          f"{summary.n_stickers_fixture} on the fixture, {summary.seconds:.1f} s")
    if not args.no_preview:
        print(f"pictures: {summary.out_dir / 'preview'}")
    return 0


def _quiet_prefect() -> None:
    import os

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


def _print_report(report: dict, out: Path) -> None:
    stages = report["stages"]
    refined, mesh = stages["refine"], report["mesh"]
    print(f"{report['sample_id']}: {len(report['passes'])} passes")
    for name, value in stages.items():
        if isinstance(value, list):
            cached = sum(v["cached"] for v in value)
            print(f"  {name:<9} {len(value)} passes, {sum(v['seconds'] for v in value):.1f} s of work, {cached} cached")
        else:
            extra = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in value.items()
                     if k in ("points_in", "points_out", "residual_median_mm", "residual_max_mm", "vertices",
                              "watertight", "surface_pairs", "surface_rms_median_mm", "largest_pose_change_mm",
                              "target_residual_median_mm")}
            took = "cached" if value["cached"] else f"{value['seconds']:.1f} s"
            print(f"  {name:<9} {took}  {extra}")
    weak = report["registration"]["pairs_below_min_common"]
    if weak:
        print("  pass pairs with fewer common targets than needed: "
              + ", ".join(f"{w['a']}|{w['b']} ({w['common_targets']})" for w in weak))
    print(f"mesh: {mesh['vertices']:,} vertices, {mesh['triangles']:,} triangles, "
          f"{'watertight' if mesh['watertight'] else 'NOT watertight'}; target residual median "
          f"{refined['target_residual_median_mm'] * 1000:.0f} um, max {refined['target_residual_max_mm'] * 1000:.0f} um")
    for name, item in report["outputs"].items():
        print(f"  {item['path']}")
    print(f"  {out / 'results' / 'report.json'}")


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    _quiet_prefect()
    from flows.reconstruct import reconstruct_sample

    sample = Path(args.sample_dir)
    out = Path(args.out) if args.out else sample.parent / f"{sample.name}-reconstruction"
    report = reconstruct_sample(str(sample), str(out), args.config)
    _print_report(report, out)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from simulator.presets import preset_config
    from simulator.run import simulate

    root = Path(args.out)
    sample = root / "sample"
    if not sample.exists():
        started = time.perf_counter()
        print(f"simulating the demo sample into {sample} ...", file=sys.stderr, flush=True)
        summary = simulate(preset_config("demo"), sample)
        print(f"  {summary.n_passes} passes, {summary.n_points:,} points, {time.perf_counter() - started:.0f} s",
              file=sys.stderr)
    config = Path(__file__).resolve().parents[1] / "deploy" / "configs" / "demo.yaml"
    args = argparse.Namespace(sample_dir=str(sample), out=str(root / "reconstruction"),
                              config=str(config) if config.is_file() else None)
    print("reconstructing ...", file=sys.stderr, flush=True)
    return _cmd_reconstruct(args)


def _cmd_schema(args: argparse.Namespace) -> int:
    from data_catalog.manifests import manifest_json_schema

    sys.stdout.write(manifest_json_schema())
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="weldrecon", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="simulate a scanning cell's output for one sample")
    sim.add_argument("out_dir", metavar="OUT_DIR", help="new folder for the sample (must not exist)")
    sim.add_argument("--preset", default="demo", help="ci, demo or paper (default: demo)")
    sim.add_argument("--config", metavar="FILE", help="YAML file of fields that override the preset")
    sim.add_argument("--seed", type=int, help="override the preset's seed")
    sim.add_argument("--sample-id", help="override the preset's sample id")
    sim.add_argument("--no-preview", action="store_true", help="skip the PNG pictures")
    sim.set_defaults(func=_cmd_simulate)
    rec = sub.add_parser("reconstruct", help="registered point cloud and watertight STL of one sample")
    rec.add_argument("sample_dir", metavar="SAMPLE_DIR", help="folder with manifest.json and the passes")
    rec.add_argument("--config", metavar="FILE", help="YAML file of reconstruction settings (schemas/reconstruction.py)")
    rec.add_argument("--out", metavar="DIR", help="output folder (default: SAMPLE_DIR-reconstruction beside it)")
    rec.set_defaults(func=_cmd_reconstruct)
    demo = sub.add_parser("demo", help="simulate the demo sample (once) and reconstruct it")
    demo.add_argument("--out", default="out/demo", help="folder for the sample and its reconstruction")
    demo.set_defaults(func=_cmd_demo)
    schema = sub.add_parser("schema", help="print the sample manifest's JSON schema")
    schema.set_defaults(func=_cmd_schema)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileExistsError, FileNotFoundError, RuntimeError) as exc:
        print(f"weldrecon {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
