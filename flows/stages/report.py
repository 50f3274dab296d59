"""Stage ``report``: the sample's report (what every stage measured, the registration, the mesh,
the settings, every stage's key) and the publishing of the deliverables into ``results/``.

``report.json`` is a function of the stages' outputs and records only (no times, no paths, no
cache flags: those are in the audit trail), so the same inputs give the same bytes."""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from pathlib import Path
from typing import Any

from data_catalog.atomic import default_mode, fsync_tree, owner_tag, replace_directory
from flows.stages.contracts import StageRef
from flows.stages.outputs import (PLY, QA_REPORT, REFINE_SUMMARY, REGISTRATION_SUMMARY, REPORT, STL, STRESS_SUMMARY,
                                  STRESS_VTU, VOLUME_INP, VOLUME_SUMMARY, VOLUME_VTU, WELD_GEOMETRY)
from data_catalog.hashing import sha256_file
from flows.stages.qa_audit import UNVERIFIED, fill_audit
from schemas.stage_documents import (Check, FEModelSummary, Report, StressFigures, StressReport, StressSummary,
                                     WeldReport)
from schemas.weld_document import WeldGeometry
from tasks.sliver_repair import MAX_ASPECT_RATIO, MIN_DIHEDRAL_DEG

__all__ = ["report", "publish", "deliverables", "checks", "fe_model_check", "stress_check", "stress_summary", "weld_summary", "RESULTS",
           "CONFIG_NAME"]

RESULTS = "results"
CONFIG_NAME = "config.json"  # the settings the published results were made with


def deliverables(sample_id: str) -> dict[str, tuple[str, str]]:
    """results/ file name -> (the stage, its output) it is a copy of (the volume's files only
    where the stage made them)."""
    return {f"{sample_id}.stl": ("export", STL.name), f"{sample_id}.ply": ("export", PLY.name),
            f"{sample_id}.inp": ("volume", VOLUME_INP.name), f"{sample_id}.vtu": ("volume", VOLUME_VTU.name),
            f"{sample_id}_stress.vtu": ("stress", STRESS_VTU.name)}


def _metrics(ref: StageRef | list[StageRef]) -> Any:
    if isinstance(ref, list):
        return [_metrics(r) for r in ref]
    return {k: v for k, v in ref.metrics.items() if k != "seconds"}


def checks(names: list[str], denoise: list[StageRef], refine: StageRef) -> list[Check]:
    """Every consistency check the run made (tasks.consistency), one entry per check and pass:
    ``result`` "ok" or "flagged", ``what`` in words. Checks that fail stop the run instead."""
    out = []
    for name, ref in zip(names, denoise):
        if "checks" not in ref.metrics:  # an imported scan: no profiles, times or chunks to check
            continue
        found = ref.metrics["checks"]
        motion = found.get("motion", {})
        out.append(Check(check="profile times and poses", pass_=name, result="ok",
                         what=("times in order; logged flange poses rigid, no jump or turn beyond the limits"
                               if motion.get("logged_poses") else "times in order (nominal motion, no logged poses)"),
                         measured=motion))
        jumps = found.get("chunk_jumps", [])
        out.append(Check(check="surface continuity at chunk boundaries", pass_=name,
                         result="flagged" if jumps else "ok",
                         what=("; ".join(f"the surface steps {j['step_mm']} mm into profile {j['profile']} (a storage "
                                         f"chunk's first), at most {j['around_mm']} mm around it: a chunk may be out of "
                                         f"place" for j in jumps) or "every chunk continues its neighbours"),
                         measured=jumps))
    residuals = refine.metrics.get("checks", {}).get("target_residuals", {})
    flagged = {f["pass"]: f for f in residuals.get("flagged", [])}
    for name, value in residuals.get("per_pass_median_mm", {}).items():
        f = flagged.get(name)
        out.append(Check(check="target residuals against the sample's", pass_=name,
                         result="flagged" if f else "ok",
                         what=(f"median target residual {f['residual_median_mm'] * 1000:.0f} um, over 3 x the sample's "
                               f"{f['sample_median_mm'] * 1000:.0f} um: its data or poses disagree with the other passes"
                               if f else "in line with the other passes"),
                         measured=value))
    shared = refine.metrics.get("checks", {}).get("surfaces_between_setups")
    if shared:
        out.append(Check(check="surfaces the setups share", pass_="all", result="flagged" if shared["flagged"] else "ok",
                         what=shared["flagged"] or (f"{shared['pairs_across']} pass pairs across setups overlap, median "
                                                    f"RMS {shared['rms_median_across_mm'] * 1000:.0f} um (one setup's "
                                                    f"{(shared['rms_median_within_mm'] or 0) * 1000:.0f} um)"),
                         measured={k: v for k, v in shared.items() if k != "flagged"}))
    return out


