"""The stress concentration along a line on an FE model's surface (a weld toe, a notch's rim):
the highest maximum principal stress in each section of the line, over a nominal stress.

``concentration_along`` cuts each line into sections of ``step_mm`` of its length; the nodes
within ``reach_mm`` of the line belong to the section their closest point on the line falls in
(``tasks.weld_zone.polyline_projection``, the same geometry as the weld zone). A section's factor
is its peak over ``nominal_mpa`` (the nominal stress of the section the caller chose: the load
over the plate's area for a butt weld in tension); the line's hot spot is its highest section,
the predicted crack start. Arrays in, numbers out: no solver, no files."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tasks.arrays import distinct
from tasks.fe_solve import max_principal
from tasks.weld_zone import polyline_projection

__all__ = ["SectionPeak", "LineConcentration", "concentration_along"]


@dataclass(frozen=True)
class SectionPeak:
    """One section of a line: ``station_mm`` its middle along the line (from the first vertex),
    its highest maximum principal stress ``peak_mpa`` (NaN: no node within reach), ``factor`` =
    peak / nominal, ``at_mm`` where it is, ``nodes`` how many nodes were looked at."""

    station_mm: float
    peak_mpa: float
    factor: float
    at_mm: tuple[float, float, float]
    nodes: int


@dataclass(frozen=True)
class LineConcentration:
    """A line's sections in order along it, and its hot spot."""

    line: str
    nominal_mpa: float
    sections: tuple[SectionPeak, ...]

    @property
    def hot_spot(self) -> SectionPeak | None:
        """The section with the highest factor (the first of equals); None: no node near the line."""
        found = [s for s in self.sections if s.nodes]
        return max(found, key=lambda s: s.factor) if found else None


def concentration_along(points_mm: np.ndarray, stress_mpa: np.ndarray, lines: Mapping[str, np.ndarray], *,
                        nominal_mpa: float, reach_mm: float, step_mm: float,
                        nodes: np.ndarray | None = None) -> list[LineConcentration]:
    """The concentration factor along each of ``lines`` (name -> (k >= 2, 3) polyline, mm, in the
    frame of ``points_mm``). ``points_mm`` (n, 3) the model's nodes, ``stress_mpa`` (n, 6) their
    stresses (xx, yy, zz, xy, yz, zx: ``tasks.fe_solve.FESolution.stress_mpa``), ``nodes`` the
    indices to look at (default all; a model's surface nodes: the peak of a notch is on its
    surface). ``step_mm``: the length of a section; ``reach_mm``: how far from the line a node may
    be."""
    points = np.asarray(points_mm, np.float64)
    stress = np.asarray(stress_mpa, np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"concentration_along: points_mm must be (n, 3), mm; got shape {points.shape}")
    if stress.shape != (len(points), 6):
        raise ValueError(f"concentration_along: stress_mpa must be ({len(points)}, 6), one row per point; "
                         f"got shape {stress.shape}")
    for name, value in (("nominal_mpa", nominal_mpa), ("reach_mm", reach_mm), ("step_mm", step_mm)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"concentration_along: {name} must be a positive number; got {value}")
    chosen = np.arange(len(points)) if nodes is None else distinct(np.asarray(nodes, np.int64))
    if len(chosen) and (chosen[0] < 0 or chosen[-1] >= len(points)):
        raise ValueError(f"concentration_along: nodes must index the {len(points)} points; "
                         f"got {chosen[0]}..{chosen[-1]}")
    sigma = max_principal(stress[chosen])
    out = []
    for name, line in lines.items():
        vertices = np.asarray(line, np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 2:
            raise ValueError(f"concentration_along: line {name!r} must be (k >= 2, 3) points, mm; "
                             f"got shape {vertices.shape}")
        length = float(np.linalg.norm(np.diff(vertices, axis=0), axis=1).sum())
        count = max(1, math.ceil(length / step_mm - 1e-9))
        distance, station = polyline_projection(points[chosen], vertices)
        near = np.flatnonzero((distance <= reach_mm) & np.isfinite(sigma))
        section = np.minimum((station[near] / step_mm).astype(np.int64), count - 1)
        sections = []
        for k in range(count):
            mine = near[section == k]
            middle = min((k + 0.5) * step_mm, length)
            if not len(mine):
                sections.append(SectionPeak(middle, math.nan, math.nan, (math.nan,) * 3, 0))
                continue
            top = mine[int(np.argmax(sigma[mine]))]
            peak = float(sigma[top])
            sections.append(SectionPeak(middle, peak, peak / float(nominal_mpa),
                                        tuple(float(v) for v in points[chosen[top]]), len(mine)))
        out.append(LineConcentration(name, float(nominal_mpa), tuple(sections)))
    return out
