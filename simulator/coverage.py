"""Which parts of the specimen's surface a pass sees, as cells of a 2-D grid on each face.

Face parameters: top/bottom and a stem's end (x, y); side walls (x, z); ends and stem faces (y, z);
specimen frame, mm.
Used to decide which passes overlap and which stickers a pass sees whole.
"""

from __future__ import annotations

import numpy as np

from simulator.specimen import Face
from tasks.arrays import distinct

__all__ = ["face_params", "cell_keys", "CoverageMap", "spread_off_line_mm"]

_OFFSET = 1 << 19


def face_params(face: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(a, b) parameters (n, 2) of specimen-frame points (n, 3) on faces (n,)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    a = np.where(np.isin(face, (Face.END_POS, Face.END_NEG, Face.STEM_NEG, Face.STEM_POS)), y, x)
    b = np.where(np.isin(face, (Face.TOP, Face.BOTTOM, Face.STEM_TOP, Face.STEM_BOTTOM)), y, z)
    return np.stack([a, b], axis=1)


def cell_keys(face: np.ndarray, ab: np.ndarray, cell_mm: float) -> np.ndarray:
    ij = np.floor(ab / cell_mm).astype(np.int64) + _OFFSET
    return (face.astype(np.int64) << 42) | (ij[:, 0] << 21) | ij[:, 1]


class CoverageMap:
    """Seen cells per pass, as sorted keys with a bitmask of the passes that saw each (<= 64)."""

    def __init__(self, pass_ids: list[str], cell_mm: float) -> None:
        if len(pass_ids) > 64:
            raise ValueError("coverage maps hold at most 64 passes")
        self.pass_ids = list(pass_ids)
        self.cell_mm = cell_mm
        self._seen: dict[int, np.ndarray] = {}

    def add(self, pass_index: int, face: np.ndarray, points: np.ndarray) -> None:
        keys = distinct(cell_keys(face, face_params(face, points), self.cell_mm))
        old = self._seen.get(pass_index)
        self._seen[pass_index] = keys if old is None else np.union1d(old, keys)

    def _table(self) -> tuple[np.ndarray, np.ndarray]:
        all_keys = distinct(np.concatenate(list(self._seen.values()))) if self._seen else np.zeros(0, np.int64)
        masks = np.zeros(all_keys.size, np.uint64)
        for index, keys in self._seen.items():
            masks[np.searchsorted(all_keys, keys)] |= np.uint64(1) << np.uint64(index)
        return all_keys, masks

    def overlapping_pairs(self, face: np.ndarray, ab: np.ndarray, points: np.ndarray, *, radius_mm: float,
                          min_area_mm2: float, area_per_point_mm2: float,
                          min_spread_mm: float) -> list[tuple[int, int]]:
        """Pass pairs that share room for stickers off one line: the sticker-eligible points
        (face, ab; ``points`` (k, 3) in 3-D), each standing for ``area_per_point_mm2``, around
        which both passes see a disc of ``radius_mm`` whole, must cover ``min_area_mm2`` and lie
        at least ``min_spread_mm`` off their best line. Slivers of overlap do not count."""
        masks = self.disc_masks(face, ab, radius_mm)
        n_min = min_area_mm2 / area_per_point_mm2
        pairs = []
        indices = sorted(self._seen)
        for i_pos, i in enumerate(indices):
            has_i = ((masks >> np.uint64(i)) & np.uint64(1)).astype(bool)
            for j in indices[i_pos + 1:]:
                common = has_i & ((masks >> np.uint64(j)) & np.uint64(1)).astype(bool)
                if np.count_nonzero(common) >= n_min and spread_off_line_mm(points[common]) >= min_spread_mm:
                    pairs.append((i, j))
        return pairs

    def disc_masks(self, face: np.ndarray, ab: np.ndarray, radius_mm: float) -> np.ndarray:
        """Bitmask (k,) of the passes that see every cell of each disc (centre ab, on face) whole."""
        keys_table, masks_table = self._table()
        angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        offsets = [(0.0, 0.0)] + [(r * np.cos(a), r * np.sin(a)) for r in (radius_mm * 0.5, radius_mm,
                                                                             radius_mm + self.cell_mm / 2)
                                  for a in angles]
        result = np.full(len(ab), np.iinfo(np.uint64).max, np.uint64)
        for da, db in offsets:
            keys = cell_keys(face, ab + np.array([da, db]), self.cell_mm)
            pos = np.clip(np.searchsorted(keys_table, keys), 0, max(keys_table.size - 1, 0))
            found = keys_table.size > 0
            m = np.where(found & (keys_table[pos] == keys), masks_table[pos], np.uint64(0)) if found else \
                np.zeros(len(keys), np.uint64)
            result &= m
        return result


def spread_off_line_mm(centres: np.ndarray) -> float:
    """Largest distance of the points (k, 3) from their best-fit line; 0 for fewer than 3."""
    if len(centres) < 3:
        return 0.0
    c = centres - centres.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    along = c @ vt[0]
    off = c - along[:, None] * vt[0][None, :]
    return float(np.linalg.norm(off, axis=1).max())
