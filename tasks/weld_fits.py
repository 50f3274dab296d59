"""The fits a weld section is made of (``tasks.weld_geometry`` cuts the sections): a plate's line,
an as-welded toe (flank, toe fillet, undercut) and an HFMI groove (the pin's circular imprint),
each figure with its 1-sigma from the fit's residuals and covariance.

Profiles are read outward from the weld's centre: ``v`` (mm, away from the weld), ``h`` (mm, height
over this side's plate line).

- as welded: the flank (a line bending with a curvature), a toe fillet of radius r tangent to the
  plate and to the flank's tangent at the toe, and an undercut (a Gaussian dip beside the fillet)
  where the plate dips below its line, fitted together by non-linear least squares: toe position,
  flank angle (the tangent at the toe to the plate), toe radius, undercut depth;
- treated: a circle fitted to the groove's lower part: depth below the plate, width at the plate,
  radius; the toe's position is where the groove meets the weld (walked inward along the circle),
  the flank a line over ``toe_window_mm[0]`` inward of it (the flank angle the weld has now, just
  above the groove: the original flank at the toe is cut away by the pin); the toe is within the
  groove when the groove's wall runs up into the weld's flank with no stretch of plate between them
  longer than ``groove_plate_gap_mm`` (points on the groove's circle are groove, not plate).
  A groove's radius and width are only reported where its circle is held by points on both sides
  of its bottom; otherwise they are not measured (NaN, the reason in the toe's note), never an
  extrapolated value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from tasks.arrays import row_medians

__all__ = ["TOE_RADIUS_BOUNDS_MM", "Measured", "SectionSettings", "PlateFit", "GrooveFit", "ToeFit", "fit_plate_line",
           "fit_robust_line", "fit_toe", "fit_groove", "propagate", "toe_radius_range", "toe_at_radius", "running_median"]

_NAN = float("nan")
_R_MIN_MM, _R_MAX_MM = 0.02, 10.0  # the toe fillet's radius is fitted between these
TOE_RADIUS_BOUNDS_MM = (_R_MIN_MM, _R_MAX_MM)


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
    min_height_mm: float  # a butt cap lower than this (tasks.weld_geometry) is no evidence of a weld


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
    position_u_mm: float  # as welded: where the flank meets the plate; treated: where the groove meets the weld
    position_sigma_mm: float  # 1-sigma of position_u_mm
    flank_angle_deg: Measured
    notch_radius: Measured  # the notch radius at the toe: the toe fillet's (as welded), the groove's (treated)
    undercut_depth: Measured
    groove: GrooveFit | None
    rms_mm: float
    n_points: int
    note: str = ""


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


def propagate(f, p: np.ndarray, cov: np.ndarray) -> float:
    """1-sigma of f(p) from the parameters' covariance (first order, central differences)."""
    g = np.zeros(len(p))
    for k in range(len(p)):
        step = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros(len(p))
        dp[k] = step
        g[k] = (f(p + dp) - f(p - dp)) / (2 * step)
    var = float(g @ cov @ g)
    return math.sqrt(var) if var >= 0 and math.isfinite(var) else _NAN


def _trimmed_line(u: np.ndarray, h: np.ndarray, keep: np.ndarray, min_points: int) -> PlateFit | None:
    """Least squares on ``keep``, trimmed by 3 robust sigmas (points only leave), three rounds."""
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


def fit_robust_line(u: np.ndarray, h: np.ndarray, *, min_points: int) -> PlateFit | None:
    """A line through points with outliers on either side (the weld's centres along the line, a
    whole section's tilt): the least-median line through point pairs (a fixed seed), then trimmed
    least squares on the points within 3 robust sigmas of it. None: too few points."""
    found = _profile(u, h, min_points)
    if found is None:
        return None
    u, h, keep = found
    pairs = _pair_lines(u[keep], h[keep])
    if pairs is not None:
        slopes, offsets, _, med = pairs
        best = int(np.argmin(med))
        r = h - (slopes[best] * u + offsets[best])
        keep = keep & (np.abs(r) <= max(3 * 1.4826 * med[best], 1e-3))
    return _trimmed_line(u, h, keep, min_points)


