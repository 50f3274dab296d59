"""The weld cap: a height field over a plate face, drawn from configurable ranges.

Profile across the weld at a position y (u = x - centre): a cap of height h and width w whose
flanks meet the plate at the flank angle, a circular toe fillet of the toe radius, optional
undercut beside each toe, crescent-shaped bead ripples, and, by treatment, an HFMI groove (the
pin's circular imprint) or a burr-ground groove (reflective) along each toe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from schemas.simulation import WeldConfig

__all__ = ["WeldCap", "draw_weld_cap"]

_MIN_SHAPE_EXPONENT = 1.2


@dataclass(frozen=True)
class _Smooth:
    """A smooth random function of y, drawn uniformly within a range at control points."""

    ys: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "_interpolate", PchipInterpolator(self.ys, self.values, extrapolate=True))

    def __call__(self, y: np.ndarray) -> np.ndarray:
        return self._interpolate(np.clip(y, self.ys[0], self.ys[-1]))


def _smooth(rng: np.random.Generator, ys: np.ndarray, low: float, high: float) -> _Smooth:
    return _Smooth(ys, rng.uniform(low, high, size=ys.size))


def _shape_exponent(half: np.ndarray, height: np.ndarray, flank_deg: np.ndarray) -> np.ndarray:
    """The cap's shape exponent on one side from its half width, height and drawn flank angle."""
    return np.maximum(half * np.tan(np.radians(flank_deg)) / height, _MIN_SHAPE_EXPONENT)


def _effective_flank_deg(half: np.ndarray, height: np.ndarray, shape_exponent: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan(height * shape_exponent / half))


