"""weldrecon's toes beside the peer's on the same real profiles: the authors' toe radius/angle tool
(Python port ``SchluppIng/Weld_Toe_Determination``, MIT; a local copy's path is the first
argument, nothing of it is kept here) on every profile of every ``.xyz`` in ``--data`` (default
``../shared/data/realweld``), and both on the port's two artificial profiles (``examples/*.asc``).

The port measures one toe on a profile that runs from the plate, level, onto the weld. Each real
profile is given to it as ``bench/draw_mark_sections.py`` cuts it for the eye: split at its top,
each half levelled by the line through its outer 8 mm, from the plate inward (the plus half
mirrored, x -> -x, and back for the positions). Its settings:

- ``default``: ``loadsettings()`` as shipped (no outlier removal, no filter), on the whole half;
- ``best``: its outlier removal (3-point running median) and a moving average of ``MA_POINTS``
  points (0.25 mm at 0.05 mm), on ``CROP_MM`` around the first point standing 0.3 mm over the
  plate for 0.3 mm (``draw_mark_sections.guess_toe_x``): the smallest window and filter that put
  its largest curvature at the toe on most toes (bench/README.md, "The peer on the same profiles").

Radius: curvature (CM), least-squares circle (LSM), iteration (IM); angle: largest slope (MAX,
over 0.2 mm), slope past the circle's end (END, of LSM and IM). Where each puts the toe: CM and
LSM at the largest curvature, IM at its circle's start on the plate, ours at the flank's virtual
corner on the plate (``tasks.weld_fits.fit_toe``).

    PYTHONPATH=PANDAS_DIR .venv/bin/python bench/bench_peer_toes.py PEER_DIR [--json OUT] [--pictures DIR]
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.draw_mark_sections import guess_toe_x, profile_halves, split_profile  # noqa: E402 - after the path is set
from data_catalog.pointclouds import read_point_cloud  # noqa: E402
from flows.scan_weld import profile_settings  # noqa: E402
from schemas.profile_weld import MeasureWeldConfig  # noqa: E402
from simulator.weld_profiles import REAL_SCAN_NOISE, add_scan_noise, draw_butt_profile  # noqa: E402
from tasks.profile_weld import measure_profile  # noqa: E402
from tasks.scan_weld import find_weld_line, measure_scan  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "realweld"
PEER_MODULES = ("loadsettings", "funcremoveoutlier", "funcfilterprofile", "funcprofilesorting", "funcderivation",
                "funcevalCM", "funcevalLSM", "funcevalIM", "funcevalangle")
MA_POINTS = 5
CROP_MM = (3.0, 1.0)  # plate side, weld side of the guess
AT_TOE_MM = 0.5  # a peer toe this close to ours is "at the toe"
NOISY_DRAWS = 20
DRAWN_RADII_MM = (0.3, 1.0, 2.0)  # simulator.weld_profiles, at DRAWN_ANGLE_DEG, 0.05 mm, real noise
DRAWN_ANGLE_DEG = 40.0
DRAWN_PROFILES = 10
NOISY_SPACING_MM = 0.05


def load_peer(path: Path):
    """The port's functions (a namespace) or the one line saying why they cannot be loaded."""
    missing = [m for m in PEER_MODULES if not (path / f"{m}.py").is_file()]
    if missing:
        return (f"no copy of the peer at {path} (its {', '.join(m + '.py' for m in missing[:3])} missing): "
                "git clone https://github.com/SchluppIng/Weld_Toe_Determination and give its folder")
    sys.path.insert(0, str(path))
    try:
        mods = {m: importlib.import_module(m) for m in PEER_MODULES}
    except ImportError as exc:
        return (f"the peer at {path} needs {exc.name}, not in this venv: pip install --no-deps --target DIR "
                "pandas python-dateutil pytz tzdata six, and run with PYTHONPATH=DIR")
    return SimpleNamespace(**{m: getattr(mod, m) for m, mod in mods.items() if m != "funcderivation"},
                           func_derivation=mods["funcderivation"].func_derivation)


def peer_settings(peer, name: str) -> dict:
    settings = peer.loadsettings()
    if name == "best":
        settings.update(outliermethod="remove", filter="Moving Average", smoothparam=MA_POINTS)
    return settings


