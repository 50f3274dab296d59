"""Screened Poisson side by side (issue 29): the mesh stage's MeshLab solve on one thread against
MeshLab's own threads, Kazhdan's PoissonRecon (``pypoisson2``) and Adobe Lagrange's
``mesh_from_oriented_points``, on the same points and normals, in one process.

    .venv/bin/python bench/bench_poisson_peers.py SAMPLE_DIR RUN_DIR \\
        [--libs /tmp/poisson-libs/pypoisson2 /tmp/poisson-libs/lagrange] [--repeats 2] [--json OUT.json]

RUN_DIR is a reconstruction of SAMPLE_DIR run at least up to stage ``mesh`` (``--stop-after mesh``
will do: the settings come from ``results/config.json`` or else from the mesh stage's record);
every contender gets its segment stage's ``specimen.zarr`` (points, normals) and the run's depth;
the other settings as far as each API allows:

- ``meshlab-1t``: ``tasks.mesh.screened_poisson`` as the mesh stage calls it (MeshLab, one
  OpenMP thread, output in canonical order): the reference of every ratio;
- ``meshlab-default``: the same MeshLab filter with its default ``threads``;
- ``pypoisson2-1t`` / ``pypoisson2-2t``: PoissonRecon 18.74 through ``pypoisson2`` (ctypes),
  degree 2 and Neumann boundary like MeshLab's filter, the same depth, samples per node, point
  weight and scale; serial (``ParallelType.NONE``) and OpenMP on the machine's cores (its
  thread pool takes ``hardware_concurrency()``; the binding has no thread count);
- ``pypoisson2-static-2t`` (with ``--pypoisson2-static-lib``): the same on 2 threads with a
  ``libpypoisson_std.so`` built from the same sdist with one line changed in
  ``PoissonRecon/Src/MultiThreading.h`` (``ThreadPool::Schedule`` ``DYNAMIC`` -> ``STATIC``), an
  attempt at a deterministic multi-threaded solve;
- ``lagrange``: ``lagrange.poisson.mesh_from_oriented_points`` (PoissonRecon inside, float,
  degree 1, TBB on all cores): depth, samples per node and point weight (``interpolation_weight``);
  its API has no scale (PoissonRecon's 1.1), no degree and no thread count.

The peers' outputs get what the mesh stage does to MeshLab's (unused vertices dropped, canonical
order: ``tasks.mesh``), inside their timing, so that every contender delivers the same kind of
mesh. Each contender runs ``--repeats`` times, round-robin (all contenders, then all again), so
that a slow spell of the machine spreads over them; "same bytes" compares the SHA-256 of the
vertices (float64) and triangles (int64) of every repeat, in canonical order and as the library
returned them (raw). Accuracy: ``bench/accuracy.py``'s ``mesh_to_truth`` (within 15 mm of the
weld, and over the scanned length). Candidates live outside the project's environment: ``--libs``
puts folders (``pip install --target``) on ``sys.path``; a contender whose library does not
import is reported, not run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
import traceback
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONTENDERS = ("meshlab-1t", "meshlab-default", "pypoisson2-1t", "pypoisson2-2t", "pypoisson2-static-2t", "lagrange")
REFERENCE = "meshlab-1t"


def digest(vertices: np.ndarray, triangles: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(triangles, np.int64).tobytes())
    return h.hexdigest()


def canonical(vertices, triangles):
    """The mesh stage's post-processing of MeshLab's output: unused vertices dropped, canonical order."""
    from tasks.mesh import _canonical_order, _drop_unused_vertices

    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles).astype(np.int64)
    v, t, _ = _canonical_order(*_drop_unused_vertices(v, t, np.zeros(len(v))))
    return v, t


def make_solvers(points, normals, s, libs_error: dict, static_lib: Path | None = None):
    """name -> callable() returning (raw_vertices, raw_triangles, canonical_vertices, canonical_triangles)."""
    import pymeshlab

    from tasks.mesh import screened_poisson

    solvers = {}

    def meshlab_1t():
        r = screened_poisson(points, normals, depth=s.poisson_depth, samples_per_node=s.samples_per_node,
                             point_weight=s.point_weight, scale=s.poisson_scale)
        return r.vertices, r.triangles, r.vertices, r.triangles  # already canonical (the stage's output)

    def meshlab_default():
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points),
                                   v_normals_matrix=np.ascontiguousarray(normals)))
        ms.generate_surface_reconstruction_screened_poisson(
            depth=s.poisson_depth, samplespernode=float(s.samples_per_node), pointweight=float(s.point_weight),
            scale=float(s.poisson_scale), preclean=False, confidence=False)  # threads: MeshLab's default
        m = ms.current_mesh()
        v = np.array(m.vertex_matrix(), dtype=np.float64)
        t = np.array(m.face_matrix(), dtype=np.int64)
        del m, ms
        return (v, t, *canonical(v, t))

    solvers["meshlab-1t"] = meshlab_1t
    solvers["meshlab-default"] = meshlab_default

    try:
        import poisson as pypoisson2  # the pypoisson2 distribution's package
        if not hasattr(pypoisson2, "poisson_reconstruction"):
            raise ImportError(f"module 'poisson' at {getattr(pypoisson2, '__file__', '?')} is not pypoisson2")
    except Exception as error:  # noqa: BLE001 (reported in the table)
        libs_error["pypoisson2-1t"] = libs_error["pypoisson2-2t"] = f"{type(error).__name__}: {error}"
    else:
        def pypoisson2_run(parallel_type):
            def run():
                v, t = pypoisson2.poisson_reconstruction(
                    points, normals, depth=int(s.poisson_depth), full_depth=5, scale=float(s.poisson_scale),
                    samples_per_node=float(s.samples_per_node), point_weight=float(s.point_weight), iters=8,
                    degree=2, boundary="neumann", parallel_type=parallel_type)
                v = np.array(v, dtype=np.float64)
                t = np.array(t, dtype=np.int64)
                return (v, t, *canonical(v, t))
            return run

        solvers["pypoisson2-1t"] = pypoisson2_run(pypoisson2.ParallelType.NONE)
        solvers["pypoisson2-2t"] = pypoisson2_run(pypoisson2.ParallelType.OPEN_MP)
        if static_lib is None:
            libs_error["pypoisson2-static-2t"] = "no --pypoisson2-static-lib given"
        else:
            # the same binding driving a libpypoisson_std.so built with PoissonRecon's thread pool on
            # its STATIC schedule (chunk c always on thread c mod threads) instead of DYNAMIC
            import ctypes

            from poisson import api as pypoisson2_api, core as pypoisson2_core

            manager = pypoisson2_core.PoissonLibrary()
            library = ctypes.CDLL(str(static_lib))  # RTLD_LOCAL: its own thread pool settings
            manager._setup_signatures(library, np.int32)
            manager._lib_std = library
            plain = pypoisson2_run(pypoisson2.ParallelType.OPEN_MP)

            def static_run():
                if pypoisson2_core.PoissonLibrary._estimate_max_nodes(len(points), int(s.poisson_depth)) > 0.8 * 2**31:
                    raise RuntimeError("needs the int64 library; only the int32 one was built with the static schedule")
                before = pypoisson2_api._library_manager
                pypoisson2_api._library_manager = manager
                try:
                    return plain()
                finally:
                    pypoisson2_api._library_manager = before

            solvers["pypoisson2-static-2t"] = static_run

    try:
        import lagrange
        lagrange.poisson.mesh_from_oriented_points  # noqa: B018  (fails here when absent)
    except Exception as error:  # noqa: BLE001
        libs_error["lagrange"] = f"{type(error).__name__}: {error}"
    else:
        def lagrange_run():
            mesh = lagrange.poisson.mesh_from_oriented_points(
                np.ascontiguousarray(points, np.float64), np.ascontiguousarray(normals, np.float64),
                octree_depth=int(s.poisson_depth), samples_per_node=float(s.samples_per_node),
                interpolation_weight=float(s.point_weight))
            v = np.array(mesh.vertices, dtype=np.float64)
            t = np.array(mesh.facets, dtype=np.int64)
            del mesh
            return (v, t, *canonical(v, t))

        solvers["lagrange"] = lagrange_run
    return solvers


def mesh_settings(run: Path) -> SimpleNamespace:
    """The mesh stage's settings: ``results/config.json`` of a finished run, else the parameters the
    mesh stage's record holds (a run stopped after ``mesh`` publishes no results)."""
    from bench.accuracy import latest_stage
    from flows.reconstruct import load_config

    config = run / "results" / "config.json"
    if config.is_file():
        m = load_config(config).mesh
        return SimpleNamespace(poisson_depth=m.poisson_depth, samples_per_node=m.samples_per_node,
                               point_weight=m.point_weight, poisson_scale=m.poisson_scale)
    p = json.loads((latest_stage(run, "mesh") / "record.json").read_text())["parameters"]
    return SimpleNamespace(**{k: p[k] for k in ("poisson_depth", "samples_per_node", "point_weight", "poisson_scale")})