@dataclass(frozen=True)
class WeldCap:
    """A drawn weld cap. All functions take y (mm, specimen frame) arrays."""

    centre_x_mm: float
    centre: _Smooth
    height: _Smooth
    width: _Smooth
    flank_deg: tuple[_Smooth, _Smooth]  # left (u < 0), right (u > 0)
    toe_radius: tuple[_Smooth, _Smooth]
    undercut: tuple[_Smooth, _Smooth]
    ripple_amplitude_mm: float
    ripple_wavelength_mm: float
    ripple_phase: float
    treatment: str
    groove_width: tuple[_Smooth, _Smooth] | None
    groove_depth: tuple[_Smooth, _Smooth] | None

    def max_half_extent_mm(self) -> float:
        """Largest |u| the cap or its toe treatment reaches."""
        ys = self.height.ys
        half = float(np.max(self.width(ys))) / 2 + 1.5
        if self.groove_width is not None:
            half += float(max(np.max(g(ys)) for g in self.groove_width))
        return half + float(np.max(np.abs(self.centre(ys) - self.centre_x_mm)))

    def shape_exponent(self, y: np.ndarray, side: int) -> np.ndarray:
        return _shape_exponent(self.width(y) / 2, self.height(y), self.flank_deg[side](y))

    def effective_flank_deg(self, y: np.ndarray, side: int) -> np.ndarray:
        """Flank angle the cap really has (the drawn one unless the shape had to be limited)."""
        half, height = self.width(y) / 2, self.height(y)
        return _effective_flank_deg(half, height, _shape_exponent(half, height, self.flank_deg[side](y)))

    def height_mm(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cap height above the plate (mm, may be negative in grooves) and a reflective mask."""
        x = np.asarray(x, dtype=float)
        y = np.broadcast_to(np.asarray(y, dtype=float), x.shape)
        u = x - self.centre(y)
        h = self.height(y)
        half = self.width(y) / 2
        au = np.abs(u)
        s = au / half
        right = u >= 0
        # each smooth function of y evaluated once (the same numbers as shape_exponent and
        # effective_flank_deg give, which evaluate them each time)
        n_side = [_shape_exponent(half, h, self.flank_deg[side](y)) for side in (0, 1)]
        n = np.where(right, n_side[1], n_side[0])
        theta = np.radians(np.where(right, _effective_flank_deg(half, h, n_side[1]),
                                    _effective_flank_deg(half, h, n_side[0])))
        inside = s < 1
        z = np.where(inside, h * (1 - np.minimum(s, 1) ** n), 0.0)
        # Crescent ripples, fading toward the toes.
        phase = 2 * np.pi * (y + 0.15 * u**2) / self.ripple_wavelength_mm + self.ripple_phase
        z = z + np.where(inside, self.ripple_amplitude_mm * (1 - s**2) * np.cos(phase), 0.0)
        # Concave toe fillet of radius r between the plate and the flank's tangent line.
        r = np.where(right, self.toe_radius[1](y), self.toe_radius[0](y))
        d = r * np.tan(theta / 2)
        centre_u = half + d
        in_fillet = (au > half - d * np.cos(theta)) & (au < half + d)
        fillet = r - np.sqrt(np.maximum(r * r - (au - centre_u) ** 2, 0.0))
        z = np.where(in_fillet, np.maximum(z, fillet), z)
        # Undercut: a narrow groove just outside the fillet.
        depth = np.where(right, self.undercut[1](y), self.undercut[0](y))
        z = z - depth * np.exp(-(((au - (half + d + 0.3)) / 0.3) ** 2))
        reflective = np.zeros(x.shape, dtype=bool)
        if self.groove_width is not None and self.groove_depth is not None:
            width = np.where(right, self.groove_width[1](y), self.groove_width[0](y))
            depth = np.where(right, self.groove_depth[1](y), self.groove_depth[0](y))
            radius = (width**2 / 4 + depth**2) / (2 * depth)
            centre_g = half + 0.25 * width
            du = au - centre_g
            in_groove = np.abs(du) < radius
            groove = -depth + radius - np.sqrt(np.maximum(radius**2 - du**2, 0.0))
            cut = in_groove & (groove < z)
            z = np.where(cut, groove, z)
            if self.treatment == "burr-ground":
                reflective = cut
        return z, reflective


def draw_weld_cap(config: WeldConfig, rng: np.random.Generator, *, centre_x_mm: float,
                  y_extent_mm: float) -> WeldCap:
    """Draw one cap over y in [-y_extent_mm, y_extent_mm] from the ranges of ``config``."""
    n_ctrl = max(4, int(np.ceil(2 * y_extent_mm / config.variation_length_mm)) + 1)
    ys = np.linspace(-y_extent_mm, y_extent_mm, n_ctrl)

    def pair(rng_range: tuple[float, float]) -> tuple[_Smooth, _Smooth]:
        return (_smooth(rng, ys, *rng_range), _smooth(rng, ys, *rng_range))

    undercut_ranges = []
    for _ in range(2):
        if rng.random() < config.undercut_probability:
            undercut_ranges.append(config.undercut_depth_mm)
        else:
            undercut_ranges.append((0.0, 0.0))
    groove_width = groove_depth = None
    if config.treatment == "hfmi-treated":
        groove_width, groove_depth = pair(config.hfmi_groove_width_mm), pair(config.hfmi_groove_depth_mm)
    elif config.treatment == "burr-ground":
        groove_width, groove_depth = pair(config.burr_width_mm), pair(config.burr_depth_mm)
    wander = config.bead_wander_mm
    return WeldCap(
        centre_x_mm=centre_x_mm,
        centre=_smooth(rng, ys, centre_x_mm - wander, centre_x_mm + wander),
        height=_smooth(rng, ys, *config.cap_height_mm),
        width=_smooth(rng, ys, *config.cap_width_mm),
        flank_deg=pair(config.flank_angle_deg),
        toe_radius=pair(config.toe_radius_mm),
        undercut=(_smooth(rng, ys, *undercut_ranges[0]), _smooth(rng, ys, *undercut_ranges[1])),
        ripple_amplitude_mm=float(rng.uniform(*config.ripple_amplitude_mm)),
        ripple_wavelength_mm=float(rng.uniform(*config.ripple_wavelength_mm)),
        ripple_phase=float(rng.uniform(0, 2 * np.pi)),
        treatment=config.treatment,
        groove_width=groove_width,
        groove_depth=groove_depth,
    )
