"""``weldrecon stages`` and ``weldrecon schema``: what the reconstruction does and what a sample
must hold, printed without running anything (the stage registry imports no stage body, so
``stages`` answers at once)."""

from __future__ import annotations

import argparse
import sys

__all__ = ["add_stages", "add_schema"]


def add_stages(sub) -> None:
    stages = sub.add_parser("stages", help="print the reconstruction's stages: inputs, settings, outputs")
    stages.set_defaults(func=_cmd_stages)


def add_schema(sub) -> None:
    schema = sub.add_parser("schema", help="print the sample manifest's JSON schema")
    schema.set_defaults(func=_cmd_schema)


def _cmd_stages(args: argparse.Namespace) -> int:
    from flows.stages import stage_table

    sys.stdout.write(stage_table())
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from data_catalog.manifests import manifest_json_schema

    sys.stdout.write(manifest_json_schema())
    return 0
