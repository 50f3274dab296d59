"""A T-joint: a stem plate welded upright across a base plate by two convex fillet welds; or a
cruciform joint (``TJointConfig.stems`` "both"): a second such stem on the base plate's other face,
in the same plane, with its own two fillets.

Specimen frame (the manifest's ``TJointSpecimen``): origin at the base plate's centre
(mid-thickness), x across the stem, y along the stem and its welds, z toward the stem. The part
is one cross-section outline in x-z swept along y (the welds' legs, convexity, toe radii and
ripples vary along y as the butt cap's do: ``simulator.weld``), closed at y = +-width/2 by two
planar end faces; the base plate's four 12 mm walls are the only surfaces that the two setups
(stem up; turned over, the stem hanging between the support blocks) both see.

Fillet weld profile (the weld on the x > 0 side; the other mirrored): legs ``a`` along the base
and ``b`` up the stem from the corner (x0, z0) = (stem_thickness/2, base_thickness/2); the face
runs from the base toe B = (x0 + a, z0) to the stem toe S = (x0, z0 + b), risen above the chord
B-S by ``h (1 - |2s - 1|^p)`` plus ripples; each toe is rounded by a circle of the toe radius
tangent to the plate and to the weld face. The true toe lines (``truth/toes.json``) are the
middles of those roundings.

A cruciform's lower stem and its fillets are the upper ones' picture turned half a turn about the
y axis ((x, z) -> (-x, -z)): each of its fillets is drawn in the frame above (legs along +x and
+z), then placed by its side (x < 0 or x > 0) and face (-1: the base's lower face). Its two
setups are alike: one stem up, the other hanging between the support blocks; the base plate's
walls are still the only surfaces both see. The weld lines of a T-joint are ``fillet-neg`` and
``fillet-pos`` (x < 0, x > 0); a cruciform's ``fillet-top-neg``, ``fillet-top-pos``,
``fillet-bottom-neg`` and ``fillet-bottom-pos`` (``weld_names``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.manifest import CruciformSpecimen, TJointSpecimen, WeldLine
from schemas.simulation import TrueMeshConfig, SimulationConfig, TJointConfig, WeldConfig
from schemas.truth import FilletSectionTruth, FilletWeldTruth, TrueToeLine
from simulator.robot import PlannedPass, _sensor_frame
from simulator.scene import StickerSet
from simulator.specimen import Face, SurfaceMesh
from simulator.stickers import Candidates, fixture_stickers_beside
from simulator.weld import _smooth

__all__ = ["TJoint", "build_tjoint", "weld_names", "tjoint_specimen", "tjoint_weld_lines", "plan_tjoint_passes",
           "constant_fillet",
           "fillet_profile", "fillet_truth",
           "tjoint_sticker_candidates", "wall_sticker_picks", "place_tjoint_fixture_stickers"]

_N_ARC = 8  # interior nodes of each toe's rounding


@dataclass(frozen=True)
class _Fillet:
    """One fillet weld's drawn parameters, functions of y (mm)."""

    leg_base: object
    leg_stem: object
    convexity: object
    toe_radius_base: object
    toe_radius_stem: object
    ripple_amplitude_mm: float
    ripple_wavelength_mm: float
    ripple_phase: float


