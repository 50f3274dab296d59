"""What each stage reads of the sample's manifest: the part of it hashed into the stage's cache key
(``Stage.manifest_view_at`` in the registry). A manifest edit outside a stage's view leaves its key,
and its outputs, as they were.

All in one place, apart from the stage bodies and with light imports only: what a stage's key
covers of the manifest reads in one page, and a view can be computed without the compute stack.
"""

from __future__ import annotations

from typing import Any

from data_catalog.acceptance import DEFAULT_ACCEPTANCE_FILE
from data_catalog.hashing import sha256_file
from schemas.manifest import PassEntry, SampleManifest

__all__ = ["pass_view", "targets_view", "setups_view", "sample_wide", "sample_wide_grids", "weld_lines_view",
           "segment_view", "weld_view", "report_view", "qa_report_view"]


def pass_view(manifest: SampleManifest, entry: PassEntry | None) -> dict[str, Any]:
    """What a per-pass stage reads from the manifest besides the pass file: the scanner (hand-eye
    transform) and the pass's entry (its nominal motion)."""
    assert entry is not None
    return {"scanner": None if manifest.scanner is None else manifest.scanner.model_dump(mode="json"),
            "pass": entry.model_dump(mode="json", exclude={"file", "content_sha256"})}


def targets_view(manifest: SampleManifest, entry: PassEntry | None) -> dict[str, Any]:
    """The pass's view and the stickers' diameter (None: a sample registered on its surfaces)."""
    return {**pass_view(manifest, entry), "sticker_diameter_mm": manifest.sticker_diameter_mm}


def setups_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """The passes in order, each with its setup, and how the sample is registered; the setups a
    positioner turned, with its calibrated turns (a hand-turned sample's key as before them)."""
    view = {"passes": [[setup, e.pass_id] for setup, e in manifest.passes()], "registration": manifest.registration}
    turns = {s.name: s.positioner.model_dump(mode="json") for s in manifest.setups if s.positioner is not None}
    if turns:
        view["positioners"] = turns
    return view


def sample_wide(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """The passes in order."""
    return {"passes": [e.pass_id for _, e in manifest.passes()]}


def sample_wide_grids(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """The passes and the pitch of each one's grid (refine reads the grids thinned by it)."""
    pitches = [None if manifest.surfaces else list(manifest.grid_pitch_mm(e)) for _, e in manifest.passes()]
    return {**sample_wide(manifest, entry), "pitch_mm": pitches}


def weld_lines_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """What a stage that treats the weld apart reads of the manifest (the merge, the FE model): the
    passes (in order), each setup's nominal placement and tolerance, and the weld lines (specimen
    frame, mm; a 1.0 and a 1.1 manifest of one part give the same lines, hence the same key)."""
    return {"passes": [e.pass_id for _, e in manifest.passes()],
            "weld_lines_mm": [[list(p) for p in line.points_mm] for line in manifest.weld_lines()],
            "setups": [{"name": s.name, "passes": [e.pass_id for e in s.passes],
                        "T_world_specimen_nominal": s.T_world_specimen_nominal,
                        "placement_tolerance_mm": s.placement_tolerance_mm} for s in manifest.setups]}


def segment_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """What the segment reads of the manifest: the passes (in order), the part's drawing box, and
    the first setup's nominal placement and tolerance (one setup: ``single_setup``; more:
    ``first_setup``, the drawing box's placement)."""
    bounds = None if manifest.specimen is None else [list(b) for b in manifest.specimen.bounds_mm()]
    view: dict[str, Any] = {"passes": [e.pass_id for _, e in manifest.passes()], "bounds_mm": bounds}
    if manifest.surfaces:
        view["registration"] = manifest.registration
    else:
        setup = manifest.setups[0]
        placement = {"T_world_specimen_nominal": setup.T_world_specimen_nominal,
                     "placement_tolerance_mm": setup.placement_tolerance_mm}
        view["single_setup" if len(manifest.setups) == 1 else "first_setup"] = placement
    return view


def weld_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """What the weld stage reads: the passes (in order), the weld (lines, joint, treatment), each
    setup's nominal placement, and the default acceptance limits' file (by sha256)."""
    weld = manifest.weld
    return {"passes": [e.pass_id for _, e in manifest.passes()],
            "weld_lines_mm": {line.name: [list(p) for p in line.points_mm] for line in manifest.weld_lines()},
            "joint": getattr(weld, "joint", "double-sided butt"), "treatment": None if weld is None else weld.treatment,
            "setups": [{"name": s.name, "first_pass": s.passes[0].pass_id,
                        "T_world_specimen_nominal": s.T_world_specimen_nominal} for s in manifest.setups],
            "default_acceptance_sha256": sha256_file(DEFAULT_ACCEPTANCE_FILE)}


def stress_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """What the stress stage reads: the passes (in order), the weld lines and joint, each setup's
    nominal placement (the specimen frame), and the part's kind (the load case)."""
    weld = manifest.weld
    return {"passes": [e.pass_id for _, e in manifest.passes()],
            "weld_lines_mm": {line.name: [list(p) for p in line.points_mm] for line in manifest.weld_lines()},
            "joint": getattr(weld, "joint", "double-sided butt"),
            "setups": [{"name": s.name, "first_pass": s.passes[0].pass_id,
                        "T_world_specimen_nominal": s.T_world_specimen_nominal} for s in manifest.setups],
            "part": None if manifest.specimen is None else manifest.specimen.kind}


def report_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """The sample and its passes by setup."""
    return {"sample_id": manifest.sample_id, "passes": [[s, e.pass_id] for s, e in manifest.passes()]}


def qa_report_view(manifest: SampleManifest, entry: PassEntry | None = None) -> dict[str, Any]:
    """What the QA page reads of the manifest: the passes by setup, the part, the weld, the stickers."""
    return {"sample_id": manifest.sample_id, "passes": [[s, e.pass_id] for s, e in manifest.passes()],
            "specimen": manifest.specimen.model_dump(mode="json") if manifest.specimen is not None else None,
            "weld": None if manifest.weld is None else manifest.weld.model_dump(mode="json"),
            "weld_lines_mm": [[list(p) for p in line.points_mm] for line in manifest.weld_lines()],
            "setups": [{"name": s.name, "first_pass": s.passes[0].pass_id,
                        "T_world_specimen_nominal": s.T_world_specimen_nominal} for s in manifest.setups],
            "sticker_diameter_mm": manifest.sticker_diameter_mm}