def run_peer(peer, v: np.ndarray, h: np.ndarray, setting: str) -> dict:
    """The port on one toe: ``v`` (n,) mm ascending from the plate onto the weld, ``h`` (n,) mm over
    the plate. Per method its radius (mm) or why it failed, and where it puts the toe (on v)."""
    settings = peer_settings(peer, setting)
    if setting == "best":
        g = guess_toe_x(v, h)
        keep = (v >= g - CROP_MM[0]) & (v <= g + CROP_MM[1])
        v, h = v[keep], h[keep]
    prof = np.column_stack([v, h])
    prof = peer.funcprofilesorting(peer.funcfilterprofile(peer.funcremoveoutlier(prof, settings), settings), settings)
    out = {"profile": prof}
    for key, fn in (("CM", peer.funcevalCM), ("LSM", peer.funcevalLSM), ("IM", peer.funcevalIM)):
        try:
            with np.errstate(all="ignore"):
                r = fn(prof, settings[key])
        except (IndexError, ValueError, np.linalg.LinAlgError) as exc:
            if key != "CM":
                out[key] = {"failed": f"{type(exc).__name__}: {exc}"}
                continue
            r = _cm_radius(peer, prof, settings[key])  # CM has its radius before its maxdist raises
        radius = float(r["radius"])
        if not math.isfinite(radius):
            out[key] = {"failed": "no circle met its criteria"}
            continue
        if key == "CM":
            at = float(r["SP"][0])
        elif key == "LSM":
            at = float(prof[min(int(r["DP_toe"]) + 1, len(prof) - 1), 0])  # its curvature's index is one short
        else:
            at = float(r["SP"][0])
        out[key] = {"radius_mm": radius, "toe_v_mm": at, "centre": [float(c) for c in r["MP"]], "raw": r}
    with np.errstate(all="ignore"):
        mx = peer.funcevalangle("MAX", prof, settings["Angle"], None)
    out["MAX"] = {"angle_deg": float(mx["angle"]), "at_v_mm": float(prof[min(int(mx["DP"]) + 1, len(prof) - 1), 0])}
    for key in ("LSM", "IM"):
        name = f"END-{key}"
        if "failed" in out[key] or int(out[key]["raw"]["DP_EP"]) >= len(prof) - 1:
            out[name] = {"failed": f"no {key} circle"}
            continue
        try:
            with np.errstate(all="ignore"):
                a = peer.funcevalangle("END", prof, settings["Angle"], out[key]["raw"])
        except (IndexError, ValueError, np.linalg.LinAlgError, TypeError) as exc:
            out[name] = {"failed": f"{type(exc).__name__}: {exc}"}
            continue
        out[name] = {"angle_deg": float(a["angle"]), "at_v_mm": float(prof[int(out[key]["raw"]["DP_EP"]), 0])}
    return out


def _cm_radius(peer, prof: np.ndarray, settings: dict) -> dict:
    """CM's radius, toe and centre as ``funcevalCM`` has them before it raises: its maxdist takes
    the largest of no points when its circle holds one profile point or none."""
    gradient, curvature = peer.func_derivation(prof, settings["smoothparam"])
    k = int(np.argmax(curvature[:, 1]))
    normal = np.array([-gradient[k, 1], 1.0]) / math.hypot(gradient[k, 1], 1.0)
    radius = 1 / curvature[k, 1]
    return {"radius": radius, "SP": prof[1 + k], "MP": prof[1 + k] + normal * radius}


def _plain(result: dict, sign: float) -> dict:
    """A peer result for the JSON: positions back on the file's x (``sign``: -1 for a mirrored half)."""
    out = {}
    for key, r in result.items():
        if key == "profile":
            continue
        if "failed" in r:
            out[key] = r
            continue
        out[key] = {k.replace("_v_", "_x_"): (sign * v if k in ("toe_v_mm", "at_v_mm") else v)
                    for k, v in r.items() if k not in ("raw", "centre")}
        if "centre" in r:
            out[key]["centre_mm"] = [sign * r["centre"][0], r["centre"][1]]
    return out


