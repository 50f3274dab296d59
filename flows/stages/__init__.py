"""The stage registry: every stage of the reconstruction, declared once, in run order.

The flow, the benchmark, the report, the audit trail and the tests iterate ``STAGES``; a stage's
``name`` is its one name everywhere (Prefect task, ``stages/<name>/`` in the store, audit trail,
catalog). Each stage's body lives in its own module (``flows/stages/<name>.py``) with the typed
description of the files it writes. ``run_stage`` (``flows.stages.runner``) runs any of them.
"""

from __future__ import annotations

from flows.stages import outputs
from flows.stages.contracts import ArrayFile, JsonFile, MeshFile, StageRef
from flows.stages.runner import Stage, StageContext, StageFailed, code_version, pass_hash, run_stage

__all__ = ["STAGES", "STAGE_NAMES", "stage", "run_stage", "Stage", "StageContext", "StageFailed", "StageRef",
           "ArrayFile", "JsonFile", "MeshFile", "code_version", "pass_hash", "downstream_of", "needed_for",
           "run_in_process", "stage_table"]


STAGES: tuple[Stage, ...] = (
    Stage("denoise", True, (), "denoise", (outputs.CLOUD, outputs.PREVIEW), "flows.stages.denoise:denoise", "flows.stages.views:pass_view",
          "ingest the pass (robot poses), remove statistical outliers, fit normals on the grid; streamed in blocks"),
    Stage("targets", True, (), "targets", (outputs.TARGETS,), "flows.stages.targets:targets", "flows.stages.views:targets_view",
          "sticker targets: Hough circles, sub-pixel 3-D rim fit; streamed in blocks"),
    Stage("registration", False, ("targets",), "registration",
          (outputs.REGISTRATION, outputs.REGISTRATION_SUMMARY), "flows.stages.registration:register",
          "flows.stages.views:setups_view",
          "match targets between passes, solve all pass poses; imported scans: none (stage refine registers them)",
          surfaces_body_at="flows.stages.registration:no_target_registration"),
    Stage("refine", False, ("denoise", "registration"), "refine", (outputs.REFINED, outputs.REFINE_SUMMARY),
          "flows.stages.refine:refine", "flows.stages.views:sample_wide_grids", "all pass poses on targets and overlapping surfaces together; imported "
          "scans (registration: surfaces) on their surfaces alone, from given poses or globally",
          surfaces_body_at="flows.stages.surfaces:refine_on_surfaces"),
    Stage("merge", False, ("denoise", "refine"), "merge", (outputs.MERGED,), "flows.stages.merge:merge", "flows.stages.views:weld_lines_view",
          "box-grid merge in the common frame, out of core; coarse cells where the surface is flat, "
          "away from the weld"),
    Stage("segment", False, ("merge", "refine"), "segment", (outputs.SPECIMEN,), "flows.stages.segment:segment",
          "flows.stages.views:segment_view",
          "remove unwanted objects (the fixture): components of occupied grid cells holding the part's stickers; "
          "a single setup: the fixture's plane, the drawing's box, one body of the part's size"),
    Stage("weld", False, ("segment", "refine"), "weld", (outputs.WELD_GEOMETRY, outputs.WELD_TOES), "flows.stages.weld:weld",
          "flows.stages.views:weld_view",
          "the weld measured on the specimen's points: sections every 1 mm, toe radius, flank angle, height, "
          "undercut, misalignment, HFMI grooves, each with its uncertainty; judged against acceptance limits"),
    Stage("mesh", False, ("segment",), "mesh", (outputs.MESH,), "flows.stages.mesh:mesh", "flows.stages.views:sample_wide",
          "screened Poisson (MeshLab) on the merged points and normals"),
    Stage("export", False, ("mesh",), None, (outputs.STL, outputs.PLY), "flows.stages.export:export", "flows.stages.views:sample_wide",
          "binary STL and PLY"),
    Stage("volume", False, ("refine", "weld", "mesh"), "volume", (outputs.VOLUME_INP, outputs.VOLUME_VTU, outputs.VOLUME_SUMMARY,
                                                     outputs.ELEMENT_QUALITY, outputs.MODEL_SURFACE),
          "flows.stages.volume:volume", "flows.stages.views:weld_lines_view", "the FE model: gmsh tetrahedra graded toward the weld lines and finer at the "
          "measured toes, one checked solid; "
          "Abaqus .inp and VTU with the weld zone as a named set"),
    Stage("stress", False, ("refine", "segment", "weld"), "stress",
          (outputs.STRESS_SUMMARY, outputs.STRESS_VTU, outputs.HOT_SECTION),
          "flows.stages.stress:stress", "flows.stages.views:stress_view",
          "the stress concentration along every measured toe: 2-D plane-strain sections across the weld from the "
          "measured points, pulled by CalculiX; hot spots, equilibrium and convergence checked"),
    Stage("report", False, ("denoise", "targets", "registration", "refine", "merge", "segment", "weld", "mesh",
                            "export", "volume", "stress"), "*",
          (outputs.REPORT,), "flows.stages.report:report", "flows.stages.views:report_view", "the sample's report",
          reads_input_metrics=True),
    Stage("qa_report", False, ("denoise", "targets", "registration", "refine", "segment", "weld", "mesh", "volume",
                               "stress", "report"), "qa_report", (outputs.QA_REPORT,), "flows.stages.qa_report:qa_report",
          "flows.stages.views:qa_report_view",
          "the QA report people read: one self-contained HTML page (coverage, stickers, registration graph, "
          "disagreement of overlapping passes, mesh renderings, weld sections and figures, FE model, provenance)"),
)

STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def stage(name: str) -> Stage:
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(f"no stage {name!r}; the stages are {', '.join(STAGE_NAMES)}")


def downstream_of(name: str) -> list[str]:
    """The stages that read ``name``'s outputs, directly or through others, in run order."""
    below = {name}
    for s in STAGES:
        if below.intersection(s.needs):
            below.add(s.name)
    return [s for s in STAGE_NAMES if s in below and s != name]


def needed_for(name: str) -> tuple[Stage, ...]:
    """``name`` and the stages whose outputs it reads, directly or through others, in run order:
    what a run stopped after ``name`` makes (``mesh``: not ``weld``, which only the FE model reads)."""
    needed = {stage(name).name}
    for s in reversed(STAGES):
        if s.name in needed:
            needed.update(s.needs)
    return tuple(s for s in STAGES if s.name in needed)


def run_in_process(*, store, sample_dir, manifest, config, upto: str | None = None) -> dict:
    """Every stage (or ``upto`` and the stages it needs, ``needed_for``) one after the other in
    this process, without Prefect (benchmarks, debugging): stage name -> its ref (a list of refs
    for per-pass stages)."""
    refs: dict = {}
    stages = STAGES if upto is None else needed_for(upto)
    for s in stages:
        s.load()
    for s in stages:
        inputs = {name: refs[name] for name in s.needs}
        common = dict(store=store, sample_dir=sample_dir, manifest=manifest, config=config, inputs=inputs)
        if s.per_pass:
            refs[s.name] = [run_stage(s, entry=e, **common) for _, e in manifest.passes()]
        else:
            refs[s.name] = run_stage(s, **common)
    return refs


def stage_table() -> str:
    """The registry as a Markdown table (``weldrecon stages``; docs/reconstruction.md holds the same)."""
    rows = ["| stage | runs | needs | settings | writes | what |", "|---|---|---|---|---|---|"]
    for s in STAGES:
        settings = {None: "-", "*": "all"}.get(s.settings, f"`{s.settings}`")
        writes = ", ".join(f"`{o.name}`" for o in s.outputs)
        rows.append(f"| `{s.name}` | {'per pass' if s.per_pass else 'once'} | {', '.join(s.needs) or '-'} | "
                    f"{settings} | {writes} | {s.summary} |")
    return "\n".join(rows) + "\n"


def _check_registry() -> None:
    from schemas.provenance import STAGE_NAMES as CLOSED

    if STAGE_NAMES != CLOSED:  # the provenance record's closed set of names is the registry's
        raise RuntimeError(f"stage registry: the stages {list(STAGE_NAMES)} are not schemas.provenance.StageName "
                           f"{list(CLOSED)}")
    seen: set[str] = set()
    for s in STAGES:
        missing = [n for n in s.needs if n not in seen]
        if missing or s.name in seen:
            raise RuntimeError(f"stage registry: {s.name} needs {missing} before it or is declared twice")
        if s.settings not in (None, "*", s.name):
            raise RuntimeError(f"stage registry: {s.name}'s settings must be the config section of its own name")
        seen.add(s.name)


_check_registry()
