"""The weld measured on the reconstruction: sections across each weld line, a fit per toe.

A weld line is a polyline on one face of the part (specimen frame, mm). Its section frame:
``t`` along the line, ``n`` the face's outward normal (from the measured normals near the line),
``a`` across the weld (``n x t``, turned to the specimen's +x where it has a component there).
Each section takes the measured points within ``section_half_width_mm`` of its position along the
line and reads them as a profile: ``u`` across (mm, along ``a``), ``h`` height (mm, along ``n``).

Per section (every figure a value and its 1-sigma from its fit's residuals and covariance):

- the two plates: a line each, fitted robustly on ``plate_window_mm`` beside the weld's centre;
  axial misalignment (the plus plate's height over the minus one's at the centre) and angular
  misalignment (the plus plate's slope less the minus one's, degrees);
- each toe (``minus``: u < centre, ``plus``: u > centre), as welded: the flank (a line bending
  with a curvature), a toe fillet of radius r tangent to the plate and to the flank's tangent at
  the toe, and an undercut (a Gaussian dip beside the fillet) where the plate dips below its line,
  fitted together by non-linear least squares: toe position, flank angle (the tangent at the toe
  to the plate), toe radius, undercut depth;
- an HFMI groove where the profile dips below the plate beside the toe: a circle fitted to the
  groove's lower part (the pin's imprint): depth below the plate, width at the plate, radius; the
  flank above it fitted by a line over ``toe_window_mm[0]`` inward of where the groove meets the
  weld (the toe's position on a treated weld): the flank angle the weld has now, just above the
  groove (the original flank at the toe is cut away by the pin); the toe is within the groove
  when the groove's wall runs up into the weld's flank with no stretch of plate between them
  longer than ``groove_plate_gap_mm``;
- reinforcement height (the peak over the line between the toes, a parabola over the peak, on the
  points within ``height_half_width_mm`` of the section, or its nearest ten over the cap's middle)
  and width (between the toes).

The line is refined on the data: a first pass finds each section's centre, a line through them
(robust) gives the weld's true offset and direction in the face, and the sections are cut again
across it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

__all__ = ["Measured", "GrooveFit", "ToeFit", "PlateFit", "SectionMeasurement", "WeldLineMeasurement",
           "SectionSettings", "fit_plate_line", "fit_toe", "fit_groove", "measure_section", "measure_weld_line",
           "along_weld_statistics", "TOE_SIDES"]

TOE_SIDES = ("minus", "plus")
_NAN = float("nan")


@dataclass(frozen=True)
class Measured:
    """A measured figure: its value and 1-sigma (NaN: not measured / not determined)."""

    value: float
    sigma: float

    @staticmethod
    def none() -> "Measured":
        return Measured(_NAN, _NAN)

    def as_dict(self, digits: int = 4) -> dict[str, float | None]:
        def r(x: float) -> float | None:
            return None if not math.isfinite(x) else round(float(x), digits)
        return {"value": r(self.value), "sigma": r(self.sigma)}


@dataclass(frozen=True)
class SectionSettings:
    """How a section is read (mm, degrees); the stage passes its settings, nothing defaults here."""

    plate_window_mm: tuple[float, float]  # plate fitted from .. to this far from the weld's centre
    toe_window_mm: tuple[float, float]  # toe fit: this far onto the flank, this far onto the plate
    toe_threshold_mm: float  # height over the plate that starts the weld (toe first guess)
    groove_min_depth_mm: float  # a dip deeper than this beside the toe is a groove (treated welds)
    groove_plate_gap_mm: float  # a longer stretch of plate between groove and flank: the toe is not within it
    undercut_min_depth_mm: float  # a dip deeper than this beside an as-welded toe is fitted as undercut
    height_half_width_mm: float  # the peak is read on the points this close to the section
    min_points: int  # fewer points in a fit: not measured


@dataclass(frozen=True)
class PlateFit:
    slope: float
    intercept: float  # height at u = 0
    cov: np.ndarray  # (2, 2) of (slope, intercept)
    rms_mm: float
    n_points: int

    def at(self, u: np.ndarray | float) -> np.ndarray | float:
        return self.slope * np.asarray(u) + self.intercept


@dataclass(frozen=True)
class GrooveFit:
    depth: Measured  # below the plate, mm
    width: Measured  # chord at plate level, mm
    radius: Measured  # the imprint's radius, mm
    centre_v_mm: float  # outward from the toe's old position
    toe_within: bool
    rms_mm: float
    n_points: int


@dataclass(frozen=True)
class ToeFit:
    side: str
    position_u_mm: float  # where the flank (or its extension) meets the plate, across the weld
    flank_angle_deg: Measured
    radius: Measured  # the toe fillet's (as welded) or the groove's (treated)
    undercut_depth: Measured
    groove: GrooveFit | None
    rms_mm: float
    n_points: int
    note: str = ""


@dataclass(frozen=True)
class SectionMeasurement:
    line: str
    position_mm: float  # along the line from its first point
    centre_mm: tuple[float, float, float]  # the weld's centre at the section, the frame the points came in
    height: Measured
    width: Measured
    axial_misalignment: Measured
    angular_misalignment_deg: Measured
    toes: tuple[ToeFit | None, ToeFit | None]
    n_points: int
    note: str = ""


@dataclass(frozen=True)
class WeldLineMeasurement:
    line: str
    sections: list[SectionMeasurement]
    offset_mm: float  # the refined line's shift across the nominal one (along a), at its middle
    turn_deg: float  # the refined line's turn from the nominal one, in the face
    normal: tuple[float, float, float]
    across: tuple[float, float, float]
    extent_mm: tuple[float, float] = field(default=(0.0, 0.0))  # the measured part of the line


def _sigmas(res, n_params: int) -> tuple[np.ndarray, float]:
    """Covariance of a least_squares result from its Jacobian and residuals, and the RMS."""
    r = res.fun
    dof = max(len(r) - n_params, 1)
    s2 = float(r @ r) / dof
    J = res.jac
    try:
        cov = np.linalg.pinv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((n_params, n_params), np.nan)
    return cov, math.sqrt(float(np.mean(r * r))) if len(r) else _NAN


def _propagate(f, p: np.ndarray, cov: np.ndarray) -> float:
    """1-sigma of f(p) from the parameters' covariance (first order, central differences)."""
    g = np.zeros(len(p))
    for k in range(len(p)):
        step = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros(len(p))
        dp[k] = step
        g[k] = (f(p + dp) - f(p - dp)) / (2 * step)
    var = float(g @ cov @ g)
    return math.sqrt(var) if var >= 0 and math.isfinite(var) else _NAN


