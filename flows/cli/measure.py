"""``weldrecon measure-weld``: a butt or fillet weld measured straight from scanned points (any
file ``data_catalog.pointclouds`` reads, a sample of imported scans, a run folder:
``flows.scan_sources``), no reconstruction needed: ``<scan>.weld.json``
(``schemas.profile_weld.ScanWeld``) and its QA page ``<scan>.weld.html`` (``flows.scan_weld_page``)
per scan in ``--out``, and a line per problem on the terminal.

Exit status: 0 when every weld passes (or is not judged), 1 when a weld fails its acceptance rule
(every scan measured and written, its problems printed), 2 on bad input (one line on stderr,
``flows.cli.errors.say_error``)."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_measure_weld", "parse_weld_line"]

_JOINTS = {"butt": "double-sided butt", "fillet": "fillet"}  # the acceptance catalog's name for each
_TREATMENTS = {"as-welded": "as-welded", "hfmi": "hfmi-treated"}


def add_measure_weld(sub) -> None:
    mw = sub.add_parser("measure-weld", help="a butt or fillet weld measured straight from scanned points: toe position, "
                        "radius, angle, undercut, reinforcement (a fillet's legs, throat, convexity), each with its "
                        "1-sigma, and the acceptance judgement (butt welds); <scan>.weld.json and <scan>.weld.html")
    mw.add_argument("scans", nargs="+", metavar="SCAN", help="point files (PLY, PCD, XYZ/CSV/TXT, E57, LAS/LAZ), sample "
                    "folders of imported scans (weldrecon import-scans) or reconstruction run folders")
    where = mw.add_mutually_exclusive_group()
    where.add_argument("--weld-line", metavar="X0,Y0,Z0:X1,Y1,Z1", help="the weld line in the scans' frame, mm (a "
                       "fillet weld's: its root line, where the plates' faces meet)")
    where.add_argument("--auto", action="store_true", help="find the weld line on the data (the default)")
    mw.add_argument("--joint", choices=sorted(_JOINTS), default="butt")
    mw.add_argument("--treatment", choices=sorted(_TREATMENTS), default="as-welded")
    mw.add_argument("--units", default="mm", metavar="mm|cm|m|in", help="the files' length unit (default mm)")
    mw.add_argument("--step-mm", type=float, help="sections every this far (default: each profile of a profile scan, "
                    "else 1 mm)")
    mw.add_argument("--config", metavar="YAML", help="settings (schemas.profile_weld.MeasureWeldConfig)")
    mw.add_argument("--out", default=".", metavar="DIR", help="folder for <scan>.weld.json (default: here)")
    mw.set_defaults(func=_cmd_measure_weld)


def parse_weld_line(text: str, option: str = "--weld-line"):
    """``X0,Y0,Z0:X1,Y1,Z1`` as two points; ValueError naming the option."""
    try:
        ends = [tuple(float(v) for v in part.split(",")) for part in text.split(":")]
    except ValueError:
        ends = []
    if len(ends) != 2 or any(len(e) != 3 for e in ends):
        raise ValueError(f"{option} must be X0,Y0,Z0:X1,Y1,Z1 (mm), got {text!r}")
    return ends


def _cmd_measure_weld(args: argparse.Namespace) -> int:
    from data_catalog.atomic import atomic_write_text
    from data_catalog.textfiles import read_yaml_model
    from pydantic import ValidationError

    from flows.scan_weld import measure_scan_weld
    from flows.scan_weld_page import scan_weld_page
    from schemas.profile_weld import MeasureWeldConfig

    line = parse_weld_line(args.weld_line) if args.weld_line else None
    config = read_yaml_model(args.config, MeasureWeldConfig, "measure-weld settings") if args.config else MeasureWeldConfig()
    if args.step_mm is not None:
        try:
            step = MeasureWeldConfig(step_mm=args.step_mm).step_mm
        except ValidationError as exc:
            raise ValueError(f"--step-mm {args.step_mm:g}: {exc.errors()[0]['msg']}") from None
        config = config.model_copy(update={"step_mm": step})
    out = Path(args.out)
    failed = []
    for scan in args.scans:
        measured = measure_scan_weld(scan, units=args.units, line=line, joint=_JOINTS[args.joint],
                                     treatment=_TREATMENTS[args.treatment], config=config)
        document, problems = measured.document, measured.problems
        path = out / f"{Path(scan).name}.weld.json"
        out.mkdir(parents=True, exist_ok=True)  # only once a scan is measured: a refused one leaves nothing
        atomic_write_text(path, document.model_dump_json(indent=1))
        atomic_write_text(path.with_suffix(".html"), scan_weld_page(measured))
        g, toes = document.geometry, document.toes
        below = sum(t.toe_radius_below_mm is not None for t in toes)
        print(f"{scan}: {g.summary.sections} sections, {sum(t.measured for t in toes)} of {len(toes)} toes measured "
              f"({below} with a radius below resolution); verdict: {g.summary.verdict} -> {path} "
              f"(QA page {path.with_suffix('.html').name})")
        for problem in problems:
            print(f"  {problem}")
        if g.summary.passed is False:
            failed.append(scan)
    return 1 if failed else 0