@dataclass(frozen=True)
class TJoint:
    config: TJointConfig
    mesh: SurfaceMesh
    toes: list[TrueToeLine]
    fillets: dict  # +1 / -1 (the weld on the x > 0 / x < 0 side) -> its drawn _Fillet
    fillets_below: dict | None = None  # a cruciform's: the lower stem's, +1 / -1 as ``fillets``

    def welds(self) -> list[tuple[int, int, str, _Fillet]]:
        """Every fillet in the manifest's order: (face: +1 on the base's upper face, -1 its lower;
        side: +1 x > 0, -1 x < 0; its weld line's name; its drawn figures)."""
        drawn = {1: self.fillets, -1: self.fillets_below}
        return [(face, side, name, drawn[face][side]) for (face, side), name in weld_names(self.config).items()]

    def section(self, y: float, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """The part's closed outline at station y as drawn, its points every ``spacing_mm`` (x, z)
        (k, 2) and their outward normals (k, 2): the base's bottom (a cruciform's: with its fillets
        and the lower stem, turned half a turn), its end walls, its top with both fillets (their
        toes rounded) and the stem to its end."""
        tj = self.config
        L, z0 = tj.base_length_mm, tj.base_thickness_mm / 2
        wall = np.arange(-z0, z0, spacing_mm)
        if self.fillets_below is None:
            bottom = np.arange(-L / 2, L / 2, spacing_mm)
            below, left_wall = np.c_[bottom, np.full(len(bottom), -z0)], wall[::-1]
        else:  # from (-L/2, -z0) to where the right wall starts; the left wall ends where it starts
            below = -self._stem_section(self.fillets_below[-1], self.fillets_below[1], y, spacing_mm)[:-1]
            left_wall = wall[::-1][:-1]
        loop = np.concatenate([below, np.c_[np.full(len(wall), L / 2), wall],
                               self._stem_section(self.fillets[1], self.fillets[-1], y, spacing_mm),
                               np.c_[np.full(len(left_wall), -L / 2), left_wall]])
        tangent = np.roll(loop, -1, axis=0) - np.roll(loop, 1, axis=0)
        normals = np.c_[tangent[:, 1], -tangent[:, 0]]  # counter-clockwise: outward is the tangent turned right
        return loop, normals / np.linalg.norm(normals, axis=1)[:, None]

    def _stem_section(self, right_fillet: _Fillet, left_fillet: _Fillet, y: float, spacing_mm: float) -> np.ndarray:
        """The upper face's outline at station y from (L/2, z0) to (-L/2, z0): the base's face,
        the x > 0 fillet, the stem up, across its end and down, the x < 0 fillet, the base's face."""
        tj = self.config
        z0, x0 = tj.base_thickness_mm / 2, tj.stem_thickness_mm / 2
        right = fillet_profile(tj, right_fillet, y, spacing_mm) + [x0, z0]
        left = (fillet_profile(tj, left_fillet, y, spacing_mm) + [x0, z0])[::-1] * [-1.0, 1.0]
        across = np.arange(x0, -x0, -spacing_mm)
        return np.concatenate([right, np.c_[across, np.full(len(across), z0 + tj.stem_height_mm)], left])

    def fillet_truth(self, step_mm: float = 1.0) -> FilletWeldTruth:
        """Every fillet as drawn every ``step_mm`` across the base plate's width (each in its own
        frame, ``fillet_profile``'s: mirrored and turned ones give the same figures)."""
        half = self.config.base_width_mm / 2
        return FilletWeldTruth(step_mm=step_mm, sections=[
            fillet_truth(self.config, fillet, float(y), name)
            for _, _, name, fillet in self.welds() for y in np.arange(-half, half + 1e-9, step_mm)])

    def weld_zone_half_mm(self) -> float:
        return float(self.config.leg_mm[1]) + 1.5


def weld_names(tj: TJointConfig) -> dict[tuple[int, int], str]:
    """Each fillet's weld line name by (face, side) (``TJoint.welds``), in the manifest's order."""
    if tj.stems == "one":
        return {(1, -1): "fillet-neg", (1, 1): "fillet-pos"}
    return {(face, side): f"fillet-{'top' if face > 0 else 'bottom'}-{'pos' if side > 0 else 'neg'}"
            for face in (1, -1) for side in (-1, 1)}


def _draw_fillet(tj: TJointConfig, weld: WeldConfig, rng: np.random.Generator) -> _Fillet:
    half = tj.base_width_mm / 2
    ys = np.linspace(-half, half, max(4, int(np.ceil(2 * half / weld.variation_length_mm)) + 1))
    return _Fillet(leg_base=_smooth(rng, ys, *tj.leg_mm), leg_stem=_smooth(rng, ys, *tj.leg_mm),
                   convexity=_smooth(rng, ys, *tj.convexity_mm),
                   toe_radius_base=_smooth(rng, ys, *weld.toe_radius_mm),
                   toe_radius_stem=_smooth(rng, ys, *weld.toe_radius_mm),
                   ripple_amplitude_mm=float(rng.uniform(*weld.ripple_amplitude_mm)),
                   ripple_wavelength_mm=float(rng.uniform(*weld.ripple_wavelength_mm)),
                   ripple_phase=float(rng.uniform(0, 2 * np.pi)))


def _graded(length: float, fine: float, coarse: float) -> np.ndarray:
    """Fractions in [0, 1) of nodes along a segment of ``length``, ``fine`` apart at its start,
    growing away from it to ``coarse``."""
    pos = [0.0]
    while pos[-1] < length:
        pos.append(pos[-1] + min(coarse, fine + 0.2 * pos[-1]))
    pos = np.array(pos[:-1])
    return pos / length


def _both_ends(fine: float, coarse: float, length: float) -> np.ndarray:
    """Fractions in [0, 1] (both ends included), fine at both ends."""
    half = _graded(length / 2, fine, coarse) * 0.5
    return np.concatenate([half, [0.5], 1 - half[::-1]])


def _arc(corner: np.ndarray, e1: np.ndarray, e2: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Round the corner (2,) where a path heading ``e1`` turns to ``e2`` (unit) by a circle of
    radius ``r`` tangent to both: (its start on the e1 line, interior points (_N_ARC, 2), its middle)."""
    turn = float(np.arccos(np.clip(e1 @ e2, -1, 1)))
    d = r * np.tan(turn / 2)
    start = corner - d * e1
    cross = e1[0] * e2[1] - e1[1] * e2[0]
    normal = np.sign(cross) * np.array([-e1[1], e1[0]])
    centre = start + r * normal
    a0 = np.arctan2(*(start - centre)[::-1])
    end = corner + d * e2
    a1 = np.arctan2(*(end - centre)[::-1])
    sweep = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
    t = a0 + sweep * (np.arange(1, _N_ARC + 1) / (_N_ARC + 1))
    pts = centre + r * np.stack([np.cos(t), np.sin(t)], 1)
    mid = centre + r * np.array([np.cos(a0 + sweep / 2), np.sin(a0 + sweep / 2)])
    return start, pts, mid


@dataclass(frozen=True)
class _Shape:
    """One fillet at one station, x > 0 side, in (x, z): the legs, the corners B (on the base) and
    S (on the stem), the toe radii, the face's points at chord fractions s and its rise above the
    chord, its tangents at B and S (not unit: the rounding needs their length) and the chord's
    length."""

    leg_base: float
    leg_stem: float
    B: np.ndarray
    S: np.ndarray
    r_base: float
    r_stem: float
    face: object
    rise: object
    tangent_b: np.ndarray
    tangent_s: np.ndarray
    length: float


def _shape(tj: TJointConfig, f: _Fillet, y: float) -> _Shape:
    x0, z0 = tj.stem_thickness_mm / 2, tj.base_thickness_mm / 2
    ya = np.array([y])
    a, b = float(f.leg_base(ya)[0]), float(f.leg_stem(ya)[0])
    h, p = float(f.convexity(ya)[0]), tj.shape_exponent
    B, S = np.array([x0 + a, z0]), np.array([x0, z0 + b])
    chord = S - B
    length = float(np.linalg.norm(chord))
    n = np.array([b, a]) / length

    def rise(s: np.ndarray) -> np.ndarray:
        w = np.abs(2 * s - 1)
        u = (s - 0.5) * length
        phase = 2 * np.pi * (y + 0.15 * u**2) / f.ripple_wavelength_mm + f.ripple_phase
        return h * (1 - w**p) + f.ripple_amplitude_mm * (1 - w**2) * np.cos(phase)

    def face(s: np.ndarray) -> np.ndarray:
        return B + s[:, None] * chord + rise(s)[:, None] * n

    return _Shape(a, b, B, S, float(f.toe_radius_base(ya)[0]), float(f.toe_radius_stem(ya)[0]), face, rise,
                  chord + 2 * h * p * n, chord - 2 * h * p * n, length)


def fillet_truth(tj: TJointConfig, f: _Fillet, y: float, weld: str) -> FilletSectionTruth:
    """The fillet as drawn at station y (``schemas.truth.FilletSectionTruth``)."""
    sh = _shape(tj, f, y)
    e_b = sh.tangent_b / np.linalg.norm(sh.tangent_b)
    e_s = sh.tangent_s / np.linalg.norm(sh.tangent_s)
    # the face leaves B toward the stem at e_b over the base (heading -x), S toward the base at -e_s along the stem (-z)
    angles = (float(np.degrees(np.arctan2(e_b[1], -e_b[0]))), float(np.degrees(np.arccos(np.clip(e_s[1], -1, 1)))))
    # where the face starts after each rounding (the roundings are tangent to the corners' tangent
    # lines, as _half_outline draws them) and its direction there, away from the toe
    s0, s1 = (_rounding_length(e, r) / float(np.linalg.norm(tangent)) for e, r, tangent in (
        (e_b @ np.array([-1.0, 0.0]), sh.r_base, sh.tangent_b), (e_s @ np.array([0.0, 1.0]), sh.r_stem, sh.tangent_s)))
    ds = 1e-6
    away_b = sh.face(np.array([s0 + ds]))[0] - sh.face(np.array([s0]))[0]
    away_s = sh.face(np.array([1 - s1 - ds]))[0] - sh.face(np.array([1 - s1]))[0]
    face = (float(np.degrees(np.arctan2(away_b[1], -away_b[0]))),
            float(np.degrees(np.arctan2(away_s[0], -away_s[1]))))
    convexity = float(sh.rise(np.linspace(0.0, 1.0, 20001)).max())
    throat = sh.leg_base * sh.leg_stem / sh.length + min(convexity, 0.0)
    return FilletSectionTruth(weld=weld, y_mm=float(y), leg_base_mm=sh.leg_base, leg_stem_mm=sh.leg_stem,
                              toe_angle_deg=angles, face_angle_deg=face, toe_radius_mm=(sh.r_base, sh.r_stem),
                              convexity_mm=convexity, throat_mm=throat)


def constant_fillet(*, leg_base: float, leg_stem: float, convexity: float, toe_radius_base: float,
                    toe_radius_stem: float, ripple_amplitude_mm: float = 0.0, ripple_wavelength_mm: float = 2.0,
                    ripple_phase: float = 0.0) -> _Fillet:
    """A fillet of the same figures all along (for known answers)."""
    def const(v):
        return lambda y: np.full(np.shape(y), float(v))
    return _Fillet(const(leg_base), const(leg_stem), const(convexity), const(toe_radius_base), const(toe_radius_stem),
                   ripple_amplitude_mm, ripple_wavelength_mm, ripple_phase)


def fillet_profile(tj: TJointConfig, f: _Fillet, y: float, spacing_mm: float) -> np.ndarray:
    """The x > 0 half of the part's outline at station y as a scanner's profile would sample it:
    (k, 2) points every ``spacing_mm`` along it (the base plate's face from its end, the weld, the
    stem's face up to its end), in (a, b) from the nominal root: a along the base away from the
    stem, b up the stem (mm)."""
    leg = float(np.mean(tj.leg_mm))
    x0, z0 = tj.stem_thickness_mm / 2, tj.base_thickness_mm / 2
    fine = min(spacing_mm / 4, 0.01)
    fr = {"weld": _both_ends(fine, fine, leg * np.sqrt(2)), "stem": _graded(tj.stem_height_mm - leg, fine, fine)}
    fr["base"] = np.concatenate([[0.0], np.sort(1 - _graded(tj.base_length_mm / 2 - x0 - leg, fine, fine)[1:])])
    nodes = _half_outline(tj, f, y, fr)[0]
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    t = np.arange(0.0, along[-1], spacing_mm)
    return np.stack([np.interp(t, along, nodes[:, 0]) - x0, np.interp(t, along, nodes[:, 1]) - z0], 1)


def _rounding_length(cos_turn: float, r: float) -> float:
    """How far from a corner a rounding of radius r starts and ends (``_arc``), the path turning
    by the angle whose cosine is ``cos_turn``."""
    return float(r * np.tan(np.arccos(np.clip(cos_turn, -1, 1)) / 2))


def _half_outline(tj: TJointConfig, f: _Fillet, y: float, fr: dict[str, np.ndarray]) -> tuple[np.ndarray, list[int],
                                                                                                 np.ndarray, np.ndarray]:
    """The x > 0 half of the outline at station y, from (L/2, z0) to the last stem node below
    the stem's end: nodes (k, 2) in (x, z), each node's following edge's face, and the two toe
    points (base, stem)."""
    x0, z0 = tj.stem_thickness_mm / 2, tj.base_thickness_mm / 2
    top = z0 + tj.stem_height_mm
    sh = _shape(tj, f, y)
    B, S, face, r_base, r_stem = sh.B, sh.S, sh.face, sh.r_base, sh.r_stem
    tangent_b, tangent_s = sh.tangent_b, sh.tangent_s
    e_b = tangent_b / np.linalg.norm(tangent_b)
    e_s = tangent_s / np.linalg.norm(tangent_s)
    start_b, arc_b, toe_b = _arc(B, np.array([-1.0, 0.0]), e_b, r_base)
    start_s, arc_s, toe_s = _arc(S, e_s, np.array([0.0, 1.0]), r_stem)
    d_b = float(np.linalg.norm(B - start_b))
    d_s = float(np.linalg.norm(start_s - S))
    s0 = d_b / float(np.linalg.norm(tangent_b))
    s1 = 1 - d_s / float(np.linalg.norm(tangent_s))
    weld = face(s0 + (s1 - s0) * fr["weld"])
    stem_start = S[1] + d_s
    base_x = tj.base_length_mm / 2 - (tj.base_length_mm / 2 - start_b[0]) * fr["base"]
    base = np.stack([base_x, np.full_like(base_x, z0)], 1)
    stem_z = stem_start + (top - stem_start) * fr["stem"]
    stem = np.stack([np.full_like(stem_z, x0), stem_z], 1)
    nodes = np.concatenate([base, [start_b], arc_b, weld, arc_s, stem])
    faces = ([Face.TOP] * len(base) + [Face.WELD] * (1 + len(arc_b) + len(weld) + len(arc_s))
             + [Face.STEM_POS] * len(stem))
    return nodes, faces, toe_b, toe_s


def _stem_outline(tj: TJointConfig, right_fillet: _Fillet, left_fillet: _Fillet, y: float, fr: dict[str, np.ndarray],
                  top_x: np.ndarray) -> tuple[np.ndarray, list[int], dict[tuple[int, str], np.ndarray]]:
    """The upper face's outline at station y from (L/2, z0) to (-L/2, z0), both corners in: the
    base's face, the x > 0 fillet, the stem up, across its end (``top_x``, both corners) and down,
    the x < 0 fillet, the base's face. Its nodes (k, 2) in (x, z), each node's following edge's
    face (the last one's: the x < 0 end wall) and the toe points by (side, plate)."""
    right, f_right, tb, ts = _half_outline(tj, right_fillet, y, fr)
    left, f_left, lb, ls = _half_outline(tj, left_fillet, y, fr)
    left = left[::-1] * np.array([-1.0, 1.0])
    f_left = [Face.STEM_NEG if f == Face.STEM_POS else f for f in f_left[::-1]]
    # each node's following edge: the reversed left half's edges run from node k to k + 1
    f_left = f_left[1:] + [Face.END_NEG]
    top = tj.base_thickness_mm / 2 + tj.stem_height_mm
    nodes = np.concatenate([right, np.stack([top_x, np.full(len(top_x), top)], 1), left])
    faces = f_right + [Face.STEM_TOP] * (len(top_x) - 1) + [Face.STEM_NEG] + f_left
    mirror = np.array([-1.0, 1.0])
    return nodes, faces, {(1, "base"): tb, (1, "stem"): ts, (-1, "base"): lb * mirror, (-1, "stem"): ls * mirror}


# a face of the upper outline turned half a turn about y: the same face of the part below the base
_TURNED = {Face.TOP: Face.BOTTOM, Face.STEM_POS: Face.STEM_NEG, Face.STEM_NEG: Face.STEM_POS,
           Face.STEM_TOP: Face.STEM_BOTTOM, Face.WELD: Face.WELD}


def build_tjoint(tj: TJointConfig, weld: WeldConfig, mesh_cfg: TrueMeshConfig, rng: np.random.Generator) -> TJoint:
    """Draw the fillet welds (a T-joint's two, a cruciform's four: the upper ones first, as a
    T-joint's) and mesh the closed surface."""
    fillets = {+1: _draw_fillet(tj, weld, rng), -1: _draw_fillet(tj, weld, rng)}
    below = None if tj.stems == "one" else {+1: _draw_fillet(tj, weld, rng), -1: _draw_fillet(tj, weld, rng)}
    L, W, t = tj.base_length_mm, tj.base_width_mm, tj.base_thickness_mm
    x0, z0 = tj.stem_thickness_mm / 2, t / 2
    leg = float(np.mean(tj.leg_mm))
    fr = {"weld": _both_ends(mesh_cfg.toe_dx_mm, mesh_cfg.weld_dx_mm, leg * np.sqrt(2)),
          "stem": _graded(tj.stem_height_mm - leg, mesh_cfg.toe_dx_mm, mesh_cfg.plate_dx_mm)}
    # the base plate's face from its far end (0) toward the toe (1, left out), fine at the toe
    fr["base"] = np.concatenate([[0.0], np.sort(1 - _graded(L / 2 - x0 - leg, mesh_cfg.toe_dx_mm,
                                                            mesh_cfg.plate_dx_mm)[1:])])
    n_bottom = max(2, int(np.ceil(L / mesh_cfg.plate_dx_mm)))
    bottom_x = -L / 2 + L * (np.arange(n_bottom) + 0.0) / n_bottom
    rows = mesh_cfg.wall_rows
    wall_z = -z0 + t * np.arange(rows - 1) / (rows - 1)  # from the bottom up, the top corner left out
    n_top = max(2, int(np.ceil(tj.stem_thickness_mm / mesh_cfg.plate_dx_mm)))
    top_x = x0 - 2 * x0 * np.arange(n_top + 1) / n_top  # both corners
    ys = np.linspace(-W / 2, W / 2, max(3, int(np.ceil(W / tj.along_weld_dx_mm)) + 1))
    outlines, toes = [], {(f, s, k): [] for f in (1, -1) for s in (1, -1) for k in ("base", "stem")}
    faces = None
    for y in ys:
        upper, f_upper, toes_upper = _stem_outline(tj, fillets[+1], fillets[-1], float(y), fr, top_x)
        if below is None:
            lower, f_lower = np.stack([bottom_x, np.full(n_bottom, -z0)], 1), [Face.BOTTOM] * n_bottom
            found = {(1, *k): p for k, p in toes_upper.items()}
        else:  # the upper outline of the lower stem's fillets, turned: from (-L/2, -z0), its last corner left
            # out (the right wall starts there); its x > 0 fillet is the lower stem's x < 0 one
            lower, f_lower, toes_lower = _stem_outline(tj, below[-1], below[+1], float(y), fr, top_x)
            lower, f_lower = -lower[:-1], [_TURNED[f] for f in f_lower[:-1]]
            found = {**{(1, *k): p for k, p in toes_upper.items()},
                     **{(-1, -s, plate): -p for (s, plate), p in toes_lower.items()}}
        poly = np.concatenate([lower, np.stack([np.full(rows - 1, L / 2), wall_z], 1), upper,
                               np.stack([np.full(rows - 2, -L / 2), -wall_z[1:]], 1)])
        if faces is None:
            faces = np.array(f_lower + [Face.END_POS] * (rows - 1) + f_upper + [Face.END_NEG] * (rows - 2), np.uint8)
        outlines.append(poly)
        for key, p in found.items():
            toes[key].append((p[0], y, p[1]))
    outline = np.stack(outlines)  # (ny, k, 2)
    ny, k, _ = outline.shape
    angle = np.unwrap(np.arctan2(outline[0, :, 1], outline[0, :, 0]))
    if not np.all(np.diff(angle) > 0) and not np.all(np.diff(angle) < 0):
        raise ValueError("T-joint outline is not star-shaped about the base plate's centre: the end faces "
                         "cannot be closed (legs too long for the plates?)")
    vertices = np.stack([outline[..., 0], np.repeat(ys[:, None], k, 1), outline[..., 1]], -1).reshape(-1, 3)
    j, i = np.meshgrid(np.arange(ny - 1), np.arange(k), indexing="ij")
    a, b = j * k + i, j * k + (i + 1) % k
    c, d = (j + 1) * k + (i + 1) % k, (j + 1) * k + i
    sweep = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    sweep_face = np.concatenate([np.tile(faces, ny - 1), np.tile(faces, ny - 1)])
    centres = np.array([[0.0, -W / 2, 0.0], [0.0, W / 2, 0.0]])
    c0, c1 = len(vertices), len(vertices) + 1
    ring = np.arange(k)
    cap0 = np.stack([np.full(k, c0), ring, (ring + 1) % k], 1)
    cap1 = np.stack([np.full(k, c1), (ny - 1) * k + (ring + 1) % k, (ny - 1) * k + ring], 1)
    vertices = np.concatenate([vertices, centres])
    triangles = np.concatenate([sweep, cap0, cap1]).astype(np.int32)
    face_id = np.concatenate([sweep_face, np.full(k, Face.SIDE_NEG), np.full(k, Face.SIDE_POS)]).astype(np.uint8)
    mesh = SurfaceMesh(vertices=vertices, triangles=triangles, face_id=face_id,
                       reflective=np.zeros(len(triangles), bool))
    if mesh.signed_volume_mm3() < 0:
        mesh = SurfaceMesh(vertices=vertices, triangles=triangles[:, ::-1].copy(), face_id=face_id,
                           reflective=mesh.reflective)
    toe_lines = [TrueToeLine(name=f"{name}-{plate}-toe", weld=name, plate=plate,
                             points_mm=[tuple(float(v) for v in p) for p in toes[(f, s, plate)]])
                 for (f, s), name in weld_names(tj).items() for plate in ("base", "stem")]
    return TJoint(config=tj, mesh=mesh, toes=toe_lines, fillets=fillets, fillets_below=below)


def tjoint_specimen(tj: TJointConfig) -> TJointSpecimen | CruciformSpecimen:
    figures = dict(base_length_mm=tj.base_length_mm, base_width_mm=tj.base_width_mm,
                   base_thickness_mm=tj.base_thickness_mm, stem_height_mm=tj.stem_height_mm,
                   stem_thickness_mm=tj.stem_thickness_mm, stem_x_mm=0.0)
    if tj.stems == "both":
        return CruciformSpecimen(kind="cruciform", **figures)
    return TJointSpecimen(kind="t-joint", **figures)


def tjoint_weld_lines(tj: TJointConfig) -> list[WeldLine]:
    """The fillets' roots: the stems' faces on the base plate, across the whole width."""
    y, x0, z0 = tj.base_width_mm / 2, tj.stem_thickness_mm / 2, tj.base_thickness_mm / 2
    where = {1: "" if tj.stems == "one" else ", upper face", -1: ", lower face"}
    return [WeldLine(name=name, label=f"fillet weld root, x {'>' if side > 0 else '<'} 0 side{where[face]}",
                     points_mm=[(side * x0, -y, face * z0), (side * x0, y, face * z0)])
            for (face, side), name in weld_names(tj).items()]


def plan_tjoint_passes(cfg: SimulationConfig, *, z_top_mm: float, setups: tuple[str, ...]) -> list[PlannedPass]:
    """The robot program, relative to the nominal placement (the base plate's upward face at
    ``z_top_mm``, centred at the origin). Stem up ("top"; a cruciform's both setups, one stem or
    the other up): four passes along the welds over the base plate (the outer two rolled outward
    onto its ends), two along each weld rolled toward it (``fillet_rolls_deg``: both toes), one
    along each long wall. A T-joint turned over ("bottom"): four along y over the underside, one
    along x down its middle, one along each long wall."""
    tj, robot, plan = cfg.tjoint, cfg.robot, cfg.plan
    standoff = cfg.scanner.reference_distance_mm
    rate = robot.profile_rate_hz()
    L, W, t = tj.base_length_mm, tj.base_width_mm, tj.base_thickness_mm
    x0 = tj.stem_thickness_mm / 2
    leg = float(np.mean(tj.leg_mm))
    m = plan.margin_mm
    along_y, along_x = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    passes: list[PlannedPass] = []

    def view(dx: float, dy: float) -> np.ndarray:  # tilted dx deg about y (toward +x), dy deg about x (toward +y)
        v = np.array([np.sin(np.radians(dx)), np.sin(np.radians(dy)), -np.cos(np.radians(dx)) * np.cos(np.radians(dy))])
        return v / np.linalg.norm(v)

    def add(setup: str, label: str, x: float, z: float, v: np.ndarray) -> None:
        count = sum(1 for p in passes if p.setup == setup and p.direction.startswith("along-weld")) + 1
        aim = np.array([x, -W / 2 - m, z])
        passes.append(PlannedPass(f"{setup}-Y{count:02d}", setup, label, _sensor_frame(along_y, v, aim, standoff),
                                  along_y, W + 2 * m, robot.speed_mm_s, rate))

    def add_x(setup: str, label: str, y: float, z: float, v: np.ndarray) -> None:
        count = sum(1 for p in passes if p.setup == setup and p.direction.startswith("along-base")) + 1
        aim = np.array([-L / 2 - m, y, z])
        passes.append(PlannedPass(f"{setup}-X{count:02d}", setup, label, _sensor_frame(along_x, v, aim, standoff),
                                  along_x, L + 2 * m, robot.speed_mm_s, rate))

    br, wr = tj.base_roll_deg, tj.wall_roll_deg
    for setup in setups:
        if setup == "top" or tj.stems == "both":
            add(setup, f"along-weld, base, rolled {br:g} out", -0.365 * L, z_top_mm, view(br, 0))
            add(setup, "along-weld, base", -0.17 * L, z_top_mm, view(0, 15))
            add(setup, "along-weld, base", 0.17 * L, z_top_mm, view(0, -15))
            add(setup, f"along-weld, base, rolled {br:g} out", 0.365 * L, z_top_mm, view(-br, 0))
            for side in (-1.0, 1.0):
                for roll in tj.fillet_rolls_deg:
                    reach = leg / 2 if roll < 55 else leg / 4
                    rise = leg / 2 if roll < 55 else leg * 1.5
                    add(setup, f"along-weld, fillet, rolled {roll:g}", side * (x0 + reach), z_top_mm + rise,
                        view(-side * roll, 0))
        else:
            add(setup, f"along-weld, base, rolled {br:g} out", -0.365 * L, z_top_mm, view(br, 0))
            add(setup, "along-weld, base", -0.115 * L, z_top_mm, view(0, 15))
            add(setup, "along-weld, base", 0.115 * L, z_top_mm, view(0, -15))
            add(setup, f"along-weld, base, rolled {br:g} out", 0.365 * L, z_top_mm, view(-br, 0))
            add_x(setup, "along-base, middle", 0.0, z_top_mm, view(15, 0))
        add_x(setup, f"along-base, wall, rolled {wr:g}", -W / 2, z_top_mm - t / 2, view(0, wr))
        add_x(setup, f"along-base, wall, rolled {wr:g}", W / 2, z_top_mm - t / 2, view(0, -wr))
    return passes


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    return np.arange(lo, hi + 1e-9, step) if hi > lo else np.zeros(0)


def tjoint_sticker_candidates(part: TJoint, cfg: SimulationConfig, step_mm: float = 1.0) -> Candidates:
    """Where a sticker may go: the base plate's faces clear of the welds, the stems' faces beyond
    them, and (``wall_stickers``) the base plate's four walls; clear of every edge."""
    tj, sc = part.config, cfg.stickers
    r, clear = sc.diameter_mm / 2, sc.edge_clearance_mm
    L, W, t = tj.base_length_mm, tj.base_width_mm, tj.base_thickness_mm
    x0, z0 = tj.stem_thickness_mm / 2, t / 2
    weld = part.weld_zone_half_mm() + sc.weld_clearance_mm + r
    ys = _grid(-W / 2 + r + clear, W / 2 - r - clear, step_mm)
    xs = _grid(-L / 2 + r + clear, L / 2 - r - clear, step_mm)
    xs_top = xs[np.abs(xs) > x0 + weld]
    zs_stem = _grid(z0 + weld, z0 + tj.stem_height_mm - r - clear, step_mm)
    zs_wall = _grid(-z0 + r + clear, z0 - r - clear, step_mm)
    if zs_wall.size == 0 and r + clear <= z0:
        zs_wall = np.zeros(1)
    blocks = []

    def add(face: int, pts: np.ndarray, normal) -> None:
        if len(pts):
            blocks.append((face, pts, np.repeat(np.asarray(normal, float)[None], len(pts), 0)))

    def plane(a: np.ndarray, b: np.ndarray, build) -> np.ndarray:
        A, B = np.meshgrid(a, b, indexing="ij")
        return build(A.ravel(), B.ravel())

    both = tj.stems == "both"
    add(Face.TOP, plane(xs_top, ys, lambda x, y: np.stack([x, y, np.full_like(x, z0)], 1)), (0, 0, 1))
    add(Face.BOTTOM, plane(xs_top if both else xs, ys, lambda x, y: np.stack([x, y, np.full_like(x, -z0)], 1)),
        (0, 0, -1))
    for face, s in ((Face.STEM_NEG, -1.0), (Face.STEM_POS, 1.0)):
        for zs in (zs_stem, -zs_stem[::-1]) if both else (zs_stem,):  # a cruciform's lower stem too
            add(face, plane(ys, zs, lambda y, z: np.stack([np.full_like(y, s * x0), y, z], 1)), (s, 0, 0))
    if tj.wall_stickers:
        for face, s in ((Face.SIDE_NEG, -1.0), (Face.SIDE_POS, 1.0)):
            add(face, plane(xs, zs_wall, lambda x, z: np.stack([x, np.full_like(x, s * W / 2), z], 1)), (0, s, 0))
        for face, s in ((Face.END_NEG, -1.0), (Face.END_POS, 1.0)):
            add(face, plane(ys, zs_wall, lambda y, z: np.stack([np.full_like(y, s * L / 2), y, z], 1)), (s, 0, 0))
    faces = np.concatenate([np.full(len(p), f, np.uint8) for f, p, _ in blocks])
    return Candidates(np.concatenate([p for _, p, _ in blocks]), np.concatenate([n for _, _, n in blocks]),
                      faces, step_mm)


def wall_sticker_picks(candidates: Candidates, masks: np.ndarray, part: TJoint,
                       rng: np.random.Generator) -> tuple[int, ...]:
    """Candidates (indices) for stickers every ``wall_sticker_pitch_mm`` along each of the base
    plate's walls, at a random height and offset, among those some pass sees."""
    tj = part.config
    picks = []
    for face in (Face.SIDE_NEG, Face.SIDE_POS, Face.END_NEG, Face.END_POS):
        on = np.flatnonzero((candidates.faces == face) & (masks != 0))
        if on.size == 0:
            continue
        along = candidates.centres[on, 1 if face in (Face.END_NEG, Face.END_POS) else 0]
        z = candidates.centres[on, 2]
        lo, hi = along.min(), along.max()
        for s in np.arange(lo + rng.uniform(0, tj.wall_sticker_pitch_mm / 2), hi, tj.wall_sticker_pitch_mm):
            target_z = rng.uniform(z.min(), z.max())
            picks.append(int(on[np.argmin(np.abs(along - s) + np.abs(z - target_z))]))
    return tuple(picks)


def place_tjoint_fixture_stickers(cfg: SimulationConfig, rng: np.random.Generator, first_id: int) -> StickerSet:
    """Stickers on the table beside the part (world frame): seen from both setups, they never move."""
    tj = cfg.tjoint
    return fixture_stickers_beside(cfg, rng, first_id, length_mm=tj.base_length_mm, half_width_mm=tj.base_width_mm / 2,
                                   spread_mm=12.0)