def fit_plate_line(u: np.ndarray, h: np.ndarray, *, min_points: int) -> PlateFit | None:
    """A line h = slope * u + intercept through the points, trimmed of outliers (stickers, spatter)
    by 3 robust sigmas, three rounds. ``u``, ``h``: (n,) float64, mm. None: too few points."""
    u, h = np.asarray(u, np.float64), np.asarray(h, np.float64)
    if u.shape != h.shape or u.ndim != 1:
        raise ValueError(f"u and h must be (n,) arrays of one length, got {u.shape} and {h.shape}")
    keep = np.isfinite(u) & np.isfinite(h)
    if keep.sum() < max(min_points, 3):
        return None
    # least median of squares first (a sticker can cover a third of a plate window, 0.1 mm high):
    # lines through point pairs drawn with a fixed seed, the one whose median |residual| is least
    uk, hk = u[keep], h[keep]
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, len(uk), size=(2, 300))
    ok = np.abs(uk[i] - uk[j]) > 1e-6
    if ok.any():
        slopes = (hk[j[ok]] - hk[i[ok]]) / (uk[j[ok]] - uk[i[ok]])
        offsets = hk[i[ok]] - slopes * uk[i[ok]]
        med = np.median(np.abs(hk[None, :] - (slopes[:, None] * uk[None, :] + offsets[:, None])), axis=1)
        best = int(np.argmin(med))
        r = h - (slopes[best] * u + offsets[best])
        keep = keep & (np.abs(r) <= max(3 * 1.4826 * med[best], 1e-3))
    for _ in range(3):
        if keep.sum() < max(min_points, 3):
            return None
        A = np.stack([u[keep], np.ones(int(keep.sum()))], 1)
        coef, *_ = np.linalg.lstsq(A, h[keep], rcond=None)
        r = h - (coef[0] * u + coef[1])
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = keep & (np.abs(r) <= max(3 * mad, 1e-3))
        if np.array_equal(new, keep):
            break
        keep = new
    if keep.sum() < max(min_points, 3):
        return None
    A = np.stack([u[keep], np.ones(int(keep.sum()))], 1)
    coef, *_ = np.linalg.lstsq(A, h[keep], rcond=None)
    r = h[keep] - A @ coef
    dof = max(len(r) - 2, 1)
    cov = np.linalg.pinv(A.T @ A) * float(r @ r) / dof
    return PlateFit(float(coef[0]), float(coef[1]), cov, float(np.sqrt(np.mean(r * r))), int(keep.sum()))