def declared_part_check(segment: StageRef) -> list[Check]:
    """The part kept held against the part declared (flows.stages.segment, tasks.declared_part): its
    size along the specimen frame's axes and, for a flat part, its thickness; none where no setup
    places the part (imported scans)."""
    found = segment.metrics.get("declared_part")
    if not found:
        return []
    measured = {k: found[k] for k in ("declared_mm", "measured_mm", "cut_faces", "thickness_mm")}
    if found["agrees"]:
        extents = " x ".join(f"{b - a:.1f}" for a, b in found["measured_mm"])
        return [Check(check="part as declared", pass_="all", result="ok",
                      what=f"the part measured ({extents} mm along x, y, z) is the part declared", measured=measured)]
    return [Check(check="part as declared", pass_="all", result="flagged", what="; ".join(found["findings"]),
                  measured=measured)]


def weld_summary(geometry: WeldGeometry) -> WeldReport:
    """The weld's part of the report: the verdict, where it fails, the figures along the weld
    (the per-section values and their uncertainties stay in the weld stage's weld_geometry.json)."""
    if not geometry.measured:
        return WeldReport(measured=False, why_not=geometry.why_not)
    return WeldReport(measured=True, joint=geometry.joint, treatment=geometry.treatment,
                      acceptance_source=geometry.acceptance_source,
                      acceptance_rule_source=None if geometry.acceptance is None else geometry.acceptance.source,
                      **geometry.summary.model_dump(), failing_sections=geometry.failing,
                      uncertain_sections=geometry.uncertain, lines=geometry.lines, statistics=geometry.statistics)


def weld_check(geometry: WeldGeometry) -> Check:
    """The weld's evidence: measured at every weld line the manifest names, and judged by a rule;
    flagged otherwise, saying what is missing (the verdict itself, pass or fail, is the weld's part
    of the report; this says whether there is one to trust)."""
    if not geometry.measured:
        return Check(check="weld measured", pass_="all", result="flagged", what=f"not measured: {geometry.why_not}",
                     measured={})
    summary = geometry.summary
    measured = {"sections": summary.sections, "sections_measured": summary.sections_measured}
    if summary.sections_measured == 0 or summary.lines_without_sections:
        return Check(check="weld measured", pass_="all", result="flagged", what=summary.verdict, measured=measured)
    if geometry.acceptance is None:
        return Check(check="weld measured", pass_="all", result="flagged",
                     what=f"{summary.sections_measured} of {summary.sections} sections measured, not judged: "
                          f"{summary.verdict}", measured=measured)
    return Check(check="weld measured", pass_="all", result="ok",
                 what=f"{summary.sections_measured} of {summary.sections} sections measured at every weld line, "
                      f"judged: {summary.verdict}", measured=measured)


ELEMENT_LIMITS = {"min_dihedral_deg": MIN_DIHEDRAL_DEG, "aspect_ratio": MAX_ASPECT_RATIO}


