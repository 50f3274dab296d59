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
    schema = sub.add_parser("schema", help="print the sample manifest's JSON schema")
    schema.set_defaults(func=_cmd_schema)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileExistsError, FileNotFoundError) as exc:
        print(f"weldrecon {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
