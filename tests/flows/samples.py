"""Samples for the flow tests made from the session's ``ci`` sample."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

QUICK_CONFIG = str(Path(__file__).resolve().parents[1] / "data" / "quick.yaml")
"""The ci settings with the weld read every 5 mm and the stress every 40 mm (tests/data/quick.yaml):
for the tests that run a flow to test what is around the weld's and the stress's figures."""

FILLET_CONFIG = str(Path(__file__).resolve().parents[1] / "data" / "fillet.yaml")
"""The ci settings with the weld read every 2 mm (tests/data/fillet.yaml): for the T-joint's and the
cruciform's fillet welds, checked as medians and percentiles over more than 100 sections a face."""


def copy_sample(ci_sample: Path, dst: Path, keep: list[str] | None = None) -> Path:
    """A copy of the ci sample at ``dst`` (manifest and pass stores), optionally with only the
    passes ``keep`` (setups left without a pass dropped)."""
    dst.mkdir(parents=True)
    manifest = json.loads((ci_sample / "manifest.json").read_text())
    if keep is not None:
        for setup in manifest["setups"]:
            setup["passes"] = [p for p in setup["passes"] if p["pass_id"] in keep]
        manifest["setups"] = [s for s in manifest["setups"] if s["passes"]]
    for setup in manifest["setups"]:
        for p in setup["passes"]:
            shutil.copytree(ci_sample / p["file"], dst / p["file"])
    (dst / "manifest.json").write_text(json.dumps(manifest))
    return dst


def as_published(run) -> dict:
    """A run's result as a plain dict: the published ``report.json`` as it reads in JSON (what a
    consumer outside weldrecon sees) with the run's own facts beside it (outputs, refs, cached,
    seconds, trail_head, stage_paths), for tests that check the published document's shape."""
    import json as _json

    body = {} if run.report is None else _json.loads(run.report.model_dump_json(by_alias=True))
    return {**body, "outputs": run.outputs, "refs": run.refs, "cached": run.cached, "seconds": run.seconds,
            "trail_head": {"seq": run.trail_head.seq, "hash": run.trail_head.hash},
            "stage_paths": {n: run.stage_path(n) for n in run.refs}}


def without_pose_logs(sample: Path, dst: Path) -> Path:
    """``sample`` as a cell that logs no flange pose per profile (``robot.log_profile_poses:
    false``) would have written it: the same profiles, no ``T_world_flange`` in the pass stores,
    the manifest saying so (``has_profile_poses`` false, the stores' hashes anew) and the truth's
    settings too. The simulator draws nothing for the log it writes, so this is the sample it
    simulates with the flag off (tests/simulator/test_ci_sample.py checks that on a small plan)."""
    from data_catalog.hashing import sha256_tree
    from data_catalog.manifests import write_manifest
    from schemas.manifest import SampleManifest
    from schemas.simulation import SimulationConfig

    dst.mkdir(parents=True)
    manifest = json.loads((sample / "manifest.json").read_text())
    for setup in manifest["setups"]:
        for p in setup["passes"]:
            shutil.copytree(sample / p["file"], dst / p["file"], ignore=shutil.ignore_patterns("T_world_flange"))
            p["has_profile_poses"] = False
            p["content_sha256"] = sha256_tree(dst / p["file"])
    write_manifest(dst / "manifest.json", SampleManifest.model_validate(manifest))  # as the simulator writes it
    shutil.copytree(sample / "truth", dst / "truth")
    config = SimulationConfig.model_validate_json((sample / "truth" / "simulation.json").read_text())
    config = config.model_copy(update={"robot": config.robot.model_copy(update={"log_profile_poses": False})})
    (dst / "truth" / "simulation.json").write_text(config.simulation_json())
    return dst
