"""A sample of imported scans without stickers (``registration: surfaces``) reconstructed end to
end by the flow: four overlapping partial views of a bumpy analytic surface, each in its own
frame, imported (a) with their true poses perturbed by 5-10 mm / 5-10 degrees (a .conf) and (b)
with no poses; the registration recovers the true relative poses, and the report names the method
of every pass. A sticker sample's report says "targets"."""

from __future__ import annotations

import json

import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation

from data_catalog.stages import load_arrays
from flows.cli import main
from tests.flows.test_import_scans_cli import _conf

# truth: relative pose within these after registration (noise 0.01 mm, 0.5 mm sampling; measured
# worst scan: given poses 0.043 deg / 0.027 mm, global 0.058 deg / 0.047 mm, the chain of four views
# along the strip bending a little)
MAX_DEG, MAX_MM = 0.1, 0.1
CONFIG = """
denoise: {alpha: 3.0}
merge: {cell_mm: 1.0, coarse_factor: 1, weld_zone_mm: 0}
mesh: {poisson_depth: 6}
refine:  # noise 0.01 mm: a pair fits to a few hundredths when right; finer last gates than the bunny's
  surfaces: {max_rms_mm: 0.1, surface_sigma_mm: 0.03, gates_given_mm: [16, 8, 4, 2, 1, 0.5, 0.25],
             gates_global_mm: [8, 4, 2, 1, 0.5, 0.25]}
"""


_BUMPS = np.random.default_rng(2).uniform([-5, -5, -4, 3], [105, 65, 4, 8], size=(40, 4))  # x, y, height, sigma (mm)


def _height(x, y):
    """A bumpy surface with nothing repeating: 40 Gaussian bumps and dents of random place,
    height (up to 4 mm) and width (sigma 3-8 mm), mm."""
    z = np.zeros_like(x)
    for bx, by, h, sigma in _BUMPS:
        z += h * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * sigma ** 2))
    return z


def _views(folder):
    """Four views (x ranges overlapping by half), each sampled on its own jittered 0.5 mm grid,
    written as PLY in the view's own frame (turned about z, shifted): file -> T_world_scan."""
    rng = np.random.default_rng(5)
    folder.mkdir()
    truth = {}
    for k, x0 in enumerate((0.0, 20.0, 40.0, 60.0)):
        gx, gy = np.meshgrid(np.arange(x0, x0 + 40, 0.5), np.arange(0.0, 60.0, 0.5))
        x = gx.ravel() + rng.uniform(-0.2, 0.2, gx.size)
        y = gy.ravel() + rng.uniform(-0.2, 0.2, gx.size)
        world = np.column_stack([x, y, _height(x, y) + rng.normal(0, 0.01, x.size)])
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 40.0 * k + 15.0, degrees=True).as_matrix()
        T[:3, 3] = [100.0 * k, -50.0, 20.0 * k]
        local = (world - T[:3, 3]) @ T[:3, :3]
        vertex = np.zeros(len(local), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
        vertex["x"], vertex["y"], vertex["z"] = local.T
        name = f"view{k}.ply"
        plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(folder / name))
        truth[name] = T
    return truth


def _perturbed(truth: dict) -> dict:
    """Each true pose turned 5-10 degrees about a random axis through its view's centre and
    shifted 5-10 mm in a random direction."""
    rng = np.random.default_rng(3)
    out = {}
    for k, (name, T) in enumerate(truth.items()):
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        centre = np.array([20.0 * k + 20.0, 30.0, 0.0])  # world
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(np.radians(rng.uniform(5, 10)) * axis / np.linalg.norm(axis)).as_matrix()
        D[:3, 3] = centre - D[:3, :3] @ centre + rng.uniform(5, 10) * shift / np.linalg.norm(shift)
        out[name] = D @ T
    return out


def _errors(run, sample, truth: dict) -> list[tuple[float, float]]:
    """Per scan: (deg, mm at its centroid) between the flow's pose and the truth, relative to
    the first scan."""
    from data_catalog.manifests import load_manifest
    from data_catalog.scans import read_scan

    report = json.loads((run / "results" / "report.json").read_text())
    T_common = load_arrays(run / "stages" / "refine" / report["stage_keys"]["refine"] / "refined.zarr",
                           "T_common_pass")["T_common_pass"]
    found, true, points = [], [], []
    for k, (_, entry) in enumerate(load_manifest(sample).passes()):
        scan = read_scan(sample / entry.file, pass_id=entry.pass_id)
        found.append(T_common[k] @ (scan.T_world_pass if scan.T_world_pass is not None else np.eye(4)))
        true.append(truth[entry.source])
        points.append(scan.points_mm)
    out = []
    for k in range(len(found)):
        A = np.linalg.inv(found[0]) @ found[k]
        B = np.linalg.inv(true[0]) @ true[k]
        c = points[k].mean(axis=0)
        deg = np.degrees(Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).magnitude())
        mm = np.linalg.norm(A[:3, :3] @ c + A[:3, 3] - B[:3, :3] @ c - B[:3, 3])
        out.append((float(deg), float(mm)))
    return out, report


@pytest.mark.parametrize("poses", ["perturbed", "none"])
def test_scans_without_stickers_register_on_their_surfaces(poses, tmp_path):
    from flows.reconstruct import reconstruct_sample

    truth = _views(tmp_path / "scans")
    files = [str(tmp_path / "scans" / n) for n in truth]
    extra = []
    if poses == "perturbed":
        _conf(tmp_path / "rough.conf", _perturbed(truth), unit_mm=1.0)
        extra = ["--poses", str(tmp_path / "rough.conf")]
    sample = tmp_path / "sample"
    assert main(["import-scans", str(sample), *files, "--units", "mm", *extra]) == 0
    (tmp_path / "config.yaml").write_text(CONFIG)
    run = tmp_path / "run"
    reconstruct_sample(str(sample), str(run), str(tmp_path / "config.yaml"), started_by="pytest")
    errors, report = _errors(run, sample, truth)
    method = "surfaces from given poses" if poses == "perturbed" else "surfaces, global"
    assert report["registration_method"] == {f"view{k}": method for k in range(4)}
    assert report["stages"]["registration"]["target_pairs"] == 0
    # no profiles, times or targets to check on imported scans; the FE model's check is there
    assert [c["check"] for c in report["checks"]] == ["FE model"]
    if poses == "none":  # only neighbours overlap; a pose found between others (a look-alike) is refused
        pairs = report["refinement"]["pairs"]
        assert sorted((p["b"], p["a"]) for p in pairs if p["accepted"]) == [("view0", "view1"), ("view1", "view2"),
                                                                           ("view2", "view3")]
    worst = np.max(errors, axis=0)
    assert worst[0] < MAX_DEG and worst[1] < MAX_MM, errors


def test_a_sticker_samples_report_says_targets(six_run):
    _, report = six_run
    assert set(report["registration_method"].values()) == {"targets"}
    assert len(report["registration_method"]) == 6
