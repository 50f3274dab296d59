"""The ``weldrecon`` command line: the parser, assembled from one module per command group, and
``main``.

- ``simulate``: simulate, plan, demo, export-cell (the only command code that may import the simulator)
- ``reconstruct``: reconstruct
- ``catalog``: catalog register|list|show|index, batch
- ``audit``: audit verify|show
- ``imports``: import, import-scans
- ``measure``: measure-weld (a butt weld straight from scanned points)
- ``info``: stages, schema
- ``positioner``: calibrate-positioner
- ``render``: a run's typed summary on the terminal
- ``errors``: one line per problem on the terminal, the traceback in a log file

A command's heavy imports (Prefect, the compute stack, the simulator) are made inside it, after
its input is checked: nothing here or at the top of those modules loads them.
"""

from __future__ import annotations

import argparse
import sys

from flows.cli import audit, catalog, imports, info, measure, positioner, reconstruct, simulate
from flows.cli.errors import end_log_file, say_error

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="weldrecon", description="The ``weldrecon`` command line.")
    sub = parser.add_subparsers(dest="command", required=True)
    ws = catalog.workspace_option()
    simulate.add_simulate(sub)
    simulate.add_plan(sub)
    reconstruct.add_reconstruct(sub)
    simulate.add_demo(sub)
    catalog.add_catalog(sub, ws)
    catalog.add_batch(sub, ws)
    audit.add_audit(sub, ws)
    imports.add_import(sub)
    imports.add_import_scans(sub)
    measure.add_measure_weld(sub)
    simulate.add_export_cell(sub)
    positioner.add_calibrate_positioner(sub)
    info.add_stages(sub)
    info.add_schema(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: this process's own command line, as the ``weldrecon``
    program; it then also ends quietly on a closed pipe: ``weldrecon audit show X | head``).
    Returns the exit status; what a command changed in this process's logging is undone."""
    if argv is None:
        import signal

        signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    args = _parser().parse_args(argv)
    if argv is None:  # the program itself: a signal stops it with its children, in one line
        from flows import stopping

        stopping.install(args.command)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"weldrecon {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - one line on the terminal, the traceback in a log file
        return say_error(args.command, exc)
    finally:
        end_log_file()