def ours_on_scan(points: np.ndarray) -> dict:
    """weldrecon's toes on a profile scan (``points`` (n, 3) mm, profiles at constant y), as
    ``measure-weld`` reads it: per (profile y, side) the toe's x on the file, angle and radius."""
    line = find_weld_line(points, min_rise_mm=MeasureWeldConfig().min_rise_mm)
    scan = measure_scan(points, line, settings=profile_settings(MeasureWeldConfig()), treated=False, step_mm=None,
                        half_width_mm=None, name="weld")
    origin, across = np.asarray(line.start_mm), np.asarray(line.across)
    t = np.subtract(line.end_mm, line.start_mm)
    t /= np.linalg.norm(t)
    ys = np.unique(np.round(points[:, 1], 3))
    toes = {}
    for section in scan.sections:
        y = float(ys[np.argmin(np.abs(ys - (origin + section.section.position_mm * t)[1]))])
        for side, toe in zip(("minus", "plus"), section.toes):
            if toe.fit is None:
                toes[(y, side)] = {"failed": toe.reason}
                continue
            f = toe.fit
            toes[(y, side)] = {"toe_x_mm": float((origin + section.section.position_mm * t + f.position_u_mm * across)[0]),
                               "toe_x_sigma_mm": f.position_sigma_mm, "angle_deg": f.flank_angle_deg.value,
                               "angle_sigma_deg": f.flank_angle_deg.sigma, "radius_mm": f.notch_radius.value,
                               "radius_below_mm": toe.radius_below_mm}
    return toes


def compare_scan(peer, points: np.ndarray, name: str) -> list[dict]:
    """Per profile and side: ours and the peer's at both settings (positions on the file's x)."""
    ours = ours_on_scan(points)
    rows = []
    for y in sorted({y for y, _ in ours}):
        for side, x, h in profile_halves(points, y):
            sign = 1.0 if side == "minus" else -1.0  # the plus half mirrored: v ascending from the plate
            peer_rows = {s: _plain(run_peer(peer, sign * x, h, s), sign) for s in ("default", "best")}
            rows.append({"file": name, "y_mm": y, "side": side, "ours": ours[(y, side)], "peer": peer_rows})
    return rows


def _median(values) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def summary_rows(rows: list[dict]) -> list[str]:
    """Markdown rows per file, side and tool: where the toe is, its radius and angle (medians)."""
    out = []
    for name in sorted({r["file"] for r in rows}):
        for side in ("minus", "plus"):
            sel = [r for r in rows if r["file"] == name and r["side"] == side]
            ours = [r["ours"] for r in sel if "failed" not in r["ours"]]
            below = [o["radius_below_mm"] for o in ours if o["radius_below_mm"] is not None]
            resolved = [o["radius_mm"] for o in ours if o["radius_below_mm"] is None]
            radius = (f"{len(resolved)} resolved" + (f" ({_median(resolved):.2f})" if resolved else "")
                      + f", {len(below)} below X (X median {_median(below):.2f})")
            out.append(f"| {name} | {side} | ours | {_median(o['toe_x_mm'] for o in ours):.2f} | - | "
                       f"{len(ours)}/{len(sel)} | {radius} | {_median(o['angle_deg'] for o in ours):.1f} |")
            for setting in ("default", "best"):
                for method, angle in (("CM", "MAX"), ("LSM", "END-LSM"), ("IM", "END-IM")):
                    got = [(r["ours"], r["peer"][setting]) for r in sel]
                    found = [(o, p) for o, p in got if "failed" not in p[method]]
                    off = [abs(p[method]["toe_x_mm"] - o["toe_x_mm"]) for o, p in found if "failed" not in o]
                    at = [(o, p) for o, p in found if "failed" not in o
                          and abs(p[method]["toe_x_mm"] - o["toe_x_mm"]) <= AT_TOE_MM]
                    r_at = _median(p[method]["radius_mm"] for _, p in at)
                    angles = [p[angle]["angle_deg"] for _, p in got if "failed" not in p[angle]]
                    out.append(f"| {name} | {side} | {method} / {angle} ({setting}) | "
                               f"{_median(p[method]['toe_x_mm'] for _, p in found):.2f} | {_median(off):.2f} | "
                               f"{len(at)}/{len(sel)} ({len(sel) - len(found)} failed) | "
                               f"{r_at:.2f} at the toe, {_median(p[method]['radius_mm'] for _, p in found):.2f} all | "
                               f"{_median(angles):.1f} |")
    return out


def drawn_truth(x: np.ndarray, h: np.ndarray) -> dict:
    """The toe drawn in a noise-free one-toe profile (``x`` (n,) mm from the weld's top onto the
    plate, ``h`` (n,) mm, the plate at 0): its fillet is the run of concave points (three-point
    circles), its radius their median; the angle the slope where the fillet meets the cap; the
    tangent point on the plate and the flank's virtual corner (the tangent there met with the plate)."""
    p = np.column_stack([x, h])
    a, b, c = p[:-2], p[1:-1], p[2:]
    cross = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    kappa = 2 * cross / (np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - b, axis=1) * np.linalg.norm(c - a, axis=1))
    fillet = np.nonzero(kappa > 1e-6)[0] + 1
    first, last = fillet.min(), fillet.max()
    slope = abs((h[first] - h[first - 1]) / (x[first] - x[first - 1]))
    return {"radius_mm": float(1 / np.median(kappa[fillet - 1])), "angle_deg": math.degrees(math.atan(slope)),
            "tangent_x_mm": float(x[last + 1]), "corner_x_mm": float(x[first] + h[first] / slope)}