def _profile(u, h, min_points: int):
    """(u, h, finite) as float64 (n,) arrays, checked; None when fewer than ``min_points`` (and 3)
    are finite."""
    u, h = np.asarray(u, np.float64), np.asarray(h, np.float64)
    if u.shape != h.shape or u.ndim != 1:
        raise ValueError(f"u and h must be (n,) arrays of one length, got {u.shape} and {h.shape}")
    keep = np.isfinite(u) & np.isfinite(h)
    return None if keep.sum() < max(min_points, 3) else (u, h, keep)


def _pair_lines(uk: np.ndarray, hk: np.ndarray):
    """Lines through 300 point pairs (a fixed seed): their slopes and offsets, every point's
    residual to each (lines, points), and each line's median absolute residual; None when no pair
    spans any u."""
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, len(uk), size=(2, 300))
    ok = np.abs(uk[i] - uk[j]) > 1e-6
    if not ok.any():
        return None
    slopes = (hk[j[ok]] - hk[i[ok]]) / (uk[j[ok]] - uk[i[ok]])
    offsets = hk[i[ok]] - slopes * uk[i[ok]]
    resid = np.multiply.outer(slopes, uk)  # h - (slope * u + offset), in place: (lines, points) is large
    resid += offsets[:, None]
    np.subtract(hk[None, :], resid, out=resid)
    return slopes, offsets, resid, row_medians(np.abs(resid), overwrite=True)


def fit_plate_line(u: np.ndarray, h: np.ndarray, *, min_points: int) -> PlateFit | None:
    """A line h = slope * u + intercept through the plate's points, not a sticker's or spatter's
    (0.1 mm of paper on the plate, possibly over most of the window). ``u``, ``h``: (n,) float64,
    mm. None: too few points.

    Lines through point pairs (a fixed seed) give the least-median line and the noise (from
    neighbours along u). A sticker or spatter lies on the plate, never under it; two starts:
    the lowest band parallel to the least-median line holding a fifth of the points (a sticker
    covering most of the window is the median's line, the plate a band under it), and the pair's
    line with the most points on it less five times those under it (where a sticker in the middle of
    the window tilts the median's line). Each is refined by trimmed least squares on the points
    around it; the one with the smaller RMS (a line across plate and sticker has the step in its
    residuals) is the plate."""
    found = _profile(u, h, min_points)
    if found is None:
        return None
    u, h, keep = found
    pairs = _pair_lines(u[keep], h[keep])
    if pairs is None:
        return _trimmed_line(u, h, keep, min_points)
    slopes, offsets, resid, med = pairs
    best = int(np.argmin(med))
    uk, hk = u[keep], h[keep]
    o = np.argsort(uk)
    step = np.diff(hk[o] - slopes[best] * uk[o])
    noise = 1.4826 * float(np.median(np.abs(step))) / math.sqrt(2) if len(step) else np.inf
    # (a band at least 0.03 mm: layers of passes registered a few um apart are one plate; a
    # sticker's paper, 0.1 mm, is not)
    tol = max(3 * min(1.4826 * float(med[best]), noise), 0.03)
    r_best = h - (slopes[best] * u + offsets[best])
    rs = np.sort(r_best[keep])
    need = max(int(np.ceil(0.2 * len(rs))), min_points, 3)
    count = np.searchsorted(rs, rs + 2 * tol, side="right") - np.arange(len(rs))
    first = np.flatnonzero(count >= need)
    level = float(np.median(rs[first[0]:first[0] + count[first[0]]])) if len(first) else 0.0
    score = np.count_nonzero(np.abs(resid) <= tol, axis=1) - 5 * np.count_nonzero(resid < -tol, axis=1)
    pick = int(np.argmax(score))
    fits = []
    for r in (r_best - level, h - (slopes[pick] * u + offsets[pick])):
        band = keep & (np.abs(r) <= tol)
        if band.sum() >= max(min_points, 3):  # the band's own line, the points around it (both sides)
            coef = np.polyfit(u[band], h[band], 1)
            r = h - np.polyval(coef, u)
            spread = min(float(med[best]), float(np.median(np.abs(r[band]))))
            band = keep & (np.abs(r) <= max(3 * 1.4826 * spread, 1e-3))
        fit = _trimmed_line(u, h, band, min_points)
        if fit is not None:
            fits.append(fit)
    return min(fits, key=lambda f: (round(f.rms_mm, 6), -f.n_points)) if fits else None


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