def fmt_acc(a: dict) -> str:
    return f"{a['median_um']} / {a['rms_um']} / {a['p95_um']}"


def table(result: dict) -> str:
    ref = result["contenders"].get(REFERENCE, {})
    ref_s = ref.get("best_s")
    lines = ["| solver | threads | seconds (each run) | / MeshLab 1 thread | vertices | faces | watertight | "
             "within 15 mm of the weld: median / RMS / 95 % (um) | scanned length: median / RMS / 95 % (um) | "
             "same bytes (canonical / raw) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in result["contenders"].items():
        if "error" in c:
            lines.append(f"| {name} | {c.get('threads', '')} | not run: {c['error']} | | | | | | | |")
            continue
        ratio = f"{c['best_s'] / ref_s:.2f}" if ref_s else ""
        secs = " / ".join(f"{x:.1f}" for x in c["seconds"])
        yes = {True: "yes", False: "NO", None: "one run"}
        same = f"{yes[c['same_bytes_canonical']]} / {yes[c['same_bytes_raw']]}"
        lines.append(f"| {name} | {c['threads']} | {secs} | {ratio} | {c['vertices']:,} | {c['faces']:,} | "
                     f"{'yes' if c['watertight'] else 'no'} | {fmt_acc(c['within 15 mm of the weld'])} | "
                     f"{fmt_acc(c['scanned length'])} | {same} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--libs", nargs="*", default=[], type=Path,
                        help="folders (pip install --target) to put on sys.path for the candidates")
    parser.add_argument("--pypoisson2-static-lib", type=Path,
                        help="a libpypoisson_std.so built with ThreadPool::Schedule = STATIC (contender "
                             "pypoisson2-static-2t; see bench/README.md)")
    parser.add_argument("--only", nargs="*", choices=CONTENDERS, help="run these contenders only")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    for lib in reversed(args.libs):
        if not lib.is_dir():
            raise SystemExit(f"--libs: {lib} is not a folder")
        sys.path.insert(0, str(lib.resolve()))

    try:  # before pymeshlab: its libtbb.so.12 is older than Lagrange's, and the first one loaded serves both
        import lagrange  # noqa: F401  (lagrange.poisson is an attribute, not an importable submodule)
    except Exception:  # noqa: BLE001  (reported by make_solvers)
        pass
    import pymeshlab  # noqa: F401  (before Open3D: beside Open3D it must load first)

    from bench.accuracy import latest_stage, mesh_to_truth
    from data_catalog.stages import load_arrays
    from tasks.mesh import mesh_report

    s = mesh_settings(args.run)
    specimen = load_arrays(latest_stage(args.run, "segment") / "specimen.zarr", "points", "normals")
    points = np.ascontiguousarray(specimen["points"], np.float64)
    normals = np.ascontiguousarray(specimen["normals"], np.float64)
    del specimen

    libs_error: dict = {}
    solvers = make_solvers(points, normals, s, libs_error, args.pypoisson2_static_lib)
    names = [n for n in CONTENDERS if not args.only or n in args.only]
    threads = {"meshlab-1t": "1", "meshlab-default": "MeshLab default (2)", "pypoisson2-1t": "1",
               "pypoisson2-2t": "2 (OpenMP, hardware_concurrency)", "pypoisson2-static-2t": "2 (OpenMP, static schedule)", "lagrange": "TBB default (all cores)"}
    result: dict = {
        "sample": str(args.sample), "run": str(args.run), "points": int(len(points)),
        "settings": {"depth": s.poisson_depth, "samples_per_node": s.samples_per_node,
                     "point_weight": s.point_weight, "scale": s.poisson_scale},
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "machine": platform.platform(),
        "repeats": args.repeats, "contenders": {}}
    runs: dict = {n: [] for n in names}
    for n in names:
        result["contenders"][n] = {"threads": threads[n]}
        if n in libs_error:
            result["contenders"][n]["error"] = libs_error[n]
    for round_ in range(args.repeats):
        for n in names:
            c = result["contenders"][n]
            if "error" in c:
                continue
            print(f"[round {round_ + 1}] {n} ...", file=sys.stderr, flush=True)
            t0 = time.perf_counter()
            try:
                raw_v, raw_t, v, t = solvers[n]()
            except Exception as error:  # noqa: BLE001
                c["error"] = f"{type(error).__name__}: {error}"
                traceback.print_exc()
                continue
            seconds = time.perf_counter() - t0
            print(f"[round {round_ + 1}] {n}: {seconds:.1f} s, {len(v)} vertices", file=sys.stderr, flush=True)
            runs[n].append({"seconds": seconds, "canonical": digest(v, t), "raw": digest(raw_v, raw_t)})
            if round_ == 0:  # measure the first run's mesh (the repeats are compared by hash)
                report = mesh_report(v, t)
                accuracy = mesh_to_truth(args.sample, args.run, v)
                c.update({"vertices": report.n_vertices, "faces": report.n_triangles,
                          "watertight": report.watertight, "boundary_edges": report.n_boundary_edges,
                          "non_manifold_edges": report.n_non_manifold_edges,
                          "within 15 mm of the weld": accuracy["within 15 mm of the weld"],
                          "scanned length": accuracy["scanned length"]})
                if n == REFERENCE:
                    stage = load_arrays(latest_stage(args.run, "mesh") / "mesh.zarr", "vertices", "triangles")
                    c["same_bytes_as_the_runs_mesh_stage"] = digest(stage["vertices"], stage["triangles"]) == runs[n][0]["canonical"]
                    del stage
                elif REFERENCE in runs and runs[REFERENCE]:
                    c["same_canonical_bytes_as_meshlab_1t"] = runs[n][0]["canonical"] == runs[REFERENCE][0]["canonical"]
            del raw_v, raw_t, v, t
    for n in names:
        c = result["contenders"][n]
        if "error" in c or not runs[n]:
            continue
        c["seconds"] = [round(r["seconds"], 2) for r in runs[n]]
        c["best_s"] = round(min(r["seconds"] for r in runs[n]), 2)
        c["same_bytes_canonical"] = len({r["canonical"] for r in runs[n]}) == 1 if len(runs[n]) > 1 else None
        c["same_bytes_raw"] = len({r["raw"] for r in runs[n]}) == 1 if len(runs[n]) > 1 else None
        c["sha256_canonical"] = [r["canonical"][:16] for r in runs[n]]
    ref_s = result["contenders"].get(REFERENCE, {}).get("best_s")
    for n in names:
        c = result["contenders"][n]
        if ref_s and "best_s" in c:
            c["over_meshlab_1t"] = round(c["best_s"] / ref_s, 2)
    print(json.dumps(result, indent=1))
    print()
    print(f"{result['points']:,} points, depth {s.poisson_depth}, samples per node {s.samples_per_node}, "
          f"point weight {s.point_weight}, scale {s.poisson_scale}; {args.repeats} runs each, round-robin; "
          f"ratio: the best run over MeshLab 1 thread's best")
    print()
    print(table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