def artificial(peer, path: Path, rng: np.random.Generator) -> dict:
    """Both tools on one of the port's artificial profiles (its header states kt; cm in the file):
    exact, and resampled at 0.05 mm with the real scans' noise (``NOISY_DRAWS`` draws)."""
    text = path.read_text().splitlines()
    data = np.loadtxt(text[1:])[:, :2] * 10.0
    x, h = data[:, 0], data[:, 1]
    truth = drawn_truth(x, h)
    settings = profile_settings(MeasureWeldConfig())

    def both(xx, hh) -> dict:
        res = measure_profile(xx, hh, settings=settings, treated=False, line="a", position_mm=0.0,
                              to_frame=lambda u, v: (u, 0.0, v)).toes[1]
        ours = ({"failed": res.reason} if res.fit is None else
                {"toe_x_mm": res.fit.position_u_mm, "angle_deg": res.fit.flank_angle_deg.value,
                 "radius_mm": res.fit.notch_radius.value, "radius_below_mm": res.radius_below_mm})
        order = np.argsort(-xx)  # from the plate onto the weld, v = -x ascending
        return {"ours": ours, "peer": {s: _plain(run_peer(peer, -xx[order], hh[order], s), -1.0)
                                       for s in ("default", "best")}}

    exact = both(x, h)
    noisy = []
    for _ in range(NOISY_DRAWS):
        xs = np.arange(x.min(), x.max(), NOISY_SPACING_MM) + rng.uniform(0, NOISY_SPACING_MM)
        xs = xs[xs <= x.max()]
        xs, hs = add_scan_noise(xs, np.interp(xs, x, h), spacing_mm=NOISY_SPACING_MM, noise=REAL_SCAN_NOISE, rng=rng)
        noisy.append(both(xs, hs))
    return {"file": path.name, "header": text[0].strip(), "truth": truth, "exact": exact, "noisy": noisy}


def drawn_rows(peer, rng: np.random.Generator) -> list[str]:
    """Both tools on drawn toes (``simulator.weld_profiles``: ``DRAWN_RADII_MM`` at ``DRAWN_ANGLE_DEG``,
    0.05 mm, the real scans' noise; the peer at its best settings): medians over both toes of
    ``DRAWN_PROFILES`` profiles."""
    settings = profile_settings(MeasureWeldConfig())
    out = []
    for r in DRAWN_RADII_MM:
        ours, theirs = [], []
        for _ in range(DRAWN_PROFILES):
            u, h, _ = draw_butt_profile(toe_radius_mm=r, toe_angle_deg=DRAWN_ANGLE_DEG, spacing_mm=0.05,
                                        noise=REAL_SCAN_NOISE, rng=rng)
            res = measure_profile(u, h, settings=settings, treated=False, line="d", position_mm=0.0,
                                  to_frame=lambda a, b: (a, 0.0, b))
            ours += [t for t in res.toes if t.fit is not None]
            for side, x, hh in split_profile(u, h):
                sign = 1.0 if side == "minus" else -1.0
                theirs.append(run_peer(peer, sign * x, hh, "best"))
        resolved = [t.fit.notch_radius.value for t in ours if t.radius_below_mm is None]
        below = [t.radius_below_mm for t in ours if t.radius_below_mm is not None]
        cells = [f"{len(resolved)} resolved ({_median(resolved):.2f}), {len(below)} below X (X median "
                 f"{_median(below):.2f}, holds {sum(b >= r for b in below)})",
                 f"{_median(t.fit.flank_angle_deg.value for t in ours):.1f}"]
        for method, angle in (("CM", "MAX"), ("LSM", "END-LSM"), ("IM", "END-IM")):
            got = [t[method]["radius_mm"] for t in theirs if "failed" not in t[method]]
            angles = [t[angle]["angle_deg"] for t in theirs if "failed" not in t[angle]]
            cells.append(f"{_median(got):.2f} ({len(theirs) - len(got)} failed), {_median(angles):.1f} deg")
        out.append(f"| {r} | {DRAWN_ANGLE_DEG:g} | " + " | ".join(cells) + " |")
    return out