def _toe_model(p: np.ndarray, w: np.ndarray, undercut: bool) -> np.ndarray:
    """Height over the plate at w (outward from the toe, mm): flank -w tan(theta) - k w^2 inside,
    a fillet of radius r tangent to the plate and to the flank's tangent line, an undercut dip."""
    v0, theta, r, k = p[:4]
    x = w - v0
    t = math.tan(theta)
    d = r * math.tan(theta / 2)
    flank = np.where(x < 0, -x * t - k * x * x, 0.0)
    in_fillet = (x > -d * math.cos(theta)) & (x < d)
    fillet = r - np.sqrt(np.maximum(r * r - (x - d) ** 2, 0.0))
    z = np.where(in_fillet, np.maximum(flank, fillet), flank)
    if undercut:
        depth, centre, width = p[4:7]
        z = z - depth * np.exp(-(((x - d - centre) / width) ** 2))
    return z


def fit_toe(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, side: str, toe_guess_v: float) -> ToeFit | None:
    """The as-welded toe in a profile: ``v`` (n,) outward from the weld's centre (mm), ``h`` (n,)
    height over this side's plate line (mm); ``toe_guess_v`` where the weld starts. Fits the
    flank, toe fillet and undercut model over ``settings.toe_window_mm`` around the guess."""
    flank_mm, plate_mm = settings.toe_window_mm
    sel = (v > toe_guess_v - flank_mm) & (v < toe_guess_v + plate_mm)
    w, z = v[sel], h[sel]
    if len(w) < settings.min_points:
        return None
    on_flank = (z > 0.2 * z.max()) & (w < toe_guess_v)
    theta0 = math.radians(30.0)
    if on_flank.sum() >= 2:
        slope = np.polyfit(w[on_flank], z[on_flank], 1)[0]
        theta0 = float(np.clip(math.atan(max(-slope, 0.05)), math.radians(3), math.radians(80)))
    plate_side = w > toe_guess_v + 0.2
    undercut = bool(plate_side.any() and z[plate_side].min() < -settings.undercut_min_depth_mm)
    best = None
    for r0 in (0.3, 1.0, 2.5):
        p0 = [toe_guess_v, theta0, r0, 0.0]
        lo = [toe_guess_v - flank_mm, math.radians(2), 0.02, 0.0]
        hi = [toe_guess_v + plate_mm, math.radians(85), 10.0, 5.0]
        if undercut:
            p0 += [max(-float(z[plate_side].min()), 0.01), 0.3, 0.3]
            lo += [0.0, -0.5, 0.05]
            hi += [2.0, 2.0, 1.5]
        p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
        res = least_squares(lambda p: _toe_model(p, w, undercut) - z, p0, bounds=(lo, hi), x_scale="jac")
        if best is None or res.cost < best.cost:
            best = res
    p = best.x
    cov, rms = _sigmas(best, len(p))
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    return ToeFit(side=side, position_u_mm=float(p[0]),
                  flank_angle_deg=Measured(math.degrees(p[1]), math.degrees(sd[1])),
                  radius=Measured(float(p[2]), float(sd[2])),
                  undercut_depth=Measured(float(p[4]), float(sd[4])) if undercut else Measured(0.0, 0.0),
                  groove=None, rms_mm=rms, n_points=len(w))


