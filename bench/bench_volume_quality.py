"""The FE model's element quality, mesher against mesher, on a finished run's surface.

    python bench/bench_volume_quality.py RUN_FOLDER [--config deploy/configs/ci.yaml] [--variants ...]

Reads the run's Poisson surface (stage ``mesh``) and the measured toes (stage ``weld``; the toes
stand in for the weld lines too: no manifest needed), simplifies the surface as the stage does
(``volume.max_surface_triangles``) and fills it with each variant, printing per variant: seconds,
tetrahedra, worst / 1st percentile smallest dihedral angle, worst aspect ratio, elements under
10 deg and over aspect ratio 10, and the volume against the surface's. Variants:

- ``hxt``: gmsh HXT and gmsh's optimiser, as the stage made it before the sliver repair
- ``hxt-netgen``: the same, then Netgen's optimiser (``volume.optimize``)
- ``hxt-repair``: ``hxt`` then ``tasks.sliver_repair`` (the stage now)
- ``tetgen``: TetGen (``pip install tetgen``) on the surface gmsh remeshed in ``hxt``, boundary kept
  (``-pYq1.5/10``: radius-edge 1.5, smallest dihedral 10 deg); its seconds are TetGen's alone
- ``mmg``: MMG3D (``pip install mmgpy``) ``-optim -hausd 0.01`` on ``hxt``'s elements; seconds MMG's alone

A run folder with an audit trail reads the stage folders it names last; without one (a copy of
``stages/mesh`` and ``stages/weld``), the one folder of each stage.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from accuracy import StageFolder, latest_stage  # noqa: E402
from flows.stages.outputs import MESH, WELD_TOES  # noqa: E402
from schemas.reconstruction import ReconstructionConfig  # noqa: E402
from tasks.mesh import mesh_report, simplify_surface  # noqa: E402
from tasks.volume_mesh import element_quality, orient_tetrahedra, signed_volumes, tetrahedralize  # noqa: E402

VARIANTS = ("hxt", "hxt-netgen", "hxt-repair", "tetgen", "mmg")


def _stage(run: Path, stage: str) -> StageFolder:
    if (run / "audit").exists():
        return StageFolder(latest_stage(run, stage))
    folders = sorted((run / "stages" / stage).iterdir()) if (run / "stages").exists() else sorted((run / stage).iterdir())
    return StageFolder(folders[-1])


def _figures(name: str, seconds: float, points: np.ndarray, tets: np.ndarray, surface_volume: float) -> dict:
    tets = orient_tetrahedra(points, tets)
    dihedral, aspect = element_quality(points, tets)
    return {"variant": name, "seconds": round(seconds, 1), "tetrahedra": len(tets),
            "worst_deg": round(float(dihedral.min()), 2), "p1_deg": round(float(np.percentile(dihedral, 1)), 2),
            "worst_aspect": round(float(aspect.max()), 1), "under_10_deg": int(np.count_nonzero(dihedral < 10)),
            "over_aspect_10": int(np.count_nonzero(aspect > 10)),
            "volume_vs_surface_pct": round(float(100 * (signed_volumes(points, tets).sum() / surface_volume - 1)), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--config", type=Path, help="the run's settings (default: the defaults, as the demo)")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    args = parser.parse_args()
    config = ReconstructionConfig.model_validate(yaml.safe_load(args.config.read_text()) or {} if args.config else {})
    s = config.volume
    surface = MESH.read(_stage(args.run, "mesh"))
    toes = WELD_TOES.read(_stage(args.run, "weld")).polylines()
    vertices, triangles = simplify_surface(surface.vertices, surface.triangles, max_triangles=s.max_surface_triangles)
    surface_volume = mesh_report(vertices, triangles).volume_mm3
    print(f"# {args.run}: {len(triangles):,} triangles, {surface_volume:,.0f} mm3, {len(toes)} toe lines", flush=True)
    sizes = dict(weld_lines_mm=toes, size_mm=s.size_mm, weld_size_mm=s.weld_size_mm, weld_zone_mm=s.weld_zone_mm,
                 growth=s.growth, feature_angle_deg=s.feature_angle_deg, toe_lines_mm=toes, toe_size_mm=s.toe_size_mm,
                 toe_zone_mm=s.toe_zone_mm, timeout_s=s.timeout_s,
                 keep_surface_after_timeout=s.keep_surface_after_timeout)
    off = dict(min_dihedral_deg=0.0, max_aspect_ratio=np.inf)  # no sliver repair
    plain = None
    for name in args.variants:
        t0 = time.perf_counter()
        if name in ("hxt", "hxt-netgen", "hxt-repair"):
            solid = tetrahedralize(vertices, triangles, optimize=name == "hxt-netgen",
                                   **sizes, **(off if name != "hxt-repair" else {}))
            points, tets = solid.points, solid.tetrahedra
            if name == "hxt":
                plain = solid
        else:
            if plain is None:
                plain = tetrahedralize(vertices, triangles, optimize=False, **sizes, **off)
                t0 = time.perf_counter()
            if name == "tetgen":
                import tetgen

                boundary = plain.boundary_triangles()
                used = np.unique(boundary)
                index = np.full(len(plain.points), -1, np.int64)
                index[used] = np.arange(len(used))
                t0 = time.perf_counter()
                points, tets, *_ = tetgen.TetGen(plain.points[used], index[boundary].astype(np.int32)).tetrahedralize(
                    switches="pYq1.5/10Q")
            else:  # mmg
                import mmgpy

                mesh = mmgpy.MmgMesh3D(plain.points, plain.tetrahedra.astype(np.int32))
                mesh.remesh(optim=True, hausd=0.01, verbose=-1)
                points, tets = mesh.get_vertices(), mesh.get_tetrahedra()
        seconds = time.perf_counter() - t0
        print(_figures(name, seconds, np.asarray(points, np.float64), np.asarray(tets, np.int64), surface_volume),
              flush=True)


if __name__ == "__main__":
    main()