def _toe_jacobian(p: np.ndarray, w: np.ndarray, undercut: bool) -> np.ndarray:
    """``_toe_model``'s derivatives (n, len(p)) at ``p``: on the flank, on the fillet where it lies
    over the flank, and of the undercut's dip (analytic; the 2-point differences scipy would take
    cost one model evaluation per parameter, ~40 % of a toe fit's time). Inside the fillet the
    circle's root is at least r cos(theta) (its reach, d (1 + cos theta) = r sin theta, stays inside
    the circle), so no derivative there is singular."""
    v0, theta, r, k = p[:4]
    x = w - v0
    t = math.tan(theta)
    half = math.tan(theta / 2)
    d = r * half
    dd_dtheta = r / (2 * math.cos(theta / 2) ** 2)
    J = np.zeros((len(w), len(p)))
    on_flank = x < 0
    flank = np.where(on_flank, -x * t - k * x * x, 0.0)
    J[:, 0] = np.where(on_flank, t + 2 * k * x, 0.0)
    J[:, 1] = np.where(on_flank, -x * (1 + t * t), 0.0)
    J[:, 3] = np.where(on_flank, -x * x, 0.0)
    y = x - d
    root = np.sqrt(np.maximum(r * r - y * y, 0.0))
    on_fillet = (x > -d * math.cos(theta)) & (x < d) & (r - root > flank) & (root > 0)
    if on_fillet.any():
        slope = -y[on_fillet] / root[on_fillet]  # the fillet's height against d (and against v0)
        J[on_fillet, 0] = slope
        J[on_fillet, 1] = slope * dd_dtheta
        J[on_fillet, 2] = 1 - r / root[on_fillet] + slope * half
        J[on_fillet, 3] = 0.0
    if undercut:
        depth, centre, width = p[4:7]
        u = (x - d - centre) / width
        dip = np.exp(-u * u)
        along = 2 * depth * u * dip / width  # the dip's term, -depth exp(-u^2), against x
        J[:, 0] -= along
        J[:, 1] -= along * dd_dtheta
        J[:, 2] -= along * half
        J[:, 4] = -dip
        J[:, 5] = -along
        J[:, 6] = -along * u
    return J


def _toe_window(v: np.ndarray, h: np.ndarray, settings: SectionSettings, toe_guess_v: float):
    """The points a toe is fitted on (w, z) and whether an undercut is fitted; None: too few."""
    flank_mm, plate_mm = settings.toe_window_mm
    sel = (v > toe_guess_v - flank_mm) & (v < toe_guess_v + plate_mm)
    w, z = v[sel], h[sel]
    if len(w) < settings.min_points:
        return None
    plate_side = w > toe_guess_v + 0.2
    return w, z, bool(plate_side.any() and z[plate_side].min() < -settings.undercut_min_depth_mm)


def _toe_start(w, z, undercut: bool, settings: SectionSettings, toe_guess_v: float, theta0: float, r0: float):
    """A toe fit's start and bounds (v0, theta, r, k[, undercut depth, centre, width])."""
    flank_mm, plate_mm = settings.toe_window_mm
    p0 = [toe_guess_v, theta0, r0, 0.0]
    lo = [toe_guess_v - flank_mm, math.radians(2), _R_MIN_MM, 0.0]
    hi = [toe_guess_v + plate_mm, math.radians(85), _R_MAX_MM, 5.0]
    if undercut:
        plate_side = w > toe_guess_v + 0.2
        p0 += [max(-float(z[plate_side].min()), 0.01), 0.3, 0.3]
        lo += [0.0, -0.5, 0.05]
        hi += [2.0, 2.0, 1.5]
    return np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9)), lo, hi


