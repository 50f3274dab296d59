"""``weldrecon import`` (a real cell's logs) and ``weldrecon import-scans`` (point clouds of any
scanner): data from elsewhere written as a sample folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from flows.cli.measure import parse_weld_line

__all__ = ["add_import", "add_import_scans"]


def add_import(sub) -> None:
    imp = sub.add_parser("import", help="a real cell's logs (profile files, pose logs, CELL.yaml) into a sample folder")
    imp.add_argument("cell_yaml", metavar="CELL.yaml", help="the cell description (docs/cell-logs.md)")
    imp.add_argument("out_sample", metavar="OUT_SAMPLE", help="new folder for the sample (must not exist)")
    imp.set_defaults(func=_cmd_import)


def add_import_scans(sub) -> None:
    isc = sub.add_parser("import-scans", help="point clouds of any scanner (PLY, PCD, XYZ/CSV/TXT, E57, LAS/LAZ) into a "
                         "sample registered on its surfaces (docs/point-clouds.md)")
    isc.add_argument("out_sample", metavar="OUT_SAMPLE", help="new folder for the sample (must not exist)")
    isc.add_argument("files", nargs="+", metavar="FILE", help="the scans, one pass each (an E57 file: one per scan in it)")
    isc.add_argument("--units", metavar="mm|cm|m|in", help="length unit of the files' coordinates and of the .conf "
                     "(required but for E57, metres by its standard)")
    isc.add_argument("--poses", metavar="FILE.conf", help="the scans' poses: a Stanford/scanalyze .conf "
                     "(bmesh FILE tx ty tz qx qy qz qw), one line per scan given")
    isc.add_argument("--ignore-poses", action="store_true", help="use no pose (not the E57 files' own): the "
                     "registration finds them")
    isc.add_argument("--sample-id", help="the sample's id (default: OUT_SAMPLE's name)")
    isc.add_argument("--view-direction", default="0,0,1", metavar="x,y,z", help="from the surface toward the scanner "
                     "in each scan's frame (normals are turned toward it; default 0,0,1)")
    weld = isc.add_argument_group("the weld in the scans (measured by reconstruct's stage weld, docs/weld.md)")
    weld.add_argument("--joint", choices=sorted(_JOINTS), help="the weld's joint: a butt weld's cap, or a fillet weld "
                      "in the corner of a T-joint")
    where = weld.add_mutually_exclusive_group()
    where.add_argument("--weld-line", action="append", metavar="X0,Y0,Z0:X1,Y1,Z1", help="a weld line (a butt weld's "
                       "centre line on the plate's face; a fillet's root), mm, in the frame of the scans' poses (none: "
                       "the first scan's own); repeat for several")
    where.add_argument("--weld-auto", action="store_true", help="find the weld line on the scans (a butt weld: where "
                       "the surface rises from the plates; a fillet: where the two plates' planes cross)")
    weld.add_argument("--treatment", choices=sorted(_TREATMENTS), default="as-welded")
    isc.set_defaults(func=_cmd_import_scans)


_JOINTS = {"butt": "double-sided butt", "fillet": "fillet"}  # the manifest's (and acceptance catalog's) names
_TREATMENTS = {"as-welded": "as-welded", "hfmi": "hfmi-treated"}
GIVEN_TOLERANCE_MM = 2.0  # how far a weld line given by hand may be off the weld (the weld stage finds it within)
FOUND_TOLERANCE_MM = 1.0  # one found on the scans


def _new_sample_folder(path: str) -> Path:
    """``OUT_SAMPLE``: a folder that does not exist yet and can be made."""
    from data_catalog.atomic import check_can_create

    out = Path(path)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_SAMPLE {out}")
    return out


def _cmd_import(args: argparse.Namespace) -> int:
    from data_catalog.cell_logs import import_cell

    out = _new_sample_folder(args.out_sample)
    summary = import_cell(args.cell_yaml, out)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_profiles:,} profiles, {summary.n_points:,} points")
    return 0


def _scans_weld(args: argparse.Namespace, read):
    """The weld the options describe (``schemas.manifest.WeldDescription``, its lines in the frame
    of the scans' poses) and the lines' tolerance; None: no weld given. ValueError naming the option."""
    from schemas.manifest import WeldDescription, WeldLine
    from schemas.profile_weld import MeasureWeldConfig
    from tasks.scan_fillet import find_fillet_root
    from tasks.scan_weld import find_weld_line, given_weld_line

    if args.joint is None:
        if args.weld_line or args.weld_auto:
            raise ValueError("--weld-line and --weld-auto describe a weld: give its --joint (butt or fillet) too")
        return None, 0.0
    if not (args.weld_line or args.weld_auto):
        raise ValueError(f"--joint {args.joint}: where is the weld? give --weld-line X0,Y0,Z0:X1,Y1,Z1 (mm, in the "
                         "frame of the scans' poses) or --weld-auto")
    points, frame = read.points_in_weld_frame()
    if args.weld_auto:
        try:
            found = (find_weld_line(points, min_rise_mm=MeasureWeldConfig().min_rise_mm) if args.joint == "butt"
                     else find_fillet_root(points))
        except ValueError as exc:
            raise ValueError(f"--weld-auto: {exc} (the scans in {frame})") from None
        ends, label, tolerance = [(found.start_mm, found.end_mm)], "found on the scans at import", FOUND_TOLERANCE_MM
    else:
        ends = [parse_weld_line(text) for text in args.weld_line]
        for k, (start, end) in enumerate(ends):
            try:
                given_weld_line(points, start, end)
            except ValueError as exc:
                raise ValueError(f"--weld-line {args.weld_line[k]}: {exc}; expected a line on the scans, in {frame}") \
                    from None
        label, tolerance = "given at import", GIVEN_TOLERANCE_MM
    lines = [WeldLine(name="weld" if len(ends) == 1 else f"weld-{k + 1}", label=label,
                      points_mm=[tuple(round(float(v), 4) for v in p) for p in (start, end)])
             for k, (start, end) in enumerate(ends)]
    return WeldDescription(joint=_JOINTS[args.joint], treatment=_TREATMENTS[args.treatment], weld_lines=lines), tolerance


def _cmd_import_scans(args: argparse.Namespace) -> int:
    from data_catalog.scan_import import read_scans, write_scans_sample

    out = _new_sample_folder(args.out_sample)
    try:
        view = tuple(float(v) for v in args.view_direction.split(","))
    except ValueError:
        view = args.view_direction
    read = read_scans(args.files, out, units=args.units, poses=args.poses, ignore_poses=args.ignore_poses,
                      sample_id=args.sample_id, view_direction=view)
    weld, tolerance = _scans_weld(args, read)
    summary = write_scans_sample(read, weld=weld, placement_tolerance_mm=tolerance)
    print(f"{summary.out_dir}: {summary.n_scans} scans, {summary.n_points:,} points, "
          f"{'poses given' if summary.with_poses else 'no poses (the registration finds them)'}; "
          f"registration: surfaces")
    if weld is not None:
        for line in weld.weld_lines:
            a, b = line.points_mm
            print(f"  weld line {line.name} ({line.label}): {','.join(f'{v:g}' for v in a)}:"
                  f"{','.join(f'{v:g}' for v in b)} mm, {weld.joint}, {weld.treatment}")
    return 0