def artificial_rows(result: dict) -> list[str]:
    """Markdown rows: the truth, then per tool its toe x, radius and angle (exact; noisy: median (worst) error)."""
    t = result["truth"]
    out = [f"| {result['file']} ({result['header']}) | drawn | tangent {t['tangent_x_mm']:.3f}, corner "
           f"{t['corner_x_mm']:.3f} | {t['radius_mm']:.3f} | {t['angle_deg']:.2f} | - | - | - |"]

    def err(values, truth):
        v = np.asarray([x - truth for x in values if x is not None and math.isfinite(x)])
        return f"{np.median(v):+.3f} ({v[np.argmax(np.abs(v))]:+.3f})" if len(v) else "-"

    o, noisy = result["exact"]["ours"], [n["ours"] for n in result["noisy"]]
    below = [n["radius_below_mm"] for n in noisy if n.get("radius_below_mm") is not None]
    out.append(f"| | ours | {o['toe_x_mm']:.3f} | {o['radius_mm']:.3f} | {o['angle_deg']:.2f} | "
               f"{err([n.get('toe_x_mm') for n in noisy], t['corner_x_mm'])} | "
               f"{len(below)} below X (X median {_median(below):.2f}, holds {sum(b >= t['radius_mm'] for b in below)}), "
               f"{err([n['radius_mm'] for n in noisy if n.get('radius_below_mm') is None], t['radius_mm'])} | "
               f"{err([n.get('angle_deg') for n in noisy], t['angle_deg'])} |")
    for setting in ("default", "best"):
        for method, angle in (("CM", "MAX"), ("LSM", "END-LSM"), ("IM", "END-IM")):
            p = result["exact"]["peer"][setting]
            got = [n["peer"][setting] for n in result["noisy"]]
            x = "failed" if "failed" in p[method] else f"{p[method]['toe_x_mm']:.3f}"
            r = "failed" if "failed" in p[method] else f"{p[method]['radius_mm']:.3f}"
            a = "failed" if "failed" in p[angle] else f"{p[angle]['angle_deg']:.2f}"
            ref = t["tangent_x_mm"] if method == "IM" else t["tangent_x_mm"] - t["radius_mm"] * math.sin(
                math.radians(t["angle_deg"]) / 2)
            failed = sum("failed" in g[method] for g in got)
            out.append(f"| | {method} / {angle} ({setting}) | {x} | {r} | {a} | "
                       f"{err([g[method]['toe_x_mm'] for g in got if 'failed' not in g[method]], ref)} | "
                       f"{failed} failed, {err([g[method]['radius_mm'] for g in got if 'failed' not in g[method]], t['radius_mm'])} | "
                       f"{err([g[angle]['angle_deg'] for g in got if 'failed' not in g[angle]], t['angle_deg'])} |")
    return out


def pick_sections(rows: list[dict]) -> list[dict]:
    """Per file and side the profiles where the tools differ most: the peer's best-setting toe
    (CM, IM) furthest from ours, and its MAX angle furthest from ours."""
    picked = []
    for name in sorted({r["file"] for r in rows}):
        for side in ("minus", "plus"):
            sel = [r for r in rows if r["file"] == name and r["side"] == side and "failed" not in r["ours"]]

            def gap(r, method):
                p = r["peer"]["best"][method]
                return -1.0 if "failed" in p else abs(p.get("toe_x_mm", r["ours"]["toe_x_mm"]) - r["ours"]["toe_x_mm"])

            def angle_gap(r):
                p = r["peer"]["best"]["MAX"]
                return -1.0 if "failed" in p else abs(p["angle_deg"] - r["ours"]["angle_deg"])

            for key in (lambda r: gap(r, "CM"), lambda r: gap(r, "IM"), angle_gap):
                best = max(sel, key=key)
                if best not in picked:
                    picked.append(best)
    return picked