def fit_toe(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, side: str, toe_guess_v: float) -> ToeFit | None:
    """The as-welded toe in a profile: ``v`` (n,) outward from the weld's centre (mm), ``h`` (n,)
    height over this side's plate line (mm); ``toe_guess_v`` where the weld starts. Fits the
    flank, toe fillet and undercut model over ``settings.toe_window_mm`` around the guess."""
    found = _toe_window(v, h, settings, toe_guess_v)
    if found is None:
        return None
    w, z, undercut = found
    on_flank = (z > 0.2 * z.max()) & (w < toe_guess_v)
    theta0 = math.radians(30.0)
    if on_flank.sum() >= 2:
        slope = np.polyfit(w[on_flank], z[on_flank], 1)[0]
        theta0 = float(np.clip(math.atan(max(-slope, 0.05)), math.radians(3), math.radians(80)))
    best = None
    for r0 in (0.3, 1.0, 2.5):
        p0, lo, hi = _toe_start(w, z, undercut, settings, toe_guess_v, theta0, r0)
        res = least_squares(lambda p: _toe_model(p, w, undercut) - z, p0, bounds=(lo, hi), x_scale="jac",
                            jac=lambda p: _toe_jacobian(p, w, undercut))
        if best is None or res.cost < best.cost:
            best = res
    p = best.x
    cov, rms = _sigmas(best, len(p))
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    return ToeFit(side=side, position_u_mm=float(p[0]), position_sigma_mm=float(sd[0]),
                  flank_angle_deg=Measured(math.degrees(p[1]), math.degrees(sd[1])),
                  notch_radius=Measured(float(p[2]), float(sd[2])),
                  undercut_depth=Measured(float(p[4]), float(sd[4])) if undercut else Measured(0.0, 0.0),
                  groove=None, rms_mm=rms, n_points=len(w))


def _fixed_radius_fit(v: np.ndarray, h: np.ndarray, settings: SectionSettings, toe_guess_v: float, fit: ToeFit):
    """``fit_toe``'s model with the radius held: (the fitted points' w, z, whether an undercut is
    fitted, fit(r) -> the least_squares result with every other parameter refitted at radius r
    (its x the whole parameter vector)); None: too few points. Starts at ``fit``, the flank's
    curvature at the flank points' own parabola."""
    found = _toe_window(v, h, settings, toe_guess_v)
    if found is None:
        return None
    w, z, undercut = found
    flank, plate_v = (w < fit.position_u_mm), w > fit.position_u_mm + 0.2
    k0 = 0.0 if flank.sum() < 3 else max(0.0, -float(np.polyfit(w[flank], z[flank], 2)[0]))
    start, lo, hi = _toe_start(w, z, undercut, settings, fit.position_u_mm, math.radians(fit.flank_angle_deg.value),
                               fit.notch_radius.value)
    start[3] = min(k0, 4.9)
    if undercut and plate_v.any():
        start[4] = min(max(fit.undercut_depth.value, 0.0), 1.99)
    free = [i for i in range(len(start)) if i != 2]
    lo_free, hi_free = np.take(lo, free), np.take(hi, free)

    def at(r: float):
        def held(q):
            p = start.copy()
            p[free] = q
            p[2] = r
            return p

        res = least_squares(lambda q: _toe_model(held(q), w, undercut) - z,
                            np.clip(start[free], lo_free + 1e-9, hi_free - 1e-9), bounds=(lo_free, hi_free),
                            x_scale="jac", jac=lambda q: _toe_jacobian(held(q), w, undercut)[:, free])
        x = start.copy()
        x[free] = res.x
        x[2] = r
        res.x = x
        return res

    return w, z, undercut, start, at


def toe_radius_range(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, toe_guess_v: float, fit: ToeFit,
                     threshold_mm2: float) -> tuple[float, float]:
    """The toe radii the points allow (mm): those whose best fit, the other parameters refitted,
    has a sum of squared residuals at most ``threshold_mm2`` over the best fit's (a profile
    likelihood; ``threshold_mm2`` = sigmas^2 x the residuals' variance). ``v``, ``h``,
    ``settings``, ``toe_guess_v`` as given to ``fit_toe``, ``fit`` its result. A lowest radius of
    0.02 mm (the fit's bound): the points cannot tell the toe from a sharp corner; the highest is
    then the radius they cannot exclude."""
    held = _fixed_radius_fit(v, h, settings, toe_guess_v, fit)
    if held is None:
        return _NAN, _NAN
    w, z, undercut, start, at = held

    def rss(r: float) -> float:
        res = at(r)
        return float(res.fun @ res.fun)

    r_hat = float(np.clip(fit.notch_radius.value, _R_MIN_MM, _R_MAX_MM))
    best = min(rss(r_hat), float(np.sum((_toe_model(start, w, undercut) - z) ** 2)))

    def allowed(r: float) -> bool:
        return rss(r) - best <= threshold_mm2

    def edge(inside: float, outside: float) -> float:
        """The allowed radius nearest ``outside`` (bisection in log r, 2 % steps)."""
        if allowed(outside):
            return outside
        while abs(math.log(outside / inside)) > 0.02:
            mid = math.sqrt(inside * outside)
            inside, outside = (mid, outside) if allowed(mid) else (inside, mid)
        return inside

    return edge(r_hat, _R_MIN_MM), edge(r_hat, _R_MAX_MM)


