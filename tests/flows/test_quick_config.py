"""The tests' quick settings (tests/data/quick.yaml) are the ci settings with the weld and the stress
read at fewer sections and fewer weld sections drawn, and their fillet settings (tests/data/fillet.yaml) the ci settings with the
weld read every 2 mm, nothing else: what the tests that run flows with them find holds for ci.yaml."""

from __future__ import annotations

from pathlib import Path

import yaml

from tests.flows.samples import FILLET_CONFIG, QUICK_CONFIG

CI_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "configs" / "ci.yaml"


def test_the_quick_settings_are_the_ci_settings_with_fewer_sections():
    ci, quick = (yaml.safe_load(Path(p).read_text()) for p in (CI_CONFIG, QUICK_CONFIG))
    fewer = {"weld": {"section_step_mm": 5.0}, "stress": {"section_step_mm": 40.0}, "qa_report": {"sections_per_line": 1}}
    assert quick == {k: {**ci.get(k, {}), **fewer.get(k, {})} for k in ci.keys() | fewer.keys()}


def test_the_fillet_settings_are_the_ci_settings_with_the_weld_every_2_mm():
    ci, fillet = (yaml.safe_load(Path(p).read_text()) for p in (CI_CONFIG, FILLET_CONFIG))
    assert fillet == {**ci, "weld": {**ci.get("weld", {}), "section_step_mm": 2.0}}
