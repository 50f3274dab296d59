"""The weld's acceptance limits (``schemas.acceptance``) from a YAML file: the project's defaults,
with their sources, in ``weld_acceptance.yaml`` beside this module."""

from __future__ import annotations

from pathlib import Path

from data_catalog.textfiles import read_yaml_model
from schemas.acceptance import AcceptanceLimits

__all__ = ["DEFAULT_ACCEPTANCE_FILE", "load_acceptance_limits"]

DEFAULT_ACCEPTANCE_FILE = Path(__file__).with_name("weld_acceptance.yaml")


def load_acceptance_limits(path: str | Path | None) -> AcceptanceLimits:
    """The limits in ``path`` (None: the project's defaults). A bad file is refused with the file
    and each wrong field named (``rules.0.groove_depth_mm.min: ...``)."""
    path = DEFAULT_ACCEPTANCE_FILE if path is None else Path(path)
    return read_yaml_model(path, AcceptanceLimits, "weld acceptance limits")
