"""Burr-ground toes are reflective: dropouts and spurious outliers at their own stated rates."""

from __future__ import annotations

import numpy as np

from data_catalog.manifests import load_manifest
from data_catalog.truth import read_truth_pass
from schemas.simulation import ScanPlanConfig, WidthPass
from schemas.truth import Material, PointLabel
from simulator.presets import preset_config
from simulator.run import simulate


def test_ground_metal_drops_and_scatters_at_its_rates(tmp_path):
    base = preset_config("ci")
    cfg = base.model_copy(update={
        "weld": base.weld.model_copy(update={"treatment": "burr-ground"}),
        "plan": ScanPlanConfig(setups=["top"], vertical_offsets_mm=[0.0], side_rolls_deg=[],
                               width_passes=[WidthPass(x_mm=0.0)]),
    })
    simulate(cfg, tmp_path / "s", previews=False)
    manifest = load_manifest(tmp_path / "s")
    assert manifest.weld.treatment == "burr-ground"
    seen = drop = out = 0
    for _, entry in manifest.passes():
        tp = read_truth_pass(tmp_path / "s" / "truth" / "passes" / f"{entry.pass_id}.zarr")
        labels = tp.label[tp.material == Material.GROUND]
        n = [np.count_nonzero(labels == v) for v in (PointLabel.VALID, PointLabel.DROPOUT, PointLabel.OUTLIER)]
        seen += sum(n)
        drop += n[1]
        out += n[2]
    sc = cfg.scanner
    assert seen > 2000
    p = sc.reflective_dropout_rate
    assert abs(drop - seen * p) < 5 * np.sqrt(seen * p * (1 - p)), drop / seen
    q = sc.reflective_outlier_rate
    kept = seen - drop
    assert abs(out - kept * q) < 5 * np.sqrt(kept * q * (1 - q)) + 1, out / kept
