"""A reconstruction's typed summary (``flows.reconstruct.RunResult``) on the terminal: the one
place that renders it."""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["print_run_summary", "print_stopped_run"]


def print_run_summary(run, out: Path) -> None:
    """The run's summary on the terminal (``run``: a ``flows.reconstruct.RunResult`` with its
    report; ``out``: the run folder); flagged checks as warnings on stderr."""
    from flows.stages import STAGES

    report = run.report
    refined, mesh = report.stages["refine"], report.mesh
    print(f"{report.sample_id}: {len(report.passes)} passes")
    for stage in STAGES:
        name = stage.name
        if name not in report.stages:
            continue
        value, seconds, cached = report.stages[name], run.seconds.get(name, 0.0), run.cached[name]
        if stage.per_pass:
            print(f"  {name:<12} {len(value)} passes, {seconds:.1f} s of work{', all cached' if cached else ''}")
        else:
            extra = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in value.items()
                     if k in ("points_in", "points_out", "residual_median_mm", "residual_max_mm", "vertices",
                              "watertight", "surface_pairs", "surface_rms_median_mm", "largest_pose_change_mm",
                              "target_residual_median_mm")}
            print(f"  {name:<12} {'cached' if cached else f'{seconds:.1f} s'}  {extra}")
    methods = report.registration_method
    if methods:  # per pass: targets, surfaces from given poses, surfaces, global
        kinds = sorted(set(methods.values()))
        print("registration: " + "; ".join(f"{k} ({sum(v == k for v in methods.values())} passes)" for k in kinds))
    for e in report.registration.between_setups:
        if e.prior == "positioner":  # matched on the positioner's calibrated turn, checked on the stickers
            turn = e.turn
            print(f"  setup {e.b}: turned by the positioner, {e.targets} stickers where its turn puts them (within "
                  f"{e.prior_difference_deg:.3f} deg, {e.prior_difference_mm:.2f} mm); the stickers' turn "
                  f"{turn.angle_deg:.3f} deg about ({', '.join(f'{v:.5f}' for v in turn.axis_direction)}) through "
                  f"({', '.join(f'{v:.2f}' for v in turn.axis_point_mm)}) mm")
    weak = report.registration.pairs_below_min_common
    if weak:
        print("  pass pairs with fewer common targets than needed: "
              + ", ".join(f"{w.a}|{w.b} ({w.common_targets})" for w in weak))
    residual = refined.get("target_residual_median_mm")
    print(f"mesh: {mesh['vertices']:,} vertices, {mesh['triangles']:,} triangles, "
          f"{'watertight' if mesh['watertight'] else 'NOT watertight'}"
          + (f"; target residual median {residual * 1000:.0f} um, max {refined['target_residual_max_mm'] * 1000:.0f} um"
             if residual is not None else ""))
    weld = report.weld
    if weld.measured and weld.verdict not in ("pass", "fail"):  # no rule, no weld found, a line without sections
        print(f"weld: {weld.sections_measured} of {weld.sections} sections measured; {weld.verdict}")
    elif weld.measured:
        failing = weld.failing_sections
        print(f"weld: {weld.sections_measured} of {weld.sections} sections measured, {weld.verdict} against "
              f"the acceptance limits" + (f" ({len(failing)} findings in {weld.failing} sections: report.json, "
                                          f"'weld')" if failing else "")
              + (f"; {weld.sections_uncertain} sections uncertain (a figure within its 1-sigma of a limit)"
                 if weld.sections_uncertain else ""))
    else:
        print(f"weld: not measured: {weld.why_not}")
    volume = report.volume_mesh
    if volume.made:
        solid, quality = volume.solid, volume.quality
        print(f"FE model: {solid.tetrahedra:,} tetrahedra, one solid, volume {100 * solid.volume_difference:+.2f} % "
              f"of the mesh's; worst element: dihedral {quality.min_dihedral_deg.worst:.1f} deg, "
              f"aspect ratio {quality.aspect_ratio.worst:.1f}")
    else:
        print(f"FE model: not made: {volume.why}")
    stress = report.stress
    if stress.made and stress.hot_spot is not None:
        hot, c = stress.hot_spot, stress.convergence
        print(f"stress: hot spot at the {hot.line} weld's {hot.side} toe, {hot.position_mm:g} mm along it, stress "
              f"concentration {hot.factor:.2f} under axial tension ({stress.sections} sections"
              + (f"; {100 * c.change:+.1f} % with half-size elements" if c is not None else "")
              + ("; not checked with half-size elements" if stress.convergence_refused else "") + ")")
        if stress.notch_hot_spots:
            notch = max(stress.notch_hot_spots, key=lambda h: h.factor)
            print(f"stress: notch stress (IIW, r = {stress.notch_radius_mm:g} mm) highest at the {notch.line} weld's "
                  f"{notch.side} toe, {notch.position_mm:g} mm along it, factor {notch.factor:.2f}")
        if stress.fatigue:
            life = min(stress.fatigue, key=lambda f: f.cycles)
            print(f"fatigue: {life.cycles:.3g} cycles at the {life.line} weld's {life.side} toe "
                  f"(notch stress range {life.notch_range_mpa:.0f} MPa, FAT {life.fat_mpa:g})")
        drawn = stress.drawn
        if drawn is not None and drawn.made:
            worst = max((t for t in drawn.toes if t.factor is not None), key=lambda t: t.factor, default=None)
            if worst is not None:
                print(f"stress: the drawn weld (toes r = {drawn.notch_radius_mm:g} mm) {worst.factor:.2f} at most")
        if stress.toes_finer_than_points:
            print(f"stress: {stress.toes_finer_than_points} toe(s) measured finer than the points' spacing "
                  f"({stress.point_spacing_mm:g} mm): their factors are lower bounds")
    elif not stress.made:
        print(f"stress: not computed: {stress.why}")
    for item in run.outputs.values():
        print(f"  {item['path']}")
    if "report.html" in run.outputs:
        print(f"QA report: {run.outputs['report.html']['path']} (one file, opens offline in a browser)")
    head = run.trail_head  # the anchor: keep it outside the run folder; `audit verify --head` checks the trail still holds it
    print(f"audit trail head: seq {head.seq} sha256 {head.hash} (weldrecon audit verify {out} --head {head.hash})")
    checks = report.checks
    flagged = [c for c in checks if c.result != "ok"]
    print(f"checks: {len(checks) - len(flagged)} of {len(checks)} ok (report.json, 'checks')")
    for c in flagged:
        print(f"weldrecon reconstruct: warning: pass {c.pass_}: {c.check}: {c.what}", file=sys.stderr)


def print_stopped_run(run, out: Path, stop_after: str) -> None:
    """One line for a run stopped after stage ``stop_after`` (``--stop-after``): the stages it ran
    and their time; nothing was published in ``out``."""
    print(f"stopped after stage {stop_after}: " + ", ".join(f"{n} ({'cached' if run.cached[n] else f'{run.seconds[n]:.1f} s'})"
                                                      for n in run.refs) + f"; nothing published in {out}")