def fe_model_check(summary: FEModelSummary) -> Check:
    """The FE model's check: made as one solid of the mesh's volume, every element within
    ``ELEMENT_LIMITS``; or why not."""
    if not summary.made:
        return Check(check="FE model", pass_="all", result="flagged", what=f"not made: {summary.why}", measured={})
    solid, quality = summary.solid, summary.quality
    # the limits FE programs accept without warnings (issue 26): no element under 10 deg, none over 10
    outside = [what for what, bad in (
        (f"{quality.below_10_deg} element(s) with a smallest dihedral angle under {ELEMENT_LIMITS['min_dihedral_deg']:g} "
         f"deg (worst {quality.min_dihedral_deg.worst:g})", quality.below_10_deg > 0),
        (f"an aspect ratio of {quality.aspect_ratio.worst:g}, over {ELEMENT_LIMITS['aspect_ratio']:g}",
         quality.aspect_ratio.worst > ELEMENT_LIMITS["aspect_ratio"])) if bad]
    return Check(check="FE model", pass_="all", result="flagged" if outside else "ok",
                 what="; ".join([f"one solid of {solid.tetrahedra} tetrahedra, volume {100 * solid.volume_difference:+.2f} % "
                                 f"of the mesh's" + ("" if summary.surface_remeshed else
                                                     f"; the surface's own triangles kept ({summary.surface_kept_because or 'gmsh could not reparametrise it'})"),
                                 *outside]),
                 measured={"volume_difference": solid.volume_difference,
                           "min_dihedral_deg": summary.quality.min_dihedral_deg.worst})


def stress_summary(summary: StressSummary) -> StressReport:
    """The stress's part of the report (the per-section figures stay in stress.json)."""
    return StressReport(**{name: getattr(summary, name) for name in StressFigures.model_fields},
                        sections=len(summary.sections))


# what the stress's checks allow: the ends' reactions 0.1 % apart, the plate's membrane stress 1 %
# off the force over its thickness, the hot spot 5 % apart with half-size elements at the toe
STRESS_LIMITS = {"imbalance": 1e-3, "membrane": 0.01, "convergence": 0.05}


def stress_check(summary: StressSummary) -> Check:
    """The stress's check: equilibrium, the membrane stress and the hot spot's convergence within
    ``STRESS_LIMITS`` (and checked: not refused with finer elements), and no section refused by
    CalculiX, or why there is no stress."""
    if not summary.made:
        return Check(check="stress at the toes", pass_="all", result="flagged", what=f"not computed: {summary.why}",
                     measured={})
    problems = []
    if not (summary.max_imbalance is not None and summary.max_imbalance <= STRESS_LIMITS["imbalance"]):
        problems.append(f"the ends' reactions {summary.max_imbalance} apart (at most {STRESS_LIMITS['imbalance']})")
    if not (summary.max_membrane_error is not None and abs(summary.max_membrane_error) <= STRESS_LIMITS["membrane"]):
        against = ("its bending stress at the surface off 6 M / t^2" if "bending" in (summary.model or "")
                   else "its membrane stress off the force over its thickness")
        problems.append(f"the plate's check: {against} by {summary.max_membrane_error} (at most "
                        f"{STRESS_LIMITS['membrane']})")
    c = summary.convergence
    if c is not None and abs(c.change) > STRESS_LIMITS["convergence"]:
        problems.append(f"the hot spot's factor moves by {100 * c.change:+.1f} % with half-size elements at the toe "
                        f"(at most {100 * STRESS_LIMITS['convergence']:.0f} %)")
    if summary.convergence_refused:
        problems.append(f"the hot spot's convergence not checked: {summary.convergence_refused}")
    if summary.sections_refused:
        first = summary.sections_refused[0]
        problems.append(f"{len(summary.sections_refused)} section(s) CalculiX refused, left out (at "
                        f"{', '.join(f'{r.position_mm:g}' for r in summary.sections_refused)} mm; the first: {first.why})")
    hot = summary.hot_spot
    what = (f"{len(summary.sections)} sections; hot spot {hot.line} {hot.side} toe at {hot.position_mm:g} mm, factor "
            f"{hot.factor:.2f}" if hot is not None else f"{len(summary.sections)} sections, no toe within reach")
    return Check(check="stress at the toes", pass_="all", result="flagged" if problems else "ok",
                 what="; ".join([what, *problems]),
                 measured={"max_imbalance": summary.max_imbalance, "max_membrane_error": summary.max_membrane_error,
                           "convergence": None if c is None else c.change})