def _circle_residuals(p: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.hypot(v - p[0], z - p[1]) - p[2]


def fit_groove(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, side: str, toe_guess_v: float) -> ToeFit | None:
    """A treated toe: the groove's circle on its lower part (points deeper than a quarter of its
    depth, around its deepest point), the flank above it by a parabola extended to the plate.
    ``v``, ``h`` as in ``fit_toe``. None: no groove deeper than ``groove_min_depth_mm``."""
    flank_mm, plate_mm = settings.toe_window_mm
    region = (v > toe_guess_v - flank_mm) & (v < toe_guess_v + plate_mm + 8.0)
    if region.sum() < settings.min_points or h[region].min() > -settings.groove_min_depth_mm:
        return None
    order = np.argsort(v[region])
    vv, hh = v[region][order], h[region][order]
    k = int(np.argmin(hh))
    depth0 = -float(hh[k])
    deep = hh < -0.25 * depth0
    lo_k = k
    while lo_k > 0 and deep[lo_k - 1]:
        lo_k -= 1
    hi_k = k
    while hi_k < len(vv) - 1 and deep[hi_k + 1]:
        hi_k += 1
    gv, gz = vv[lo_k:hi_k + 1], hh[lo_k:hi_k + 1]
    if len(gv) < max(settings.min_points, 4):
        return None
    span = max(gv[-1] - gv[0], 1e-3)
    r0 = (span * span / 4 + depth0 * depth0) / (2 * depth0)
    lo, hi = np.array([gv[0] - 5, -50.0, 0.05]), np.array([gv[-1] + 5, 50.0, 60.0])
    x0 = np.clip([float(vv[k]), r0 - depth0, r0], lo + 1e-9, hi - 1e-9)
    res = least_squares(_circle_residuals, x0, args=(gv, gz), bounds=(lo, hi), x_scale="jac")
    p = res.x
    cov, rms = _sigmas(res, 3)

    def depth(q):
        return q[2] - q[1]

    def width(q):
        return 2 * math.sqrt(max(q[2] ** 2 - q[1] ** 2, 0.0))

    D, W = depth(p), width(p)
    g_depth = Measured(D, _propagate(depth, p, cov))
    g_width = Measured(W, _propagate(width, p, cov))
    g_radius = Measured(float(p[2]), math.sqrt(max(float(cov[2, 2]), 0.0)))
    # the groove's inner edge: inward from its deepest point, the last point on the circle (three
    # off it in a row end the walk); the flank is the points inward of that edge
    on_circle_z = p[1] - np.sqrt(np.maximum(p[2] ** 2 - (v - p[0]) ** 2, 0.0))
    on = (np.abs(v - p[0]) < p[2]) & (np.abs(h - on_circle_z) <= max(3 * rms, 0.02))
    inner = np.flatnonzero(v <= vv[k])
    inner = inner[np.argsort(-v[inner])]
    v_meet, misses = float(vv[k]), 0
    for i in inner:
        if on[i]:
            v_meet, misses = float(v[i]), 0
        else:
            misses += 1
            if misses >= 3:
                break
    flank = (v < v_meet - 0.05) & (v > v_meet - flank_mm) & (h > 0)
    # the toe is within the groove when the groove's wall runs straight up into the weld's flank:
    # no stretch of plate (|h| < groove_min_depth_mm) longer than groove_plate_gap_mm between them
    inward = np.sort(v[(v < vv[k]) & (v > toe_guess_v - flank_mm - W)])
    level = np.sort(v[(v < vv[k]) & (v > toe_guess_v - flank_mm - W) & (np.abs(h) < settings.groove_min_depth_mm)])
    up = v[(v < vv[k]) & (h > settings.toe_threshold_mm)]
    flat = level[level > up.max()] if len(up) else level
    toe_within = bool(len(up) and len(inward) and (len(flat) < 2 or flat.max() - flat.min() <= settings.groove_plate_gap_mm))
    note = ""
    angle, toe_v = Measured.none(), v_meet
    if flank.sum() >= 3:
        fv, fz = v[flank], h[flank]
        if len(fv) >= 3 and np.ptp(fv) > 0.1:
            A = np.stack([fv, np.ones(len(fv))], 1)
            coef, *_ = np.linalg.lstsq(A, fz, rcond=None)
            r = fz - A @ coef
            c_cov = np.linalg.pinv(A.T @ A) * float(r @ r) / max(len(r) - 2, 1)
            if coef[0] < 0:
                angle = Measured(math.degrees(math.atan(-coef[0])),
                                 math.degrees(math.sqrt(max(c_cov[0, 0], 0.0)) / (1 + coef[0] ** 2)))
            else:
                note = "the flank above the groove does not fall toward the plate"
        else:
            note = "too few flank points above the groove"
    else:
        note = "too few flank points above the groove"
    groove = GrooveFit(depth=g_depth, width=g_width, radius=g_radius, centre_v_mm=float(p[0]),
                       toe_within=toe_within, rms_mm=rms, n_points=len(gv))
    return ToeFit(side=side, position_u_mm=toe_v, flank_angle_deg=angle, radius=g_radius,
                  undercut_depth=Measured(0.0, 0.0), groove=groove, rms_mm=rms, n_points=len(gv), note=note)


def _centre_guess(u: np.ndarray, h: np.ndarray) -> float | None:
    """The weld's centre across a profile: the middle of the band raised over the plate (median
    height), over half the highest rise (on 0.5 mm bins)."""
    if len(u) < 10:
        return None
    plate = fit_plate_line(u, h, min_points=10)  # the plates dominate a section: tilt taken out
    base = plate.at(u) if plate is not None else np.median(h)
    bins = np.floor(u / 0.5).astype(np.int64)
    ub, inv = np.unique(bins, return_inverse=True)
    top = np.full(len(ub), -np.inf)
    np.maximum.at(top, inv, h - base)
    if top.max() <= 0:
        return None
    high = top > 0.5 * top.max()
    k = lo = hi = int(np.argmax(top))  # the run of high bins around the highest (gaps of 2 bins bridged)
    while lo > 0 and (high[lo - 1] or (lo > 1 and high[lo - 2] and ub[lo - 1] - ub[lo - 2] <= 2)):
        lo -= 1
    while hi < len(ub) - 1 and (high[hi + 1] or (hi < len(ub) - 2 and high[hi + 2] and ub[hi + 2] - ub[hi + 1] <= 2)):
        hi += 1
    del k
    return float((ub[lo] + ub[hi] + 1) * 0.25)


def measure_section(u: np.ndarray, h: np.ndarray, s: np.ndarray, *, settings: SectionSettings, treated: bool,
                    line: str, position_mm: float, to_frame) -> SectionMeasurement:
    """One section: ``u`` across (mm), ``h`` along the face normal (mm), ``s`` along the line
    relative to the section (mm), (n,) float64 each. ``treated``: look for HFMI grooves.
    ``to_frame(u, h)``: the 3-D point (the points' frame) of a profile position."""
    n = len(u)
    empty = (None, None)

    def failed(why: str) -> SectionMeasurement:
        none = Measured.none()
        return SectionMeasurement(line, position_mm, tuple(float(x) for x in to_frame(0.0, 0.0)), none, none, none,
                                  none, empty, n, why)

    c = _centre_guess(u, h)
    if c is None:
        return failed("no raised weld in the section")
    near, far = settings.plate_window_mm
    plates = []
    for sign in (-1, 1):
        sel = (sign * (u - c) > near) & (sign * (u - c) < far)
        plates.append(fit_plate_line(u[sel], h[sel], min_points=settings.min_points))
    if plates[0] is None or plates[1] is None:
        return failed("a plate beside the weld has too few points")
    toes: list[ToeFit | None] = []
    for side, sign, plate in (("minus", -1, plates[0]), ("plus", 1, plates[1])):
        half = sign * (u - c) >= 0
        v = sign * (u[half] - c)
        rel = h[half] - plate.at(u[half])
        order = np.argsort(v)
        v, rel = v[order], rel[order]
        raised = rel > settings.toe_threshold_mm
        if not raised.any():
            toes.append(None)
            continue
        # outward from the centre, the last point of the raised run that starts at the centre
        first_low = np.flatnonzero(~raised & (v > v[raised].min()))
        guess = float(v[first_low[0]]) if len(first_low) else float(v[raised].max())
        fit = fit_groove(v, rel, settings=settings, side=side, toe_guess_v=guess) if treated else None
        if fit is None:
            fit = fit_toe(v, rel, settings=settings, side=side, toe_guess_v=guess)
        if fit is not None:
            fit = ToeFit(**{**fit.__dict__, "position_u_mm": c + sign * fit.position_u_mm})
        toes.append(fit)
    # misalignment at the weld's centre
    a, b = plates
    axial = b.at(c) - a.at(c)
    J = np.array([c, 1.0])
    axial_sd = math.sqrt(max(J @ a.cov @ J + J @ b.cov @ J, 0.0))
    ang = math.degrees(math.atan(b.slope) - math.atan(a.slope))
    ang_sd = math.degrees(math.sqrt(max(a.cov[0, 0] / (1 + a.slope ** 2) ** 2 + b.cov[0, 0] / (1 + b.slope ** 2) ** 2, 0)))
    height = width = Measured.none()
    centre = c
    if toes[0] is not None and toes[1] is not None:
        u0, u1 = toes[0].position_u_mm, toes[1].position_u_mm
        width = Measured(u1 - u0, math.hypot(_toe_sd(toes[0]), _toe_sd(toes[1])))
        centre = (u0 + u1) / 2
        z0, z1 = float(a.at(u0)), float(b.at(u1))
        # the peak on the points nearest the section along the line (bead ripples): within
        # height_half_width_mm, or out to the tenth nearest point over the cap's middle
        between = (u > u0) & (u < u1)
        middle = np.sort(np.abs(s[between & (np.abs(u - centre) < 2.0)]))
        reach = max(settings.height_half_width_mm, float(middle[min(9, len(middle) - 1)]) if len(middle) else np.inf)
        between &= np.abs(s) <= reach
        rise = h[between] - (z0 + (z1 - z0) * (u[between] - u0) / max(u1 - u0, 1e-9))
        height = _peak(u[between], rise)
    return SectionMeasurement(line, position_mm, tuple(float(x) for x in to_frame(centre, float(a.at(centre)))),
                              height, width, Measured(float(axial), axial_sd), Measured(ang, ang_sd),
                              (toes[0], toes[1]), n)


def _toe_sd(toe: ToeFit) -> float:
    return 0.05 if toe.groove is not None else max(toe.radius.sigma if math.isfinite(toe.radius.sigma) else 0.05, 0.0)


def _peak(u: np.ndarray, rise: np.ndarray) -> Measured:
    """The highest rise: a parabola over the points within 1 mm of the highest one."""
    if len(u) < 3:
        return Measured.none()
    k = int(np.argmax(rise))
    sel = np.abs(u - u[k]) <= 1.0
    if sel.sum() < 4:
        return Measured(float(rise[k]), _NAN)
    x = u[sel] - u[k]
    A = np.stack([x * x, x, np.ones(len(x))], 1)
    coef, *_ = np.linalg.lstsq(A, rise[sel], rcond=None)
    r = rise[sel] - A @ coef
    cov = np.linalg.pinv(A.T @ A) * float(r @ r) / max(len(r) - 3, 1)

    def top(c):
        if c[0] >= -1e-9:  # not a cap: the highest fitted value on the points
            return float(np.max(c[0] * x * x + c[1] * x + c[2]))
        xm = float(np.clip(-c[1] / (2 * c[0]), x.min(), x.max()))
        return c[0] * xm * xm + c[1] * xm + c[2]

    return Measured(float(top(coef)), _propagate(top, coef, cov))


def _frame(points_line: np.ndarray, normals_near: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = points_line[-1] - points_line[0]
    t = t / np.linalg.norm(t)
    n = normals_near.mean(axis=0)
    n = n - (n @ t) * t
    n = n / np.linalg.norm(n)
    a = np.cross(n, t)
    if a[0] < 0 or (abs(a[0]) < 1e-9 and a[1] < 0):
        a = -a
    return t, n, a


def measure_weld_line(points: np.ndarray, normals: np.ndarray, line_points_mm: np.ndarray, *, name: str,
                      step_mm: float, section_half_width_mm: float, reach_mm: float, end_margin_mm: float,
                      min_normal_cos: float, settings: SectionSettings, treated: bool) -> WeldLineMeasurement:
    """Sections every ``step_mm`` across one weld line. ``points``, ``normals``: (n, 3) float64, mm,
    unit, the measured surface in the frame of ``line_points_mm`` ((k, 3), a straight line: its
    first and last point), normals outward. Points within ``reach_mm`` across the line, facing
    its face (normal . n > ``min_normal_cos``) are read; sections run where they reach, less
    ``end_margin_mm`` at each end."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    line = np.asarray(line_points_mm, np.float64)
    if points.ndim != 2 or points.shape[1:] != (3,) or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (n, 3) arrays of one shape, got {points.shape} and {normals.shape}")
    if line.ndim != 2 or line.shape[1:] != (3,) or len(line) < 2:
        raise ValueError(f"line_points_mm must be (k >= 2, 3), got {line.shape}")
    if step_mm <= 0 or section_half_width_mm <= 0:
        raise ValueError(f"step_mm and section_half_width_mm must be positive, got {step_mm}, {section_half_width_mm}")
    t = line[-1] - line[0]
    length = float(np.linalg.norm(t))
    t = t / length
    rel = points - line[0]
    s_all = rel @ t
    across = rel - np.outer(s_all, t)
    near = (np.linalg.norm(across, axis=1) < reach_mm) & (s_all > -1) & (s_all < length + 1)
    if near.sum() < settings.min_points:
        return WeldLineMeasurement(name, [], 0.0, 0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    t, n, a = _frame(line, normals[near])
    face = near & (normals @ n > min_normal_cos) & (np.abs(rel @ n) < reach_mm / 2)
    P = rel[face]
    s, u, h = P @ t, P @ a, P @ n
    origin = line[0]
    if len(s) < settings.min_points:
        return WeldLineMeasurement(name, [], 0.0, 0.0, tuple(float(x) for x in n), tuple(float(x) for x in a))

    def cut(s, u, h, origin, t, a, n):
        lo, hi = float(s.min()) + end_margin_mm, float(s.max()) - end_margin_mm
        order = np.argsort(s)
        s, u, h = s[order], u[order], h[order]
        out = []
        if hi < lo:
            return out
        for pos in np.arange(np.ceil(lo / step_mm) * step_mm, hi + 1e-9, step_mm):
            i0, i1 = np.searchsorted(s, [pos - section_half_width_mm, pos + section_half_width_mm])

            def to_frame(uu, hh, pos=pos):
                return origin + pos * t + uu * a + hh * n

            try:
                out.append(measure_section(u[i0:i1], h[i0:i1], s[i0:i1] - pos, settings=settings, treated=treated,
                                           line=name, position_mm=float(pos), to_frame=to_frame))
            except (ValueError, np.linalg.LinAlgError) as exc:  # one section's fit, not the weld's
                none = Measured.none()
                out.append(SectionMeasurement(name, float(pos), tuple(float(x) for x in to_frame(0.0, 0.0)), none,
                                              none, none, none, (None, None), int(i1 - i0), f"fit failed: {exc}"))
        return out

    first = cut(s, u, h, origin, t, a, n)
    # the line refined on the data: a robust line through the sections' centres, in the face
    cs = np.array([[sec.position_mm, (np.asarray(sec.centre_mm) - origin) @ a] for sec in first
                   if sec.width.value == sec.width.value])
    offset = turn = 0.0
    sections = first
    if len(cs) >= 3:
        fit = fit_plate_line(cs[:, 0], cs[:, 1], min_points=3)
        if fit is not None:
            turn = math.atan(fit.slope)
            origin = origin + fit.intercept * a
            t2 = math.cos(turn) * t + math.sin(turn) * a
            a2 = np.cross(n, t2)
            a2 = a2 if a2 @ a > 0 else -a2
            t, a = t2, a2
            P = points[face] - origin
            s, u, h = P @ t, P @ a, P @ n
            sections = cut(s, u, h, origin, t, a, n)
            offset = fit.intercept + fit.slope * length / 2
    extent = (float(s.min()), float(s.max())) if len(s) else (0.0, 0.0)
    return WeldLineMeasurement(name, sections, float(offset), math.degrees(turn), tuple(float(x) for x in n),
                               tuple(float(x) for x in a), extent)


def along_weld_statistics(values: np.ndarray, positions: list) -> dict:
    """min, 5th / 50th / 95th percentile and max of one figure along the weld, and where its lowest
    and highest are (``positions``: one label per value). NaN values are not counted."""
    values = np.asarray(values, np.float64)
    ok = np.isfinite(values)
    if not ok.any():
        return {"n": 0}
    v = values[ok]
    where = [p for p, k in zip(positions, ok) if k]
    return {"n": int(ok.sum()), "min": round(float(v.min()), 4), "p5": round(float(np.percentile(v, 5)), 4),
            "median": round(float(np.median(v)), 4), "p95": round(float(np.percentile(v, 95)), 4),
            "max": round(float(v.max()), 4), "min_at": where[int(np.argmin(v))], "max_at": where[int(np.argmax(v))]}
