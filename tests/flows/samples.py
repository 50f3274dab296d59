"""Samples for the flow tests made from the session's ``ci`` sample."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


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
