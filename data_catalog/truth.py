"""Ground-truth stores written by the simulator (``truth/`` beside a sample). Pipeline code never
reads these; tests and benchmarks compare against them.

``truth/passes/<pass_id>.zarr``: T_world_sensor (n, 4, 4) float64 true sensor pose per profile;
label (n, m) uint8 (schemas.truth.PointLabel); material (n, m) uint8 (schemas.truth.Material);
sticker_id (n, m) int16 (-1 for none). ``truth/truth.json``: schemas.truth.GroundTruth;
``truth/weld_sections.json``: schemas.truth.WeldTruth; ``truth/toes.json`` (fillet-welded parts):
schemas.truth.TrueToeLines.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from data_catalog.atomic import atomic_write_text
from data_catalog.passes import check_complete, create_chunked_array
from schemas.truth import FilletWeldTruth, GroundTruth, TrueToeLines, WeldTruth

__all__ = ["TRUTH_DIR", "WELD_TRUTH_NAME", "TruthPassWriter", "TruthPass", "read_truth_pass", "write_truth", "read_truth",
           "write_weld_truth", "read_weld_truth", "read_true_toes", "FILLET_TRUTH_NAME", "read_fillet_truth"]

TRUTH_DIR = "truth"
WELD_TRUTH_NAME = "weld_sections.json"  # schemas.truth.WeldTruth: the drawn weld every 1 mm
FILLET_TRUTH_NAME = "fillet_weld.json"  # schemas.truth.FilletWeldTruth: a T-joint's fillets every 1 mm


class TruthPassWriter:
    def __init__(self, path: Path, *, n_profiles: int, n_columns: int, chunk_profiles: int) -> None:
        self._group = zarr.open_group(str(path), mode="w-")
        self._group.attrs.update({"format": "weldrecon-truth-pass", "format_version": 1})
        grid = (n_profiles, n_columns)
        self._arrays = {
            "T_world_sensor": create_chunked_array(self._group, "T_world_sensor", (n_profiles, 4, 4),
                                                   chunk_profiles, "float64", np.nan),
            "label": create_chunked_array(self._group, "label", grid, chunk_profiles, "uint8", 255),
            "material": create_chunked_array(self._group, "material", grid, chunk_profiles, "uint8", 0),
            "sticker_id": create_chunked_array(self._group, "sticker_id", grid, chunk_profiles, "int16", -1),
        }

    def write(self, start: int, **blocks: np.ndarray) -> None:
        for name, block in blocks.items():
            self._arrays[name][start:start + len(block)] = block


@dataclass(frozen=True)
class TruthPass:
    T_world_sensor: np.ndarray
    label: np.ndarray
    material: np.ndarray
    sticker_id: np.ndarray


def read_truth_pass(path: Path) -> TruthPass:
    group = zarr.open_group(str(path), mode="r")
    arrays = {}
    for name in ("T_world_sensor", "label", "material", "sticker_id"):
        check_complete(group[name], what=f"truth {path}")
        arrays[name] = group[name][...]
    return TruthPass(**arrays)


def write_truth(path: Path, truth: GroundTruth) -> None:
    atomic_write_text(Path(path), truth.model_dump_json(indent=1) + "\n")


def read_truth(path: Path) -> GroundTruth:
    return GroundTruth.model_validate(json.loads(Path(path).read_text()))


def write_weld_truth(path: Path, truth: WeldTruth) -> None:
    atomic_write_text(path, truth.model_dump_json(indent=1) + "\n")


def read_weld_truth(path: Path) -> WeldTruth:
    return WeldTruth.model_validate_json(Path(path).read_text(encoding="utf-8"))


def read_true_toes(path: Path) -> TrueToeLines:
    """``truth/toes.json``: the true toe lines of a fillet-welded part."""
    return TrueToeLines.model_validate(json.loads(Path(path).read_text()))


def read_fillet_truth(path: Path) -> FilletWeldTruth:
    """``truth/fillet_weld.json``: a T-joint's fillet welds as drawn."""
    return FilletWeldTruth.model_validate_json(Path(path).read_text(encoding="utf-8"))
