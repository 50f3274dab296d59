"""The stress concentration along the measured toes, on a finished run's FE model and on the
simulator's true surface through the same meshing and solver: the probe behind issue 26's first
figures, until the ``stress`` stage does this in the pipeline.

    .venv/bin/python bench/stress_probe.py RUN_FOLDER SAMPLE_FOLDER [--strip-mm 12] [--config deploy/configs/ci.yaml]

RUN_FOLDER: a finished ``weldrecon reconstruct`` run of a simulated dog-bone sample (its stages);
SAMPLE_FOLDER: the sample, its ``truth/`` included. Both models are put in the true specimen
frame by the stickers (``simulator.evaluate.fit_gauge``, as the accuracy tests do), held and
pulled (0.05 mm along x) on two cross-section slabs 15 mm inside the drawing's ends (inside the
measured length: the Poisson end caps carry no load), solved by CalculiX on linear tetrahedra
(C3D4, the whole model), then again on quadratic tetrahedra (C3D10: the same elements with their
mid-side nodes) over the strip |x| < ``--strip-mm`` driven at its cut by the whole model's
displacements (a sub-model). Along each measured toe, in 2 mm sections, the largest maximum
principal stress of the surface nodes within 0.75 mm over the nominal stress (the reaction over
the gauge section's drawn area): ``tasks.concentration``. Prints both models' factors and their
differences; writes nothing."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

import tasks  # noqa: F401  (pymeshlab first: tasks/__init__.py)
from accuracy import stage_folder
from data_catalog.manifests import load_manifest
from flows.stages.outputs import REFINED, WELD_TOES
from flows.stages.placement import model_weld_zone
from schemas.reconstruction import ReconstructionConfig
from simulator.evaluate import fit_gauge
from tasks.concentration import concentration_along
from tasks.fe_solve import DisplacementCase, solve_static
from tasks.frames import apply, invert
from tasks.mesh import simplify_surface
from tasks.volume_mesh import boundary_faces, face_nodes, tetrahedralize

ROOT = Path(__file__).resolve().parents[1]
_EDGES = [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]  # C3D10's mid-side nodes 5..10, Abaqus order


def _boundary(tets: np.ndarray) -> np.ndarray:
    """(f, 3) the nodes of the faces only one of ``tets`` has, each row sorted."""
    return np.sort(face_nodes(tets, *boundary_faces(tets)), axis=1)


def _factors(points, stress, toes, nominal, nodes) -> list[dict]:
    lines = {f"toe{k}": t for k, t in enumerate(toes)}
    out = []
    for c in concentration_along(points, stress, lines, nominal_mpa=nominal, reach_mm=0.75, step_mm=2.0, nodes=nodes):
        hot = c.hot_spot
        out.append({"line": c.line, "factors": np.array([s.factor for s in c.sections]), "hot": hot.factor,
                    "at": np.array(hot.at_mm)})
    return out


def _solve(points: np.ndarray, tets: np.ndarray, spec, toes: list[np.ndarray], strip_mm: float):
    """(C3D4 whole-model factors, C3D10 strip factors, figures) of one model in the specimen frame."""
    half = spec.length_mm / 2
    x = points[:, 0]
    held = np.flatnonzero(np.abs(x - (-half + 15)) < 0.75)
    pulled = np.flatnonzero(np.abs(x - (half - 15)) < 0.75)
    a, b = held[np.argmin(points[held, 1])], held[np.argmax(points[held, 1])]
    case = DisplacementCase(node_sets={"HELD": held, "PULLED": pulled, "A": np.array([a]), "B": np.array([b])},
                            prescribed={"HELD": {1: 0.0}, "PULLED": {1: 0.05}, "A": {2: 0.0, 3: 0.0}, "B": {3: 0.0}})
    t0 = time.perf_counter()
    whole = solve_static(points, tets, case, timeout_s=1800)
    figures = {"nodes": len(points), "tetrahedra": len(tets), "solve_s": time.perf_counter() - t0}
    force = whole.reaction_n["PULLED"][0]
    figures["balance"] = float((force + whole.reaction_n["HELD"][0]) / force)
    nominal = force / (spec.gauge_width_mm * spec.thickness_mm)
    outside = _boundary(tets)
    surface = np.unique(outside)
    linear = _factors(points, whole.stress_mpa, toes, nominal, surface)
    # the strip, quadratic, driven at its cut by the whole model's displacements: the cut is the
    # strip's boundary that is not the model's
    inside = np.abs(points[tets].mean(axis=1)[:, 0]) < strip_mm
    strip_faces = _boundary(tets[inside])
    rows = np.dtype((np.void, strip_faces.dtype.itemsize * 3))
    on_surface = np.isin(np.ascontiguousarray(strip_faces).view(rows), np.ascontiguousarray(outside).view(rows))
    cut = np.unique(strip_faces[~on_surface.ravel()])
    used = np.unique(tets[inside])
    index = np.full(len(points), -1, np.int64)
    index[used] = np.arange(len(used))
    corner = index[tets[inside]]
    edges, mid = np.unique(np.sort(corner[:, _EDGES].reshape(-1, 2), axis=1), axis=0, return_inverse=True)
    sub_points = np.vstack([points[used], (points[used][edges[:, 0]] + points[used][edges[:, 1]]) / 2])
    sub_tets = np.c_[corner, len(used) + mid.reshape(-1, 6)]
    u = whole.displacement_mm[used]
    u = np.vstack([u, (u[edges[:, 0]] + u[edges[:, 1]]) / 2])  # linear along each edge, as the C3D4 field
    on_cut = np.zeros(len(sub_points), bool)
    on_cut[index[cut]] = True
    on_cut[len(used):] = on_cut[edges[:, 0]] & on_cut[edges[:, 1]]
    driven = np.flatnonzero(on_cut)
    sub_case = DisplacementCase(node_sets={f"C{k}": np.array([n]) for k, n in enumerate(driven)},
                                prescribed={f"C{k}": {1: float(u[n, 0]), 2: float(u[n, 1]), 3: float(u[n, 2])}
                                            for k, n in enumerate(driven)})
    t0 = time.perf_counter()
    strip = solve_static(sub_points, sub_tets, sub_case, timeout_s=3600)
    figures.update(strip_nodes=len(sub_points), strip_tetrahedra=len(sub_tets), strip_solve_s=time.perf_counter() - t0)
    corner_surface = np.setdiff1d(index[surface[index[surface] >= 0]], index[cut])
    is_surface = np.zeros(len(sub_points), bool)
    is_surface[corner_surface] = True
    sub_surface = np.r_[corner_surface, len(used) + np.flatnonzero(is_surface[edges[:, 0]] & is_surface[edges[:, 1]])]
    quadratic = _factors(sub_points, strip.stress_mpa, toes, nominal, sub_surface)
    return linear, quadratic, figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--strip-mm", type=float, default=12.0)
    parser.add_argument("--config", type=Path, default=ROOT / "deploy" / "configs" / "ci.yaml")
    args = parser.parse_args()
    manifest = load_manifest(args.sample / "manifest.json")
    spec = manifest.specimen
    refined = REFINED.read(stage_folder(args.run, "refine"))
    positions = refined.track_positions_mm
    T_common_specimen = fit_gauge(args.sample, positions[refined.specimen_track], positions).T_recon_specimen
    S = invert(T_common_specimen)
    toes = [apply(S, t) for t in WELD_TOES.read(stage_folder(args.run, "weld")).polylines()]
    config = ReconstructionConfig.model_validate(yaml.safe_load(args.config.read_text()) or {})

    import meshio
    import open3d as o3d

    model = meshio.read(stage_folder(args.run, "volume").file("model.vtu"))
    # the linear elements: the corners of the stage's C3D10 (volume.element_order 2), its edge nodes left out
    cells = model.cells_dict
    corners = (cells["tetra10"][:, :4] if "tetra10" in cells else cells["tetra"]).astype(np.int64)
    used = np.unique(corners)
    renumber = np.full(len(model.points), -1, np.int64)
    renumber[used] = np.arange(len(used))
    rec = apply(S, model.points[used].astype(np.float64)), renumber[corners]
    truth = o3d.io.read_triangle_mesh(str(args.sample / "truth" / "specimen.ply"))
    v, f = simplify_surface(np.asarray(truth.vertices, np.float64), np.asarray(truth.triangles, np.int64),
                            max_triangles=config.volume.max_surface_triangles)
    zone = model_weld_zone(manifest, refined.T_common_pass, config)  # the reconstruction's zone, specimen frame
    s = config.volume
    solid = tetrahedralize(v, f, weld_lines_mm=[apply(S, np.asarray(z.points_mm)) for z in zone.zones],
                           size_mm=s.size_mm, weld_size_mm=s.weld_size_mm, weld_zone_mm=s.weld_zone_mm, growth=s.growth,
                           feature_angle_deg=s.feature_angle_deg, optimize=s.optimize, toe_lines_mm=toes,
                           toe_size_mm=s.toe_size_mm, toe_zone_mm=s.toe_zone_mm, timeout_s=s.timeout_s,
                           keep_surface_after_timeout=s.keep_surface_after_timeout)
    results = {name: _solve(points, tets, spec, toes, args.strip_mm)
               for name, (points, tets) in (("reconstruction", rec), ("truth", (solid.points, solid.tetrahedra)))}
    for name, (_, _, figures) in results.items():
        print(name, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in figures.items()})
    for order, label in ((0, "C3D4, whole model"), (1, f"C3D10, strip |x| < {args.strip_mm:g} mm")):
        print(f"-- {label}: reconstruction against truth")
        for r, t in zip(results["reconstruction"][order], results["truth"][order]):
            d = np.abs(r["factors"] - t["factors"]) / t["factors"]
            print(f"{r['line']}: median {np.nanmedian(r['factors']):.3f} vs {np.nanmedian(t['factors']):.3f}, "
                  f"per section |diff| median {100 * np.nanmedian(d):.1f} % worst {100 * np.nanmax(d):.1f} %; "
                  f"hot spot {r['hot']:.3f} vs {t['hot']:.3f} ({100 * (r['hot'] / t['hot'] - 1):+.1f} %), "
                  f"{np.linalg.norm(r['at'] - t['at']):.1f} mm apart")


if __name__ == "__main__":
    main()