def report(ctx) -> dict[str, Any]:
    inputs = ctx.inputs
    volume = VOLUME_SUMMARY.read(inputs["volume"])
    stress = STRESS_SUMMARY.read(inputs["stress"])
    weld = WELD_GEOMETRY.read(inputs["weld"])
    body = Report(
        sample_id=ctx.manifest.sample_id,
        passes=ctx.names,
        config=ctx.config.model_dump(mode="json"),
        stages={name: _metrics(ref) for name, ref in inputs.items()},
        registration=REGISTRATION_SUMMARY.read(inputs["registration"]),
        refinement=REFINE_SUMMARY.read(inputs["refine"]),
        # per pass, what registered it: "targets" (stickers), "surfaces from given poses", "surfaces, global"
        registration_method=inputs["refine"].metrics.get("registration_method", {}),
        mesh=_metrics(inputs["mesh"]),
        volume_mesh=volume,
        stress=stress_summary(stress),
        weld=weld_summary(weld),
        # the stress is checked where the weld was measured (elsewhere the weld's part says why not)
        # the weld's evidence where the manifest describes a weld (imported scans of a bare part need none)
        checks=(checks(ctx.names, inputs["denoise"], inputs["refine"]) + declared_part_check(inputs["segment"])
                + ([weld_check(weld)] if ctx.manifest.weld_lines() else []) + [fe_model_check(volume)]
                + ([stress_check(stress)] if weld.measured else [])),
        deliverables={name: inputs[stage].outputs[source]
                      for name, (stage, source) in deliverables(ctx.manifest.sample_id).items()
                      if source in inputs[stage].outputs},
        stage_keys={name: ([r.key for r in ref] if isinstance(ref, list) else ref.key) for name, ref in inputs.items()},
    )
    REPORT.write(ctx.out, body)
    return {"deliverables": len(body.deliverables)}


def publish(out_dir: Path, sample_id: str, report_ref: StageRef, refs: dict[str, StageRef],
            config_json: str, audit_status: dict[str, Any] | None = None) -> dict[str, dict[str, str]]:
    """Publish the deliverables, the report and the settings they were made with (``config.json``)
    into ``out_dir/results/`` as one unit, with the QA report (``report.html``, when the run made
    one) whose audit section is filled with ``audit_status`` (``qa_report.fill_audit``): the folder
    is built complete beside it, each copy checked
    against its stage record, flushed to disk, then swapped in whole
    (``data_catalog.atomic.replace_directory``). Readers see the previous results whole or these
    whole, never a mix, even after a kill; files of an earlier publication that this one does not
    have (another sample id's) go with it. Returns file name -> {path, sha256}."""
    out_dir = Path(out_dir)
    results = out_dir / RESULTS
    # an optional output the stage left out (or a stage that did not run for this sample) is not published
    sources = {name: (refs[stage], source) for name, (stage, source) in deliverables(sample_id).items()
               if stage in refs and source in refs[stage].outputs}
    sources[REPORT.name] = (report_ref, REPORT.name)
    staging = Path(tempfile.mkdtemp(prefix=f".{RESULTS}.{owner_tag()}.", suffix=".partial", dir=out_dir))
    try:
        digests = {}
        for name, (ref, source) in sources.items():
            shutil.copyfile(ref.file(source), staging / name)
            digests[name] = sha256_file(staging / name)
            if digests[name] != ref.outputs[source]:
                raise OSError(f"{ref.file(source)} changed while it was published (sha256 differs from its record)")
        (staging / CONFIG_NAME).write_text(config_json, encoding="utf-8")
        digests[CONFIG_NAME] = sha256_file(staging / CONFIG_NAME)
        if "qa_report" in refs:
            source = refs["qa_report"].file(QA_REPORT.name)
            page = source.read_bytes()
            if hashlib.sha256(page).hexdigest() != refs["qa_report"].outputs[QA_REPORT.name]:
                raise OSError(f"{refs['qa_report'].file(QA_REPORT.name)} changed while it was published "
                              "(sha256 differs from its record)")
            (staging / QA_REPORT.name).write_bytes(fill_audit(page.decode("utf-8"), audit_status or UNVERIFIED).encode())
            digests[QA_REPORT.name] = sha256_file(staging / QA_REPORT.name)
        default_mode(staging)
        fsync_tree(staging)
        replace_directory(staging, results)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return {name: {"path": str(results / name), "sha256": digest} for name, digest in digests.items()}
