"""A plan's folder (``weldrecon plan PART --out PLAN_DIR``), written atomically::

    plan.json              the plan (schemas.scan_plan.ScanPlan): read by `weldrecon simulate --plan`
    manifest_setups.json   the plan's setups and passes as a sample manifest's ``setups``
    robot_program.csv      the TCP (the scanner's frame) at the start and end of every pass
    robot_program.json     the same, with each pass's speed and profile rate
    stickers-FACE.svg      a printable sticker map per face of the part, 1:1 (mm)
    plan.html              the plan page: scan time, predicted coverage, the overlap graph

``read_plan`` reads a plan folder back, with one clear line for what is wrong with it.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from data_catalog.atomic import atomic_directory
from schemas.manifest import Setup
from schemas.scan_plan import ScanPlan
from schemas.simulation import PlacementConfig
from simulator.placement import nominal_placement, placement_tolerance_mm, resting_plate_mm, turned_setup
from simulator.planner import planned_passes
from simulator.robot import pass_entry
from tasks.pass_coverage import dog_bone_half_width

__all__ = ["PLAN_NAME", "write_plan_folder", "read_plan", "PlanFolderError", "manifest_setups"]

PLAN_NAME = "plan.json"


class PlanFolderError(ValueError):
    pass


def read_plan(folder: Path) -> ScanPlan:
    folder = Path(folder)
    path = folder / PLAN_NAME
    if not path.is_file():
        raise PlanFolderError(f"{folder}: no {PLAN_NAME}; expected a folder written by `weldrecon plan`")
    try:
        return ScanPlan.model_validate_json(path.read_text(encoding="utf-8"))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise PlanFolderError(f"{path}: field {where}: {first['msg']} ({exc.error_count()} problem(s) in all)") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise PlanFolderError(f"{path}: not a plan's JSON ({exc})") from None


def manifest_setups(plan: ScanPlan) -> list[Setup]:
    """The plan's setups as a manifest's (``schemas.manifest.Setup``), content hashes left out."""
    cfg = plan.part
    req = plan.requirements
    passes = planned_passes(plan)
    out = []
    tj = cfg.tjoint
    thickness, half_width = resting_plate_mm(cfg)
    for setup in req.setups:
        entries = [pass_entry(p, cfg.robot) for p in passes if p.setup == setup]
        if tj is None:
            up = "top face up"
        elif tj.stems == "both":
            up = "the upper stem up, the lower one hanging between the support blocks" if setup == "top" else \
                "turned over about the base plate's length: the lower stem up"
        else:
            up = "stem up, the base plate on the support blocks" if setup == "top" else \
                "turned over about the base plate's length: the stem hangs between the support blocks"
        description = (f"{up}, against the fixture's stops" if setup == "top" or tj is not None else
                       "turned 180 deg about its length, against the fixture's stops")
        nominal = nominal_placement(cfg.fixture, thickness, flipped=(setup == "bottom"))
        turn = None
        if cfg.positioner is not None and out:  # turned by the positioner, as simulator.run's manifest says
            turn, nominal, description = turned_setup(cfg, from_setup=out[0].name)
        placement = PlacementConfig(translation_mm=req.placement_tolerance_mm, yaw_deg=req.placement_yaw_deg)
        tol = placement_tolerance_mm(placement, half_width)
        out.append(Setup(name=setup, description=description, passes=entries,
                         T_world_specimen_nominal=nominal.tolist(), placement_tolerance_mm=round(tol, 3),
                         positioner=turn))
    return out


def _program_rows(plan: ScanPlan) -> list[dict]:
    rows = []
    for p in plan.passes:
        T = np.asarray(p.T_world_sensor_start)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        for point, s in (("start", 0.0), ("end", p.length_mm)):
            xyz = T[:3, 3] + s * np.asarray(p.travel_world)
            rows.append({"pass_id": p.pass_id, "setup": p.setup, "point": point, "t_s": round(s / p.speed_mm_s, 4),
                         "x_mm": round(float(xyz[0]), 4), "y_mm": round(float(xyz[1]), 4),
                         "z_mm": round(float(xyz[2]), 4), "qw": round(float(q[3]), 9), "qx": round(float(q[0]), 9),
                         "qy": round(float(q[1]), 9), "qz": round(float(q[2]), 9), "speed_mm_s": p.speed_mm_s})
    return rows


def _program_csv(plan: ScanPlan) -> str:
    rows = _program_rows(plan)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def _program_json(plan: ScanPlan) -> str:
    cfg = plan.part
    rows = _program_rows(plan)
    passes = []
    for p in plan.passes:
        passes.append({"pass_id": p.pass_id, "setup": p.setup, "purpose": p.purpose, "direction": p.direction,
                       "speed_mm_s": p.speed_mm_s, "profile_rate_hz": p.profile_rate_hz, "length_mm": p.length_mm,
                       "duration_s": round(p.duration_s, 4),
                       "waypoints": [{k: v for k, v in r.items() if k not in ("pass_id", "setup", "speed_mm_s")}
                                     for r in rows if r["pass_id"] == p.pass_id]})
    doc = {"frame": "the cell (world); the part at its nominal placement on the fixture",
           "tcp": "the scanner's frame: z along the laser's central ray, y along the travel, x along the line",
           "orientation": "unit quaternion qw, qx, qy, qz of T_world_sensor", "units": "mm, s",
           "T_flange_sensor": cfg.robot.T_flange_sensor, "setups": list(plan.requirements.setups),
           "scan_time_s": plan.scan_time_s, "passes": passes}
    return json.dumps(doc, indent=1) + "\n"


# --- sticker maps ----------------------------------------------------------------------------


def _outline(plan: ScanPlan, step: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    sp = plan.part.specimen
    x = np.arange(-sp.length_mm / 2, sp.length_mm / 2 + 1e-9, step)
    return x, dog_bone_half_width(x, gauge_length_mm=sp.gauge_length_mm, gauge_width_mm=sp.gauge_width_mm,
                                  grip_width_mm=sp.grip_width_mm, transition_radius_mm=sp.transition_radius_mm)


def _arc_length(x: np.ndarray, hw: np.ndarray) -> np.ndarray:
    ds = np.hypot(np.diff(x), np.diff(hw))
    return np.concatenate([[0.0], np.cumsum(ds)])


def _svg(width: float, height: float, body: list[str], title: str) -> str:
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.1f}mm" height="{height:.1f}mm" '
            f'viewBox="0 0 {width:.3f} {height:.3f}" font-family="sans-serif">\n<title>{html.escape(title)}</title>\n'
            + "\n".join(body) + "\n</svg>\n")


def _sticker_marks(u: float, v: float, r: float, sticker_id: int) -> list[str]:
    return [f'<circle cx="{u:.3f}" cy="{v:.3f}" r="{r:.3f}" fill="none" stroke="black" stroke-width="0.2"/>',
            f'<path d="M{u - r * 0.4:.3f},{v:.3f}H{u + r * 0.4:.3f}M{u:.3f},{v - r * 0.4:.3f}V{v + r * 0.4:.3f}" '
            'stroke="black" stroke-width="0.15"/>',
            f'<text x="{u + r + 0.8:.3f}" y="{v - r:.3f}" font-size="3">{sticker_id}</text>']


def _footer(width: float, height: float, pad: float, note: str, count: int, r: float) -> list[str]:
    return [f'<path d="M{pad:.2f},{height - 8:.2f}h50" stroke="black" stroke-width="0.5"/>'
            f'<text x="{pad + 52:.2f}" y="{height - 7:.2f}" font-size="3">50 mm: print at 100 %</text>',
            f'<text x="{pad:.2f}" y="{height - 2:.2f}" font-size="3">{html.escape(note)}; '
            f'{count} stickers of {2 * r:g} mm</text>']


# a T-joint's faces, seen from outside: (u: specimen axis and sign to the right, v: axis and sign up)
_TJOINT_VIEWS = {"top": ((0, 1.0), (1, 1.0), "the base plate's face on the stem's side, seen from above; x to the right, +y up"),
                 "bottom": ((0, 1.0), (1, -1.0), "the base plate's other face, seen from below; x to the right, +y down"),
                 "side_neg": ((0, 1.0), (2, 1.0), "the base plate's wall at -y, seen from outside; x to the right, z up"),
                 "side_pos": ((0, -1.0), (2, 1.0), "the base plate's wall at +y, seen from outside; -x to the right, z up"),
                 "end_neg": ((1, -1.0), (2, 1.0), "the base plate's end at -x, seen from outside; -y to the right, z up"),
                 "end_pos": ((1, 1.0), (2, 1.0), "the base plate's end at +x, seen from outside; y to the right, z up"),
                 "stem_neg": ((1, -1.0), (2, 1.0), "the stem's face at -x, seen from outside; -y to the right, z up"),
                 "stem_pos": ((1, 1.0), (2, 1.0), "the stem's face at +x, seen from outside; y to the right, z up")}


def _tjoint_maps(plan: ScanPlan) -> dict[str, str]:
    """A T-joint's or a cruciform's faces with stickers, each a rectangle seen from outside
    (``_TJOINT_VIEWS``), the weld zone shaded where the face meets a fillet; specimen frame."""
    tj = plan.part.tjoint
    r = plan.part.stickers.diameter_mm / 2
    pad = 15.0
    L, W, t, H = tj.base_length_mm, tj.base_width_mm, tj.base_thickness_mm, tj.stem_height_mm
    z0, x0 = t / 2, tj.stem_thickness_mm / 2
    keep = plan.no_sticker_x_mm[1] - x0  # the weld zone and its clearance, from the stem's face
    lower = tj.stems == "both"
    extent = {0: (-L / 2, L / 2), 1: (-W / 2, W / 2)}
    maps = {}
    for face, ((ua, us), (va, vs), seen) in _TJOINT_VIEWS.items():
        stickers = [s for s in plan.stickers if s.face == face]
        if not stickers:
            continue
        if face.startswith("stem"):
            v_lo, v_hi = (-z0 - H if lower else z0), z0 + H
        else:
            v_lo, v_hi = (-z0, z0) if va == 2 else extent[va]
        u_lo, u_hi = extent[ua]
        width = max((u_hi - u_lo) + 2 * pad, 200.0)  # room for the notes below
        height = (v_hi - v_lo) + 2 * pad + 16

        def to_uv(point, ua=ua, us=us, va=va, vs=vs, u_lo=u_lo, u_hi=u_hi, v_lo=v_lo, v_hi=v_hi):
            u = point[ua] * us - (u_lo if us > 0 else -u_hi)
            v = point[va] * vs - (v_lo if vs > 0 else -v_hi)
            return pad + u, pad + (v_hi - v_lo) - v

        body = [f'<rect x="{pad:.2f}" y="{pad:.2f}" width="{u_hi - u_lo:.2f}" height="{v_hi - v_lo:.2f}" fill="none" '
                'stroke="black" stroke-width="0.3"/>']
        shaded = []
        if face == "top" or (face == "bottom" and lower):
            shaded.append(((-x0 - keep, -W / 2, 0.0), (x0 + keep, W / 2, 0.0)))
        if face.startswith("stem"):
            sign = 1.0 if face == "stem_pos" else -1.0
            shaded.append(((sign * x0, -W / 2, z0), (sign * x0, W / 2, z0 + keep)))
            if lower:
                shaded.append(((sign * x0, -W / 2, -z0 - keep), (sign * x0, W / 2, -z0)))
                shaded.append(((sign * x0, -W / 2, -z0), (sign * x0, W / 2, z0)))  # the base plate
        for a, b in shaded:
            (ua_, va_), (ub_, vb_) = to_uv(a), to_uv(b)
            body.append(f'<rect x="{min(ua_, ub_):.2f}" y="{min(va_, vb_):.2f}" width="{abs(ub_ - ua_):.2f}" '
                        f'height="{abs(vb_ - va_):.2f}" fill="#ddd"/>')
        for s in stickers:
            body += _sticker_marks(*to_uv(s.centre_mm), r, s.sticker_id)
        body.append(f'<text x="{pad:.2f}" y="{height - 12:.2f}" font-size="3">{face}: {html.escape(seen)}</text>')
        note = "shaded: the welds and their keep-out, no stickers; specimen frame, mm"
        body += _footer(width, height, pad, note, len(stickers), r)
        maps[face] = _svg(width, height, body, f"{plan.part.sample_id}: stickers on the {face}")
    return maps


def sticker_maps(plan: ScanPlan) -> dict[str, str]:
    """One SVG per face with stickers, 1:1 in mm, the face as seen from outside it: top from
    above (x to the right, y up); bottom from below (x to the right, y down); a side wall from its
    side, unrolled along the wall (the length along the wall to the right from the end at -x on
    side_neg, from the end at +x on side_pos; z up). A T-joint's or a cruciform's: ``_tjoint_maps``."""
    if plan.part.tjoint is not None:
        return _tjoint_maps(plan)
    cfg = plan.part
    L, t = cfg.specimen.length_mm, cfg.specimen.thickness_mm
    r = cfg.stickers.diameter_mm / 2
    pad = 15.0
    x, hw = _outline(plan)
    keep_lo, keep_hi = plan.no_sticker_x_mm
    maps = {}
    for face in ("top", "bottom", "side_neg", "side_pos"):
        stickers = [s for s in plan.stickers if s.face == face]
        if not stickers:
            continue
        body = []
        if face in ("top", "bottom"):
            W = 2 * float(hw.max())
            width, height = L + 2 * pad, W + 2 * pad + 12
            flip = -1.0 if face == "top" else 1.0  # SVG's y grows downward

            def to_uv(px, py, flip=flip, W=W):
                return px + L / 2 + pad, pad + W / 2 + flip * py

            upper = " ".join(f"{a:.2f},{b:.2f}" for a, b in (to_uv(a, h) for a, h in zip(x, hw)))
            lower = " ".join(f"{a:.2f},{b:.2f}" for a, b in (to_uv(a, -h) for a, h in zip(x[::-1], hw[::-1])))
            body.append(f'<polygon points="{upper} {lower}" fill="none" stroke="black" stroke-width="0.3"/>')
            u0, _ = to_uv(keep_lo, 0)
            u1, _ = to_uv(keep_hi, 0)
            body.append(f'<rect x="{u0:.2f}" y="{pad:.2f}" width="{u1 - u0:.2f}" height="{W:.2f}" fill="#ddd"/>')
            body.append(f'<text x="{(u0 + u1) / 2:.2f}" y="{pad - 2:.2f}" font-size="3.5" text-anchor="middle">weld '
                        'zone: no stickers</text>')
            for s in stickers:
                body += _sticker_marks(*to_uv(s.centre_mm[0], s.centre_mm[1]), r, s.sticker_id)
            note = f"{face} face, seen from {'above' if face == 'top' else 'below'}; x to the right, " \
                   f"{'+y up' if face == 'top' else '+y down'}; specimen frame, the weld at x = {(keep_lo + keep_hi) / 2:g} mm"
        else:
            s_along = _arc_length(x, hw)
            total = float(s_along[-1])
            width, height = total + 2 * pad, t + 2 * pad + 12
            sign = -1.0 if face == "side_neg" else 1.0

            def to_uv(px, pz, total=total, s_along=s_along, sign=sign):
                along = float(np.interp(px, x, s_along))
                u = along if sign < 0 else total - along
                return u + pad, pad + t / 2 - pz

            body.append(f'<rect x="{pad:.2f}" y="{pad:.2f}" width="{total:.2f}" height="{t:.2f}" fill="none" '
                        'stroke="black" stroke-width="0.3"/>')
            for s in stickers:  # the marks' heights are from the plate's mid-plane
                body += _sticker_marks(*to_uv(s.centre_mm[0], s.centre_mm[2]), r, s.sticker_id)
            end = "-x" if sign < 0 else "+x"
            note = f"{face} wall, seen from outside, unrolled along the wall from the end at {end}; z up"
        body += _footer(width, height, pad, note, len(stickers), r)
        maps[face] = _svg(width, height, body, f"{plan.part.sample_id}: stickers on the {face}")
    return maps


# --- the plan page ---------------------------------------------------------------------------


def _graph_svg(plan: ScanPlan) -> str:
    """The passes on a circle per setup, an edge per overlap labelled with its shared stickers;
    the setups' shared stickers between the circles."""
    setups = list(plan.requirements.setups)
    size, radius = 360.0, 130.0
    width = size * len(setups)
    pos = {}
    for k, setup in enumerate(setups):
        members = [p.pass_id for p in plan.passes if p.setup == setup]
        cx, cy = size * k + size / 2, size / 2
        for i, pid in enumerate(members):
            a = 2 * math.pi * i / max(len(members), 1) - math.pi / 2
            pos[pid] = (cx + radius * math.cos(a), cy + radius * math.sin(a))
    body = []
    for o in plan.overlaps:
        (x1, y1), (x2, y2) = pos[o.pass_a], pos[o.pass_b]
        body.append(f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" stroke="#4a7" '
                    f'stroke-width="{1 + 0.3 * len(o.sticker_ids):.1f}" opacity="0.6"/>')
        body.append(f'<text x="{(x1 + x2) / 2:.1f}" y="{(y1 + y2) / 2:.1f}" font-size="10" fill="#264">'
                    f'{len(o.sticker_ids)}</text>')
    for pid, (px, py) in pos.items():
        body.append(f'<circle cx="{px:.1f}" cy="{py:.1f}" r="5" fill="#247"/>'
                    f'<text x="{px + 7:.1f}" y="{py - 6:.1f}" font-size="10">{html.escape(pid)}</text>')
    for k, setup in enumerate(setups):
        body.append(f'<text x="{size * k + size / 2:.1f}" y="16" font-size="13" text-anchor="middle">setup '
                    f'{html.escape(setup)}</text>')
    for link in plan.setup_links:
        body.append(f'<text x="{width / 2:.1f}" y="{size - 8:.1f}" font-size="12" text-anchor="middle">setups '
                    f'{link.setups[0]} and {link.setups[1]} share {len(link.sticker_ids)} stickers '
                    f'({link.spread_mm:.0f} mm off a line)</text>')
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{size:.0f}" '
            f'viewBox="0 0 {width:.0f} {size:.0f}" font-family="sans-serif" role="img" '
            'aria-label="overlap graph">' + "".join(body) + "</svg>")


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def plan_page(plan: ScanPlan, maps: dict[str, str]) -> str:
    req = plan.requirements
    minutes = plan.scan_time_s / 60
    parts = [f"<h1>Scan plan: {html.escape(plan.part.sample_id)}</h1>",
             f"<p><b>{len(plan.passes)} passes</b> over {len(req.setups)} setup(s), <b>{plan.scan_time_s:.0f} s "
             f"({minutes:.1f} min) of scanning</b>, {len(plan.stickers)} stickers of {plan.part.stickers.diameter_mm:g} mm "
             f"on the part. The fastest of {plan.candidates_tried} candidate plans that met every requirement.</p>",
             "<h2>Requirements</h2>",
             _table(["what", "value"], [
                 ["weld toes measured from both sides", f"{100 * req.toe_coverage:.0f} % of every toe, the laser within "
                                                       f"{req.toe_incidence_limit_deg:g} deg of the plate's normal"],
                 ["faces seen", f"{100 * req.face_coverage:.0f} % of each face"],
                 ["placement of the part", f"within {req.placement_tolerance_mm:g} mm and {req.placement_yaw_deg:g} deg "
                                           "of nominal (against the fixture's stops)"],
                 ["stickers", f"{plan.part.stickers.min_common} whole per overlapping pass pair, "
                              f"{plan.part.stickers.min_spread_mm:g} mm off a line, put within "
                              f"{req.sticker_tolerance_mm:g} mm of their marks; {req.min_setup_stickers} shared by "
                              "the setups"],
                 ["robot", f"TCP within {list(req.reach.workspace_min_mm)}..{list(req.reach.workspace_max_mm)} mm, "
                           f"view at most {req.reach.max_tilt_deg:g} deg from straight down"],
                 ["between the setups", "turned by hand" if plan.part.positioner is None else
                  f"turned {plan.part.positioner.angle_deg:g} deg by the positioner, the part still clamped "
                  "(manifest_setups.json: the calibrated axis)"]]),
             "<h2>Predicted coverage</h2>",
             _table(["face", "area, mm²", "seen", "passes per cell (median)"],
                    [[f.face, f"{f.area_mm2:.0f}", f"{100 * f.seen:.1f} %", f"{f.passes_median:g}"] for f in plan.faces]),
             _table(["toe", "rule", "length, mm", "from over the plate (two directions: seen)",
                     "from over the weld (two directions: from a second, 20 deg apart)", "as the rule asks"],
                    [[t.toe, t.rule, f"{t.length_mm:.0f}", f"{100 * t.plate_side:.1f} %", f"{100 * t.weld_side:.1f} %",
                      f"{100 * t.both_sides:.1f} %"] for t in plan.toes]),
             "<h2>Passes</h2>",
             _table(["pass", "setup", "what for", "direction", "length, mm", "time, s", "stand-off, mm", "tilt, deg",
                     "roll, deg"],
                    [[p.pass_id, p.setup, p.purpose, p.direction, f"{p.length_mm:.0f}", f"{p.duration_s:.1f}",
                      f"{p.standoff_mm:.0f}", f"{p.tilt_deg:.0f}", f"{p.roll_deg:.0f}"] for p in plan.passes]),
             "<h2>Overlaps and the stickers they share</h2>", _graph_svg(plan),
             _table(["passes", "stickers shared", "off a line, mm"],
                    [[f"{o.pass_a} + {o.pass_b}", ", ".join(map(str, o.sticker_ids)), f"{o.spread_mm:.1f}"]
                     for o in plan.overlaps]),
             "<h2>Sticker maps (print the SVG files at 100 %)</h2>"]
    for face, svg in maps.items():
        parts.append(f"<h3>{html.escape(face)}</h3><div class='map'>{svg.split('?>')[-1]}</div>")
    style = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}"
             ".map svg{width:100%;height:auto}")
    return ("<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>Scan plan "
            f"{html.escape(plan.part.sample_id)}</title><style>{style}</style></head><body>\n"
            + "\n".join(parts) + "\n</body></html>\n")


def write_plan_folder(plan: ScanPlan, out_dir: Path) -> Path:
    """Write the plan's folder; it appears only when complete."""
    maps = sticker_maps(plan)
    setups = manifest_setups(plan)
    with atomic_directory(Path(out_dir)) as tmp:
        (tmp / PLAN_NAME).write_text(plan.model_dump_json(indent=1) + "\n", encoding="utf-8")
        (tmp / "manifest_setups.json").write_text(
            json.dumps({"setups": [s.model_dump(mode="json") for s in setups]}, indent=1) + "\n", encoding="utf-8")
        (tmp / "robot_program.csv").write_text(_program_csv(plan), encoding="utf-8")
        (tmp / "robot_program.json").write_text(_program_json(plan), encoding="utf-8")
        for face, svg in maps.items():
            (tmp / f"stickers-{face}.svg").write_text(svg, encoding="utf-8")
        (tmp / "plan.html").write_text(plan_page(plan, maps), encoding="utf-8")
    return Path(out_dir)
