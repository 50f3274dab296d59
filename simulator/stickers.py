"""Semi-random sticker placement: every pair of overlapping passes must see at least
``min_common`` common stickers whole, not in a line; a few more go on the fixture."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from schemas.simulation import SimulationConfig
from simulator.coverage import CoverageMap, face_params, spread_off_line_mm
from simulator.scene import StickerSet
from simulator.specimen import Face, Specimen

__all__ = ["StickerPlacementError", "Candidates", "sticker_candidates", "place_stickers", "place_fixture_stickers",
           "fixture_stickers_beside"]


class StickerPlacementError(ValueError):
    """The scan plan leaves no room for the stickers an overlapping pass pair needs."""


@dataclass(frozen=True)
class Candidates:
    """Sticker-eligible surface points, one per ``step_mm`` x ``step_mm`` of face."""

    centres: np.ndarray  # (k, 3) specimen frame, on the surface
    normals: np.ndarray  # (k, 3)
    faces: np.ndarray  # (k,)
    step_mm: float

    def params(self) -> np.ndarray:
        return face_params(self.faces, self.centres)


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    return np.arange(lo, hi + 1e-9, step) if hi > lo else np.zeros(0)


def sticker_candidates(specimen: Specimen, cfg: SimulationConfig, step_mm: float = 1.0) -> Candidates:
    """Points where a sticker may go: flat faces, clear of the weld zone and the face edges."""
    sc = specimen.config
    r = cfg.stickers.diameter_mm / 2
    clear = cfg.stickers.edge_clearance_mm
    weld_half = specimen.weld_zone_half_mm() + cfg.stickers.weld_clearance_mm + r
    centre_x = specimen.weld_top.centre_x_mm
    xs = _grid(-sc.length_mm / 2 + r + clear, sc.length_mm / 2 - r - clear, step_mm)
    xs = xs[np.abs(xs - centre_x) > weld_half]
    hw_min = np.minimum.reduce([specimen.half_width(xs + dx) for dx in (-r, 0.0, r)])
    centres, normals, faces = [], [], []
    eps = 0.05
    # the grid across each x, all x at once (the faces' heights are pointwise functions of x, y)
    rows = [_grid(-(hw - r - clear), hw - r - clear, step_mm) for hw in hw_min]
    ys = np.concatenate(rows) if rows else np.zeros(0)
    xx = np.repeat(xs, [len(row) for row in rows]) if rows else np.zeros(0)
    for face, z_of, sign in ((Face.TOP, specimen.top_z, 1.0), (Face.BOTTOM, specimen.bottom_z, -1.0)):
        if ys.size == 0:
            continue
        z = z_of(xx, ys)
        dzdx = (z_of(xx + eps, ys) - z_of(xx - eps, ys)) / (2 * eps)
        dzdy = (z_of(xx, ys + eps) - z_of(xx, ys - eps)) / (2 * eps)
        n = np.stack([-dzdx * sign, -dzdy * sign, np.full_like(ys, sign)], 1)
        centres.append(np.stack([xx, ys, z], 1))
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
        faces.append(np.full(ys.size, face))
    half_t = sc.thickness_mm / 2 - r - clear
    if half_t >= 0:
        for face, s in ((Face.SIDE_NEG, -1.0), (Face.SIDE_POS, 1.0)):
            for x in xs:
                zs = specimen.z_shift(np.array([x]))[0] + _grid(-half_t, half_t, step_mm)
                hw = specimen.half_width(np.array([x - eps, x, x + eps]))
                slope = (hw[2] - hw[0]) / (2 * eps)
                n = np.array([-slope, s, 0.0])
                centres.append(np.stack([np.full_like(zs, x), np.full_like(zs, s * hw[1]), zs], 1))
                normals.append(np.repeat((n / np.linalg.norm(n))[None], zs.size, 0))
                faces.append(np.full(zs.size, face))
    return Candidates(np.concatenate(centres), np.concatenate(normals), np.concatenate(faces).astype(np.uint8),
                      step_mm)


def _bits(mask: np.uint64) -> set[int]:
    m = int(mask)
    return {i for i in range(64) if m >> i & 1}


def place_stickers(candidates: Candidates, coverage: CoverageMap, pairs: list[tuple[int, int]],
                   cfg: SimulationConfig, rng: np.random.Generator, *, margin_mm: float = 0.0,
                   first: tuple[int, ...] = ()) -> StickerSet:
    """Greedy semi-random placement on the specimen (specimen frame). A pass counts as seeing a
    candidate when it sees the disc grown by ``margin_mm`` whole; the common stickers of a pair
    must lie ``min_spread_mm + 2 * margin_mm`` off their best line. ``first``: candidates placed
    before any (a T-joint's wall stickers)."""
    sc = cfg.stickers
    r = sc.diameter_mm / 2
    masks = coverage.disc_masks(candidates.faces, candidates.params(), r + margin_mm)
    tree = cKDTree(candidates.centres)
    spacing = sc.spacing_factor * sc.diameter_mm
    available = masks != 0
    chosen: list[int] = []

    def add(k: int) -> None:
        chosen.append(k)
        available[tree.query_ball_point(candidates.centres[k], spacing)] = False

    def room(pair: tuple[int, int]) -> int:
        both = (np.uint64(1) << np.uint64(pair[0])) | (np.uint64(1) << np.uint64(pair[1]))
        return int(np.count_nonzero((masks & both) == both))

    for k in first:
        add(int(k))
    # The pairs with the least room choose first; random extra stickers come last.
    pairs = sorted(pairs, key=room)
    for _ in range(4):
        changed = False
        for i, j in pairs:
            both = (np.uint64(1) << np.uint64(i)) | (np.uint64(1) << np.uint64(j))
            while True:
                common = [k for k in chosen if masks[k] & both == both]
                spread = spread_off_line_mm(candidates.centres[common])
                if len(common) >= sc.min_common and spread >= sc.min_spread_mm + 2 * margin_mm:
                    break
                pool = np.flatnonzero(available & ((masks & both) == both))
                if pool.size == 0:
                    names = coverage.pass_ids
                    raise StickerPlacementError(
                        f"passes {names[i]} and {names[j]} overlap but leave no room for sticker "
                        f"{len(common) + 1} of {sc.min_common} (diameter {sc.diameter_mm} mm); "
                        "widen their overlap (plan) or use smaller stickers"
                    )
                score = rng.random(pool.size)
                if common:
                    pts = candidates.centres[common]
                    if len(common) == 1:
                        off = np.linalg.norm(candidates.centres[pool] - pts[0], axis=1)
                    else:
                        c = pts.mean(axis=0)
                        direction = np.linalg.svd(pts - c, full_matrices=False)[2][0]
                        rel = candidates.centres[pool] - c
                        off = np.linalg.norm(rel - (rel @ direction)[:, None] * direction, axis=1)
                    score += np.minimum(off, 3 * sc.min_spread_mm) / sc.min_spread_mm
                add(int(pool[np.argmax(score)]))
                changed = True
        if not changed:
            break
    seen_area = np.count_nonzero(masks) * candidates.step_mm**2
    for _ in range(int(sc.fill_density_per_1000mm2 * seen_area / 1000)):
        pool = np.flatnonzero(available)
        if pool.size == 0:
            break
        add(int(rng.choice(pool)))
    ids = np.arange(len(chosen))
    return StickerSet(centres=candidates.centres[chosen], normals=candidates.normals[chosen], ids=ids,
                      faces=candidates.faces[chosen], radius_mm=r, thickness_mm=sc.thickness_mm)


def place_fixture_stickers(cfg: SimulationConfig, rng: np.random.Generator, first_id: int) -> StickerSet:
    """Stickers on the base plate beside the specimen (world frame)."""
    spec = cfg.specimen
    return fixture_stickers_beside(cfg, rng, first_id, length_mm=spec.length_mm, half_width_mm=spec.grip_width_mm / 2,
                                   spread_mm=10.0)


def fixture_stickers_beside(cfg: SimulationConfig, rng: np.random.Generator, first_id: int, *, length_mm: float,
                            half_width_mm: float, spread_mm: float) -> StickerSet:
    """``cfg.stickers.n_fixture`` stickers on the table (world frame, z = 0) beside a part of
    ``length_mm`` along x and ``half_width_mm`` either side of x: clear of where the placement may
    put it, within ``spread_mm`` more, never closer than the stickers' spacing."""
    sc = cfg.stickers
    r = sc.diameter_mm / 2
    centres: list[np.ndarray] = []
    gap = cfg.placement.translation_mm + 2 * r + 3
    tries = 0
    while len(centres) < sc.n_fixture and tries < 10000:
        tries += 1
        x = rng.uniform(-length_mm / 2 + 20, length_mm / 2 - 20)
        y = rng.choice([-1.0, 1.0]) * (half_width_mm + gap + rng.uniform(0, spread_mm))
        c = np.array([x, y, 0.0])
        if all(np.linalg.norm(c - o) > sc.spacing_factor * sc.diameter_mm for o in centres):
            centres.append(c)
    pts = np.array(centres).reshape(-1, 3)
    return StickerSet(centres=pts, normals=np.tile([0.0, 0.0, 1.0], (len(pts), 1)),
                      ids=first_id + np.arange(len(pts)), faces=np.full(len(pts), Face.FIXTURE, np.uint8),
                      radius_mm=r, thickness_mm=sc.thickness_mm)
