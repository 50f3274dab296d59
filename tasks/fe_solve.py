"""A linear static solve of a tetrahedral FE model by CalculiX (``ccx``, Debian's ``calculix-ccx``).

The model goes in as arrays (nodes in mm, C3D4 or C3D10 tetrahedra in Abaqus node order, named
node sets), the load case as prescribed displacements on node sets (one value for a set, or one
per node of it), one isotropic linear elastic material (N, mm, MPa); CalculiX runs in a child process of its own in a scratch folder, one
thread (the same model, the same numbers), killed past ``timeout_s`` of CPU time
(``tasks.volume_mesh.run_limited``) and when this process dies.
Out come the displacements, the stresses extrapolated to the nodes and averaged (CalculiX's
``*NODE FILE`` S, the ``.frd`` file) and the reaction force summed over each constrained set
(``*NODE PRINT`` RF totals, the ``.dat`` file), node by node as well for the sets asked for.

A missing ``ccx`` raises CalculixNotFound; a model CalculiX refuses, or a run that ends without
results, raises FESolveError with CalculiX's own last words.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tasks.arrays import distinct
from tasks.volume_mesh import ONE_THREAD_ENV, run_limited

__all__ = ["CalculixNotFound", "FESolveError", "FESolveTimeout", "Material", "DisplacementCase", "FESolution", "solve_static",
           "max_principal", "GMSH_TO_ABAQUS_TET10"]

# gmsh's 10-node tetrahedron numbers its edge nodes (0-1, 1-2, 2-0, 3-0, 3-2, 3-1); Abaqus's C3D10
# (0-1, 1-2, 2-0, 0-3, 1-3, 2-3): the last two swap
GMSH_TO_ABAQUS_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])

_ONE_THREAD = {**ONE_THREAD_ENV, "CCX_NPROC_EQUATION_SOLVER": "1", "CCX_NPROC_RESULTS": "1", "CCX_NPROC_STIFFNESS": "1"}


class CalculixNotFound(RuntimeError):
    """No CalculiX on this machine."""


class FESolveError(RuntimeError):
    """CalculiX refused the model or ended without results."""


class FESolveTimeout(FESolveError):
    """CalculiX did not finish within the CPU time it was given (its process killed)."""


@dataclass(frozen=True)
class Material:
    """Isotropic linear elastic: Young's modulus (MPa) and Poisson's ratio; structural steel by default."""

    youngs_modulus_mpa: float = 210_000.0
    poisson_ratio: float = 0.3


@dataclass(frozen=True)
class DisplacementCase:
    """Node sets held or moved: ``prescribed`` set name -> {dof (1 x, 2 y, 3 z): displacement mm},
    one value for the whole set or an array of one per node of it (in the set's order: a
    ``*BOUNDARY`` line per node); ``reactions_per_node``: sets whose reactions are read node by
    node as well as summed."""

    node_sets: dict[str, np.ndarray]
    prescribed: dict[str, dict[int, float | np.ndarray]]
    reactions_per_node: tuple[str, ...] = ()


@dataclass
class FESolution:
    """Per node (in the model's node order): ``displacement_mm`` (n, 3), ``stress_mpa`` (n, 6: xx, yy,
    zz, xy, yz, zx; nodes no element uses are NaN); ``reaction_n`` set name -> (3,) summed force;
    ``node_reaction_n`` set name -> (k, 3) each node's force in the set's order (the case's
    ``reactions_per_node``)."""

    displacement_mm: np.ndarray
    stress_mpa: np.ndarray
    reaction_n: dict[str, np.ndarray] = field(default_factory=dict)
    node_reaction_n: dict[str, np.ndarray] = field(default_factory=dict)
    log: str = ""


def _ccx() -> str:
    found = shutil.which("ccx")
    if found is None:
        raise CalculixNotFound("CalculiX (ccx) is not installed: the FE solve needs it (Debian package "
                               "calculix-ccx; `make setup` installs it)")
    return found


def _element_type(nodes_per_element: int, plane: str | None) -> str:
    if plane is None:
        return {4: "C3D4", 10: "C3D10"}[nodes_per_element]
    return {"strain": "CPE6", "stress": "CPS6"}[plane]


def _write_deck(path: Path, points: np.ndarray, elements: np.ndarray, case: DisplacementCase, material: Material,
                plane: str | None = None, thickness_mm: float = 1.0):
    kind = _element_type(elements.shape[1], plane)
    with open(path, "w", encoding="ascii") as f:
        f.write("*HEADING\nweldrecon linear static solve (mm, N, MPa)\n*NODE, NSET=NALL\n")
        # formatted from Python's own numbers (tolist: the same text as numpy's scalars give, in half the time)
        f.write("".join(map("{},{:.12e},{:.12e},{:.12e}\n".format, range(1, len(points) + 1), *points.T.tolist())))
        f.write(f"*ELEMENT, TYPE={kind}, ELSET=EALL\n")
        # one line an element: its number and its 4, 6 or 10 nodes (CalculiX reads up to 16 entries a line)
        line = ",".join(["{}"] * (1 + elements.shape[1])) + "\n"
        f.write("".join(map(line.format, range(1, len(elements) + 1), *(elements + 1).T.tolist())))
        for name, nodes in case.node_sets.items():
            f.write(f"*NSET, NSET={name}\n")
            ids = np.asarray(nodes, np.int64) + 1
            f.writelines(",".join(map(str, ids[k:k + 16])) + "\n" for k in range(0, len(ids), 16))
        f.write(f"*MATERIAL, NAME=STEEL\n*ELASTIC\n{material.youngs_modulus_mpa:.6e},{material.poisson_ratio:.6f}\n"
                "*SOLID SECTION, ELSET=EALL, MATERIAL=STEEL\n" + (f"{thickness_mm:.12e}\n" if plane else "")
                + "*STEP\n*STATIC\n*BOUNDARY\n")
        for name, dofs in case.prescribed.items():
            for dof, value in sorted(dofs.items()):
                if np.ndim(value) == 0:
                    f.write(f"{name},{dof},{dof},{value:.12e}\n")
                else:
                    ids = np.asarray(case.node_sets[name], np.int64) + 1
                    f.writelines(f"{i},{dof},{dof},{v:.12e}\n" for i, v in zip(ids, np.asarray(value, np.float64)))
        f.write("*NODE FILE\nU,S\n")
        for name in case.prescribed:
            f.write(f"*NODE PRINT, NSET={name}, TOTALS={'YES' if name in case.reactions_per_node else 'ONLY'}\nRF\n")
        f.write("*END STEP\n")


def solve_static(points: np.ndarray, elements: np.ndarray, case: DisplacementCase, *,
                 material: Material = Material(), timeout_s: float = 3600.0,
                 workdir: Path | None = None, plane: str | None = None, thickness_mm: float = 1.0) -> FESolution:
    """Solve the model (see the module's description). ``workdir``: where CalculiX's files are kept
    (default: a temporary folder, removed). ``plane``: a 2-D model in the x-y plane, ``"strain"``
    (CPE6) or ``"stress"`` (CPS6) of ``thickness_mm``: ``points`` (n, 2), ``elements`` (e, 6)
    6-node triangles (corners counter-clockwise, then the edge nodes of 0-1, 1-2, 2-0); the
    displacements and reactions then have a zero third component, the stresses their
    out-of-plane ``zz`` (plane strain: Poisson's ratio times the in-plane sum)."""
    ccx = _ccx()
    points = np.asarray(points, np.float64)
    elements = np.asarray(elements, np.int64)
    if plane is not None:
        if plane not in ("strain", "stress"):
            raise ValueError(f"plane: expected 'strain' or 'stress', got {plane!r}")
        if points.ndim != 2 or points.shape[1] != 2 or elements.ndim != 2 or elements.shape[1] != 6:
            raise ValueError(f"a plane model takes (n, 2) points and (e, 6) triangles, got {points.shape} and "
                             f"{elements.shape}")
        if not thickness_mm > 0:
            raise ValueError(f"thickness_mm must be positive, got {thickness_mm}")
        points = np.c_[points, np.zeros(len(points))]
    elif elements.ndim != 2 or elements.shape[1] not in (4, 10):
        raise ValueError(f"elements: expected (e, 4) or (e, 10) node numbers, got shape {elements.shape}")
    if len(elements) and (elements.min() < 0 or elements.max() >= len(points)):
        raise ValueError(f"elements: node numbers must lie in 0..{len(points) - 1}")
    missing = sorted(set(case.prescribed) - set(case.node_sets))
    if missing:
        raise ValueError(f"prescribed displacements on node sets not given: {missing}")
    for name, dofs in case.prescribed.items():
        for dof, value in dofs.items():
            if np.ndim(value) != 0 and np.shape(value) != (len(case.node_sets[name]),):
                raise ValueError(f"set {name}, dof {dof}: expected one displacement or one per node "
                                 f"({len(case.node_sets[name])}), got shape {np.shape(value)}")
    unread = sorted(set(case.reactions_per_node) - set(case.prescribed))
    if unread:
        raise ValueError(f"reactions per node asked of sets with no prescribed displacement: {unread}")
    place = (contextlib.nullcontext(workdir) if workdir is not None
             else tempfile.TemporaryDirectory(prefix="weldrecon-ccx-"))
    with place as where:
        folder = Path(where)
        folder.mkdir(parents=True, exist_ok=True)
        _write_deck(folder / "job.inp", points, elements, case, material, plane, thickness_mm)
        log = _run(ccx, folder, timeout_s)
        displacement, stress = _read_frd(folder / "job.frd", len(points))
        reactions = _read_totals(folder / "job.dat", list(case.prescribed))
        per_node = _read_node_forces(folder / "job.dat",
                                     {name: case.node_sets[name] for name in case.reactions_per_node})
    return FESolution(displacement_mm=displacement, stress_mpa=stress, reaction_n=reactions, node_reaction_n=per_node,
                      log=log)


def _run(ccx: str, folder: Path, timeout_s: float) -> str:
    try:
        done = run_limited([ccx, "-i", "job"], cwd=folder, capture_output=True, text=True,
                           env={**os.environ, **_ONE_THREAD}, timeout_s=timeout_s)
    except subprocess.TimeoutExpired:
        raise FESolveTimeout(f"CalculiX did not finish within {timeout_s:g} s of CPU time") from None
    log = done.stdout + done.stderr
    errors = [line.strip() for line in log.splitlines() if "*ERROR" in line]
    if done.returncode != 0 or errors or not (folder / "job.frd").exists():
        said = errors[0] if errors else (log.strip().splitlines() or ["no output"])[-1]
        raise FESolveError(f"CalculiX refused the model (exit {done.returncode}): {said}")
    return log


def _read_frd(path: Path, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The last DISP and STRESS blocks of a CalculiX ``.frd`` (ASCII) as (n, 3) and (n, 6) arrays."""
    data = b"\n" + Path(path).read_bytes()
    starts: dict[str, int] = {}  # the last block of each name: where its heading line ends
    at = data.find(b"\n -4")
    while at >= 0:
        end = data.find(b"\n", at + 1)
        heading = data[at + 4:end if end >= 0 else len(data)].split()
        if heading and heading[0] in (b"DISP", b"STRESS"):
            starts[heading[0].decode()] = end if end >= 0 else len(data)
        at = data.find(b"\n -4", at + 1)
    blocks = {}
    for name, start in starts.items():
        end = data.find(b"\n -3", start)
        blocks[name] = _frd_values(data[start:end if end >= 0 else len(data)])
    if "DISP" not in blocks or "STRESS" not in blocks:
        raise FESolveError(f"{path.name}: no displacements or stresses in CalculiX's results")
    u = np.full((n_nodes, 3), np.nan)
    s = np.full((n_nodes, 6), np.nan)
    for out, (nodes, values) in ((u, blocks["DISP"]), (s, blocks["STRESS"])):
        width = out.shape[1]
        if len(nodes):
            out[nodes - 1] = values[:, :width]
    return u, s


def _frd_values(block: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A result block's node lines (`` -1``: the node in columns 4-13, then a value every 12
    columns) as their node numbers (k,) and values (k, m), a node given twice by its last line.
    Parsed as fixed-width fields all at once, each field's text by the same correctly rounded
    conversion as Python's ``float`` (the same numbers; a section model's 25 MB file read in 0.31 s
    instead of 0.68 s line by line); lines not all of one length are read one by one."""
    lines = [line for line in block.split(b"\n") if line.startswith(b" -1")]
    if not lines:
        return np.zeros(0, np.int64), np.zeros((0, 6))
    length = len(lines[0])
    if length >= 25 and all(len(line) == length for line in lines) and b"\r" not in lines[0]:
        table = np.frombuffer(b"".join(lines), np.uint8).reshape(len(lines), length)
        nodes = table[:, 3:13].copy().view("S10").ravel().astype(np.int64)
        values = table[:, 13:13 + 12 * ((length - 13) // 12)].copy().view("S12").astype(np.float64)
    else:
        rows = [line[13:].decode("ascii", "replace").rstrip("\r") for line in lines]
        parsed = [[float(body[k:k + 12]) for k in range(0, len(body) - 11, 12)] for body in rows]
        width = min(len(v) for v in parsed)
        nodes = np.array([int(line[3:13]) for line in lines], np.int64)
        values = np.array([v[:width] for v in parsed], np.float64).reshape(len(lines), width)
    if len(distinct(nodes)) < len(nodes):  # the last line of each node
        _, last = np.unique(nodes[::-1], return_index=True)
        nodes, values = nodes[::-1][last], values[::-1][last]
    return nodes, values


def _read_totals(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    """The summed reaction forces per node set from a CalculiX ``.dat``."""
    text = path.read_text(encoding="ascii", errors="replace").splitlines()
    totals: dict[str, np.ndarray] = {}
    for i, line in enumerate(text):
        match = re.search(r"total force \(fx,fy,fz\) for set (\S+)", line)
        if match:
            values = next(v for v in text[i + 1:] if v.strip())
            totals[match.group(1).upper()] = np.array([float(v) for v in values.split()[:3]])
    return {name: totals[name.upper()] for name in names if name.upper() in totals}


def _read_node_forces(path: Path, sets: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each node's reaction force per node set (k, 3; in the set's order) from a CalculiX ``.dat``
    (``*NODE PRINT, TOTALS=YES``: a line per node, node number first, after the set's heading)."""
    if not sets:
        return {}
    text = path.read_text(encoding="ascii", errors="replace").splitlines()
    forces: dict[str, dict[int, list[float]]] = {}
    current = None
    for line in text:
        match = re.match(r"\s*forces \(fx,fy,fz\) for set (\S+)", line)
        if match:
            current = forces.setdefault(match.group(1).upper(), {})
        elif current is not None and line.strip():
            cells = line.split()
            if len(cells) == 4 and cells[0].isdigit():
                current[int(cells[0])] = [float(v) for v in cells[1:]]
            else:
                current = None
    out = {}
    for name, nodes in sets.items():
        found = forces.get(name.upper(), {})
        ids = np.asarray(nodes, np.int64) + 1
        if any(int(i) not in found for i in ids):
            raise FESolveError(f"{path.name}: no reaction for every node of set {name} in CalculiX's results")
        out[name] = np.array([found[int(i)] for i in ids], np.float64).reshape(-1, 3)
    return out


def max_principal(stress: np.ndarray) -> np.ndarray:
    """The largest principal stress of each (xx, yy, zz, xy, yz, zx) row."""
    s = np.asarray(stress, np.float64)
    tensor = np.empty((len(s), 3, 3))
    tensor[:, 0, 0], tensor[:, 1, 1], tensor[:, 2, 2] = s[:, 0], s[:, 1], s[:, 2]
    tensor[:, 0, 1] = tensor[:, 1, 0] = s[:, 3]
    tensor[:, 1, 2] = tensor[:, 2, 1] = s[:, 4]
    tensor[:, 2, 0] = tensor[:, 0, 2] = s[:, 5]
    finite = np.all(np.isfinite(s), axis=1)
    out = np.full(len(s), np.nan)
    out[finite] = np.linalg.eigvalsh(tensor[finite])[:, -1]
    return out