def toe_at_radius(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, toe_guess_v: float, fit: ToeFit,
                  radius_mm: float) -> ToeFit:
    """``fit`` (``fit_toe``'s result on ``v``, ``h``, ``settings``, ``toe_guess_v``) refitted with
    its radius held at ``radius_mm``: its position, flank angle and undercut are the held fit's, their
    1-sigma ``fit``'s (which hold the radius's own spread). For a toe whose radius the points do not
    resolve: a radius they cannot tell apart otherwise must not steer its angle (at a 10 deg flank
    the fillet's radius is free from a sharp corner to several mm, and a wider fillet is fitted with
    a steeper flank: the free fit's angle runs 1-2 deg high under the real scans' noise)."""
    held = _fixed_radius_fit(v, h, settings, toe_guess_v, fit)
    if held is None:
        return fit
    *_, undercut, _, at = held
    p = at(float(np.clip(radius_mm, _R_MIN_MM, _R_MAX_MM))).x
    return ToeFit(side=fit.side, position_u_mm=float(p[0]), position_sigma_mm=fit.position_sigma_mm,
                  flank_angle_deg=Measured(math.degrees(p[1]), fit.flank_angle_deg.sigma),
                  notch_radius=fit.notch_radius,
                  undercut_depth=Measured(float(p[4]), fit.undercut_depth.sigma) if undercut else fit.undercut_depth,
                  groove=None, rms_mm=fit.rms_mm, n_points=fit.n_points, note=fit.note)


def _circle_residuals(p: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    return np.hypot(v - p[0], z - p[1]) - p[2]


def running_median(z: np.ndarray, k: int = 5) -> np.ndarray:
    """Each value replaced by the median of the k (odd) around it (fewer at the ends)."""
    if len(z) < k:
        return z.copy()
    half = k // 2
    padded = np.concatenate([np.full(half, np.nan), z, np.full(half, np.nan)])
    return np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, k), axis=1)


def _fit_circle(gv: np.ndarray, gz: np.ndarray, depth0: float, v_bottom: float):
    """The groove's circle through (gv, gz), then again without the points off it by more than
    4 robust sigmas (spatter, a stray return): (least_squares result, the points kept)."""
    span = max(float(gv[-1] - gv[0]), 1e-3)
    r0 = (span * span / 4 + depth0 * depth0) / (2 * depth0)
    lo, hi = np.array([gv[0] - 5, -50.0, 0.05]), np.array([gv[-1] + 5, 50.0, 60.0])
    x0 = np.clip([v_bottom, r0 - depth0, r0], lo + 1e-9, hi - 1e-9)
    keep = np.ones(len(gv), bool)
    res = least_squares(_circle_residuals, x0, args=(gv, gz), bounds=(lo, hi), x_scale="jac")
    r = _circle_residuals(res.x, gv, gz)
    new = np.abs(r) <= max(4 * 1.4826 * float(np.median(np.abs(r))), 0.01)
    if not new.all() and new.sum() >= 4:
        keep = new
        res = least_squares(_circle_residuals, np.clip(res.x, lo + 1e-9, hi - 1e-9), args=(gv[keep], gz[keep]),
                            bounds=(lo, hi), x_scale="jac")
    return res, keep


