"""``weldrecon import`` (a real cell's logs) and ``weldrecon import-scans`` (point clouds of any
scanner): data from elsewhere written as a sample folder."""

from __future__ import annotations

import argparse
from pathlib import Path

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
    isc.set_defaults(func=_cmd_import_scans)


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


def _cmd_import_scans(args: argparse.Namespace) -> int:
    from data_catalog.scan_import import import_scans

    out = _new_sample_folder(args.out_sample)
    try:
        view = tuple(float(v) for v in args.view_direction.split(","))
    except ValueError:
        view = args.view_direction
    summary = import_scans(args.files, out, units=args.units, poses=args.poses, ignore_poses=args.ignore_poses,
                           sample_id=args.sample_id, view_direction=view)
    print(f"{summary.out_dir}: {summary.n_scans} scans, {summary.n_points:,} points, "
          f"{'poses given' if summary.with_poses else 'no poses (the registration finds them)'}; "
          f"registration: surfaces")
    return 0