def draw_section(points: np.ndarray, row: dict, out: Path) -> Path:
    """One toe: the half profile (top: 6 mm around our toe) and 1.5 mm around it (bottom, the
    height exaggerated), ours (toe, flank at its angle) and the peer's best-setting circles and toes."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, h = next((x, h) for s, x, h in profile_halves(points, row["y_mm"]) if s == row["side"])
    o, p = row["ours"], row["peer"]["best"]
    inward = 1.0 if row["side"] == "minus" else -1.0  # the weld lies toward +x of a minus toe
    fig, axes = plt.subplots(2, 1, figsize=(6.4, 6.4), dpi=90)
    for ax, half in zip(axes, (3.0, 0.75)):
        lo, hi = o["toe_x_mm"] - half, o["toe_x_mm"] + half
        inside = (x >= lo) & (x <= hi)
        ax.plot(x[inside], h[inside], ".", color="k", ms=2.5, label="points")
        ax.axvline(o["toe_x_mm"], color="k", lw=1.2, label=f"ours: {o['angle_deg']:.1f} deg, " + (
            f"r {o['radius_mm']:.2f}" if o["radius_below_mm"] is None else f"r below {o['radius_below_mm']:.2f}"))
        run = np.linspace(0, 1.2 * half, 20)
        ax.plot(o["toe_x_mm"] + inward * run, run * math.tan(math.radians(o["angle_deg"])), "k--", lw=0.8)
        for method, colour in (("CM", "tab:blue"), ("LSM", "tab:red"), ("IM", "tab:green")):
            if "failed" in p[method]:
                continue
            c, r = p[method]["centre_mm"], p[method]["radius_mm"]
            t = np.linspace(0, 2 * np.pi, 200)
            ax.plot(c[0] + r * np.cos(t), c[1] + r * np.sin(t), color=colour, lw=0.8)
            ax.axvline(p[method]["toe_x_mm"], color=colour, lw=0.8, ls=":",
                       label=f"{method}: r {r:.2f}" + (f", {p['MAX']['angle_deg']:.1f} deg (MAX)" if method == "CM" else ""))
        ax.set_xlim(lo, hi)
        ax.set_ylim(-0.1, 1.2 if half > 1 else 0.4)
        ax.grid(color="0.9", lw=0.5)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=6, loc="upper left" if inward < 0 else "upper right")
    axes[0].set_title(f"{row['file']}  y = {row['y_mm']:g} mm  {row['side']} toe (peer: best settings)", fontsize=9)
    axes[1].set_xlabel("x mm (file); height over the plate mm", fontsize=8)
    fig.tight_layout()
    path = out / f"{Path(row['file']).stem}_y{row['y_mm']:05.1f}_{row['side']}.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("peer", type=Path, help="a local copy of SchluppIng/Weld_Toe_Determination")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of profile scans (*.xyz, mm)")
    parser.add_argument("--json", type=Path, help="per-profile rows and the artificial profiles' answers")
    parser.add_argument("--pictures", type=Path, help="folder for the sections where the tools differ (PNG)")
    args = parser.parse_args()
    peer = load_peer(args.peer)
    if isinstance(peer, str):
        print(f"bench_peer_toes: {peer}", file=sys.stderr)
        return 2
    scans = sorted(args.data.glob("*.xyz"))
    if not scans:
        print(f"bench_peer_toes: no *.xyz scans in {args.data}", file=sys.stderr)
        return 2
    rows, clouds = [], {}
    for scan in scans:
        clouds[scan.name] = read_point_cloud(scan, units="mm").points_mm
        rows += compare_scan(peer, clouds[scan.name], scan.name)
    print(f"| file | toe | tool (settings) | toe x median mm | off ours median mm | at the toe (within {AT_TOE_MM} mm "
          "of ours) | radius median mm | angle median deg |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(summary_rows(rows)))
    rng = np.random.default_rng(27)
    answers = [artificial(peer, path, rng) for path in sorted((args.peer / "examples").glob("*.asc"))]
    print(f"\n| profile | tool (settings) | toe x mm | radius mm | angle deg | noisy ({NOISY_DRAWS} draws at "
          f"{NOISY_SPACING_MM} mm): toe x error median (worst) | radius | angle |")
    print("|---|---|---|---|---|---|---|---|")
    for result in answers:
        print("\n".join(artificial_rows(result)))
    print("\n| drawn r mm | angle deg | ours: radius | ours: angle deg | CM / MAX (best) | LSM / END-LSM (best) "
          "| IM / END-IM (best) |")
    print("|---|---|---|---|---|---|---|")
    print("\n".join(drawn_rows(peer, rng)))
    if args.pictures:
        args.pictures.mkdir(parents=True, exist_ok=True)
        for row in pick_sections(rows):
            print(f"picture: {draw_section(clouds[row['file']], row, args.pictures)}")
    if args.json:
        args.json.write_text(json.dumps({"settings": {s: {k: v for k, v in peer_settings(peer, s).items()}
                                                      for s in ("default", "best")},
                                         "crop_mm": CROP_MM, "profiles": rows, "artificial": answers}, indent=1,
                                        default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