def fit_groove(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, side: str, toe_guess_v: float) -> ToeFit | None:
    """A treated toe: the groove's circle on its lower part (points deeper than a quarter of its
    depth, around its deepest point), the flank above it by a parabola extended to the plate.
    ``v``, ``h`` as in ``fit_toe``. None: no groove deeper than ``groove_min_depth_mm``.

    Robust to what a real (or coarse) profile holds: the deepest point is found on a running
    median of five points (one stray return below the groove is not its bottom); the circle is
    refitted without points off it by more than 4 robust sigmas; a circle with fewer than
    ``min_points // 2`` (at least 3) points on either side of its bottom does not determine its
    radius and width (a wall seen, not a groove): those are not measured (NaN, said in ``note``),
    the depth is read on the median profile, and the toe is still treated."""
    flank_mm, plate_mm = settings.toe_window_mm
    region = (v > toe_guess_v - flank_mm) & (v < toe_guess_v + plate_mm + 8.0)
    if region.sum() < settings.min_points:
        return None
    order = np.argsort(v[region])
    vv, hh = v[region][order], h[region][order]
    smooth = running_median(hh)
    k = int(np.argmin(smooth))
    depth0 = -float(smooth[k])
    if depth0 < settings.groove_min_depth_mm:
        return None
    deep = smooth < -0.25 * depth0
    lo_k = k
    while lo_k > 0 and deep[lo_k - 1]:
        lo_k -= 1
    hi_k = k
    while hi_k < len(vv) - 1 and deep[hi_k + 1]:
        hi_k += 1
    gv, gz = vv[lo_k:hi_k + 1], hh[lo_k:hi_k + 1]
    if len(gv) < max(settings.min_points, 4):
        return None
    res, kept = _fit_circle(gv, gz, depth0, float(vv[k]))
    p = res.x
    cov, rms = _sigmas(res, 3)

    def depth(q):
        return q[2] - q[1]

    def width(q):
        return 2 * math.sqrt(max(q[2] ** 2 - q[1] ** 2, 0.0))

    need = max(3, settings.min_points // 2)
    n_in, n_out = int(np.count_nonzero(gv[kept] < p[0])), int(np.count_nonzero(gv[kept] > p[0]))
    note = ""
    if n_in >= need and n_out >= need:
        D, W = depth(p), width(p)
        g_depth = Measured(D, propagate(depth, p, cov))
        g_width = Measured(W, propagate(width, p, cov))
        g_radius = Measured(float(p[2]), math.sqrt(max(float(cov[2, 2]), 0.0)))
    else:
        # the circle is not held on both sides of its bottom: its radius and width are guesses
        near = np.abs(gv - vv[k]) <= max(2 * float(np.median(np.diff(gv))) if len(gv) > 2 else 0.5, 0.2)
        spread = float(np.std(gz[near])) if near.sum() > 1 else rms
        D, W = depth0, 2 * float(max(gv[-1] - gv[0], 0.0))
        g_depth = Measured(D, spread / math.sqrt(max(int(near.sum()), 1)))
        g_width = g_radius = Measured.none()
        note = (f"groove radius and width not measured: {n_in} points inward and {n_out} outward of the "
                f"circle's bottom (at least {need} each needed)")
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
    # no stretch of plate (|h| < groove_min_depth_mm, off the groove's circle: a wide shallow
    # groove's wall is itself nearly level where it crosses the plate) longer than
    # groove_plate_gap_mm between them
    # groove_plate_gap_mm: consecutive points (along v) all at the plate's level and off the
    # circle, so that a steep, sparsely sampled wall whose clumps of points each straddle the
    # plate's level is not read as plate
    reach = W if math.isfinite(W) else 2 * float(gv[-1] - gv[0])
    between = (v < vv[k]) & (v > toe_guess_v - flank_mm - reach)
    up = v[(v < vv[k]) & (h > settings.toe_threshold_mm)]
    if len(up):
        between &= v > up.max()
    order_b = np.argsort(v[between])
    bv = v[between][order_b]
    flat = ((np.abs(h[between]) < settings.groove_min_depth_mm) & ~on[between])[order_b]
    longest, start = 0.0, None
    for i in range(len(bv)):
        if flat[i]:
            start = i if start is None else start
            longest = max(longest, float(bv[i] - bv[start]))
        else:
            start = None
    toe_within = bool(len(up) and np.count_nonzero((v < vv[k]) & (v > toe_guess_v - flank_mm - reach))
                      and longest <= settings.groove_plate_gap_mm)
    angle, toe_v = Measured.none(), v_meet
    groove_note, note = note, ""
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
    note = "; ".join(x for x in (groove_note, note) if x)
    groove = GrooveFit(depth=g_depth, width=g_width, radius=g_radius, centre_v_mm=float(p[0]),
                       toe_within=toe_within, rms_mm=rms, n_points=len(gv))
    # where the groove leaves its circle is known to the points' spacing there (uniform: /sqrt 12)
    spacing = float(np.median(np.diff(np.sort(v[np.abs(v - v_meet) < 1.0])))) if np.count_nonzero(np.abs(v - v_meet) < 1.0) > 2 else _NAN
    return ToeFit(side=side, position_u_mm=toe_v, position_sigma_mm=spacing / math.sqrt(12), flank_angle_deg=angle, notch_radius=g_radius,
                  undercut_depth=Measured(0.0, 0.0), groove=groove, rms_mm=rms, n_points=len(gv), note=note)
