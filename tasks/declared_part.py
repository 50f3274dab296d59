"""The part measured against the part declared (the manifest's specimen), in the specimen frame.

The segment stage keeps what lies inside the declared part's box, placed where the first setup
says and grown by its placement tolerance; a part larger than declared is cut there without a word,
and one smaller than declared leaves the box half empty. Three pieces of evidence, each a figure
with the declared one beside it:

- **beyond the box**: the kept part touches a face of the grown box (a cut: the honest samples
  keep nothing within ``link_mm`` of it), and the merged cloud goes on past it by more than
  ``link_mm``, linked to the part: how far the part reaches, followed through the merged points in
  the box extended on that side;
- **shorter than declared**: along an axis, the kept part's extent (its extreme points: noise and
  tilt only lengthen it) falls short of the declared extent by more than ``max(5 mm, 10 %)``: the
  scans cover less of the part than declared, or the part is not the one declared (a flat part's
  thickness is checked as the next item says instead);
- **thickness** (flat parts: plate, dog-bone): the distance between the part's two faces along its
  own thinnest principal axis (the densest heights, one in each half: the weld's caps spread)
  against the declared thickness, off by more than ``max(1 mm, 5 %)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.frames import apply, invert
from tasks.segment import keep_specimen_components

__all__ = ["against_declaration", "AXES"]

AXES = "xyz"
CUT_FRACTION = 5e-4  # of the kept points within link_mm of a grown face: a cut (the honest samples: none)
SHORT_MM, SHORT_FRACTION = 5.0, 0.10
THICKNESS_MM, THICKNESS_FRACTION = 1.0, 0.05
_MAX_POINTS = 1_000_000  # the principal axes from every k-th kept point (deterministic)


def _thickness(local: np.ndarray, bin_mm: float = 0.1) -> float:
    """The distance between the part's two faces along its thinnest principal axis, mm: the
    densest bins of a histogram of the points along it, one in each half (a face is a sharp peak;
    the weld's caps, the side walls and the weld zone's finer cells spread)."""
    sample = local[:: max(1, -(-len(local) // _MAX_POINTS))]
    centre = sample.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((sample - centre).T))
    along = (sample - centre) @ vectors[:, 0]  # eigh: ascending, the first is the thinnest
    low, high = float(along.min()), float(along.max())
    counts, edges = np.histogram(along, bins=max(2, int(np.ceil((high - low) / bin_mm))), range=(low, high))
    middle = len(counts) // 2
    bottom = int(np.argmax(counts[:middle]))
    top = middle + int(np.argmax(counts[middle:]))
    bin_of = np.clip(np.searchsorted(edges, along, side="right") - 1, 0, len(counts) - 1)
    return float(along[bin_of == top].mean() - along[bin_of == bottom].mean())  # each face's mean height


def _reach(merged_local: np.ndarray, kept_near_face: np.ndarray, lo: np.ndarray, hi: np.ndarray, axis: int,
           side: int, extend_mm: float, link_mm: float) -> float:
    """How far along ``axis`` (side +1: up, -1: down) the part goes on past the grown box
    [lo, hi]: the merged points in the box extended by ``extend_mm`` on that side, linked
    (``link_mm``) to the kept points at the cut face; mm in the specimen frame."""
    lo, hi = lo.copy(), hi.copy()
    if side > 0:
        hi[axis] += extend_mm
    else:
        lo[axis] -= extend_mm
    inside = np.all((merged_local >= lo) & (merged_local <= hi), axis=1)
    candidates = merged_local[inside]
    linked = keep_specimen_components(candidates, link_mm=link_mm, target_points_mm=kept_near_face).keep
    along = candidates[linked, axis]
    return float(along.max() if side > 0 else along.min())


def against_declaration(kept_points: np.ndarray, merged_points: np.ndarray, *, T_frame_part: np.ndarray,
                        part_bounds_mm: tuple, grow_mm: float, link_mm: float, flat: bool,
                        declared_thickness_mm: float | None = None) -> dict[str, Any]:
    """The evidence above as a document (JSON types): ``agrees`` and, per disagreement, a sentence
    in ``findings``; the figures in ``declared_mm``, ``measured_mm`` (per axis: low, high; the
    reach past a cut face where there is one), ``cut_faces``, ``thickness_mm``.

    kept_points : (k, 3) mm, the part kept (the points' frame); merged_points : (n, 3) mm, every
    merged point (the same frame); T_frame_part : (4, 4) the part's nominal placement in that frame;
    part_bounds_mm : the declared box, specimen frame ((x0, y0, z0), (x1, y1, z1)); grow_mm : how far
    the segment stage grew the box (placement tolerance and margin); link_mm : the components' cell
    edge; flat : a plate or dog-bone (its thickness is checked); declared_thickness_mm : its thickness.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in part_bounds_mm)
    T_part_frame = invert(np.asarray(T_frame_part, dtype=np.float64))
    kept = apply(T_part_frame, kept_points)
    low, high = kept.min(axis=0), kept.max(axis=0)
    grown_lo, grown_hi = lo - grow_mm, hi + grow_mm
    declared = hi - lo
    findings: list[str] = []
    cut_faces = []
    merged = None
    for axis, name in enumerate(AXES):
        for side, face in ((-1, grown_lo[axis]), (1, grown_hi[axis])):
            near = np.abs(kept[:, axis] - face) <= link_mm
            count = int(np.count_nonzero(near))
            if count < max(1, CUT_FRACTION * len(kept)):
                continue
            if merged is None:
                merged = apply(T_part_frame, merged_points)
            reach = _reach(merged, kept[near], grown_lo, grown_hi, axis, side, float(declared.max()), link_mm)
            if (reach - face) * side <= link_mm:  # at the face, not past it (a weld's cap near a thin box)
                continue
            if side > 0:
                high[axis] = max(high[axis], reach)
            else:
                low[axis] = min(low[axis], reach)
            sign = "+" if side > 0 else "-"
            cut_faces.append({"axis": name, "side": sign, "points_at_face": count, "reaches_mm": round(reach, 2)})
            findings.append(f"the part goes on past its declared box at {sign}{name}: it reaches {name} = {reach:.1f} mm, "
                            f"the declared part {lo[axis]:g} .. {hi[axis]:g} mm (grown by {grow_mm:.1f} mm for the "
                            f"placement): measured {high[axis] - low[axis]:.1f} mm along {name}, declared "
                            f"{declared[axis]:g} mm")
    measured = high - low
    thin_axis = int(np.argmin(declared)) if flat and declared_thickness_mm is not None else None
    for axis, name in enumerate(AXES):
        if any(c["axis"] == name for c in cut_faces) or axis == thin_axis:  # a flat part's thickness: below
            continue
        short = declared[axis] - measured[axis]
        if short > max(SHORT_MM, SHORT_FRACTION * declared[axis]):
            findings.append(f"the part measured is {measured[axis]:.1f} mm along {name}, the declared part "
                            f"{declared[axis]:g} mm: the scans cover less of it than declared, or the part is not "
                            "the one declared")
    thickness = None
    if flat and declared_thickness_mm is not None and not cut_faces and len(kept) >= 3:
        thickness = _thickness(kept)
        off = thickness - declared_thickness_mm
        if abs(off) > max(THICKNESS_MM, THICKNESS_FRACTION * declared_thickness_mm):
            findings.append(f"the part measured is {thickness:.1f} mm thick (between its faces), declared "
                            f"{declared_thickness_mm:g} mm thick")
    return {"agrees": not findings, "findings": findings,
            "declared_mm": [[round(float(a), 2), round(float(b), 2)] for a, b in zip(lo, hi)],
            "measured_mm": [[round(float(a), 2), round(float(b), 2)] for a, b in zip(low, high)],
            "grow_mm": round(float(grow_mm), 3), "cut_faces": cut_faces,
            "thickness_mm": None if thickness is None else round(thickness, 2)}
