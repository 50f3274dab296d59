"""``weldrecon measure-weld``: a butt or a fillet weld measured straight from a scan's points. Its settings
(``MeasureWeldConfig``, written into the document) and its document (``ScanWeld``,
``<scan>.weld.json``): the weld document of the pipeline (``schemas.weld_document.WeldGeometry``,
frame: the scan's own) with what only a scan needs: the scan, the weld line and how it was found,
and per toe the radius the points cannot resolve ("below X mm") or why the toe is not measured.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from schemas.common import InputModel, StrictModel
from schemas.reconstruction import WeldGeometryConfig
from schemas.weld_document import WeldGeometry

__all__ = ["MeasureWeldConfig", "ScanSource", "ScanWeldLine", "ScanToe", "ScanWeld"]


class MeasureWeldConfig(InputModel):
    """How a scan's weld is read (``tasks.profile_weld``, ``tasks.scan_weld``), mm."""

    min_rise_mm: float = Field(default=0.3, gt=0, le=50, description=(
        "a weld found without a given line rises at least this over the plates (less: no weld in the scan)"))
    step_mm: float | None = Field(default=None, gt=0, le=100, description=(
        "sections every this far along the weld; None: each profile of a profile scan (1 mm in a cloud)"))
    section_half_width_mm: float | None = Field(default=None, gt=0, le=50, description=(
        "a slab section reads the points this close to it; None: half the step"))
    toe_window_mm: tuple[float, float] = Field(default=(1.5, 2.5), description=(
        "the toe fit: this much flank, this much plate around the first guess (a 3 mm fillet at 60 deg "
        "reaches 1.7 mm onto the plate and 0.9 mm up the flank from the corner)"))
    toe_threshold_mm: float = Field(default=0.1, gt=0, le=5, description=(
        "a rise this high over the plate starts the weld (the real plates' waviness reaches 0.05 mm)"))
    rise_run_mm: float = Field(default=0.3, gt=0, le=10, description="... held for this long")
    seed_fraction: float = Field(default=0.5, gt=0, le=1, description=(
        "each plate's first line is the lowest through this outer fraction of its side of the profile"))
    plate_gap_mm: float = Field(default=1.0, ge=0, le=20, description=(
        "a plate's line ends this far short of the toe's first guess"))
    min_plate_mm: float = Field(default=2.0, gt=0, le=100, description=(
        "less plate than this beside a toe: the toe is not measured"))
    undercut_min_depth_mm: float = Field(default=0.03, gt=0, le=5, description=(
        "a dip deeper than this beside a toe is fitted as undercut"))
    groove_min_depth_mm: float = Field(default=0.05, gt=0, le=5, description=(
        "treated welds: a dip deeper than this beside the toe is fitted as the HFMI groove"))
    groove_plate_gap_mm: float = Field(default=0.5, gt=0, le=10, description=(
        "treated welds: more plate than this between groove and flank: the toe is not within the groove"))
    spike_window: int = Field(default=7, ge=3, le=101, description="points in the running median that finds spikes")
    spike_sigmas: float = Field(default=8.0, gt=0, le=100, description="a spike is off it by more robust sigmas than this")
    spike_min_mm: float = Field(default=0.05, ge=0, le=10, description="... and more than this")
    bound_sigmas: float = Field(default=2.0, gt=0, le=10, description=(
        "the toe radii the points allow: within this many sigmas (profile likelihood)"))
    min_points: int = Field(default=8, ge=4, le=10000, description="fewer points in a fit: not measured")
    fillet: WeldGeometryConfig | None = Field(default=None, description=(
        "a fillet weld (--joint fillet) is read as stage weld reads a T-joint's (tasks.fillet_section) with "
        "these settings (schemas.reconstruction.WeldGeometryConfig; its section_step_mm and "
        "section_half_width_mm replaced by step_mm and section_half_width_mm where given); None: the "
        "stage's defaults, written in the document of a fillet weld; the butt weld's fields above do not apply"))
    fillet_plane_tolerance_mm: float = Field(default=0.3, gt=0, le=10, description=(
        "a fillet scan's plates are the planes most points lie within this of (tasks.scan_fillet)"))

    @model_validator(mode="after")
    def _odd_window(self) -> "MeasureWeldConfig":
        if self.spike_window % 2 == 0:
            raise ValueError(f"spike_window must be odd, got {self.spike_window}")
        if min(self.toe_window_mm) <= 0:
            raise ValueError(f"toe_window_mm must be positive, got {list(self.toe_window_mm)}")
        return self


class ScanSource(StrictModel):
    """What was measured: ``file`` a point file, or a folder (``kind``): a sample of imported scans
    (every scan, each placed by its pose) or a reconstruction's run folder (its published mesh's
    vertices, ``results/<sample_id>.ply``)."""

    file: str
    kind: Literal["file", "sample", "run"] = "file"
    files: list[str] = Field(default_factory=list, description="a folder's: the files its points came from")
    points: int
    profile_scan: bool  # each profile a section; False: slabs of an unordered cloud
    profile_pitch_mm: float | None  # between profiles along the weld
    point_spacing_mm: float | None  # median, along a section
    spikes_dropped: int


class ScanWeldLine(StrictModel):
    """The weld line in the scan's frame; ``found``: given on the command line or found on the data.
    A fillet weld's: its root line, ``face_normal`` up the stem (the base's normal), ``across``
    out along the base away from the stem."""

    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]
    face_normal: tuple[float, float, float]
    across: tuple[float, float, float]
    found: Literal["given", "auto"]


class ScanToe(StrictModel):
    """One toe of one section, beside its figures in ``geometry.sections``."""

    position_mm: float  # the section's, along the line
    side: Literal["minus", "plus", "base", "stem"]  # a butt weld's two sides, a fillet weld's two plates
    measured: bool
    toe_radius_below_mm: float | None = Field(default=None, description=(
        "the points do not resolve the toe radius (a sharp corner fits them): it is at most this "
        "(the largest radius within bound_sigmas); the section's toe_radius_mm is then None"))
    reason: str | None = None  # why the toe is not measured


class ScanWeld(StrictModel):
    """``<scan>.weld.json``."""

    schema_version: Literal["1"] = "1"
    source: ScanSource
    config: MeasureWeldConfig
    weld_line: ScanWeldLine
    geometry: WeldGeometry
    toes: list[ScanToe]
