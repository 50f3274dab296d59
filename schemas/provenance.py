"""Provenance: one typed record per stage run, for the sample's audit trail (HFMI QA)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import Field, field_validator

from schemas.common import StrictModel

__all__ = ["PROVENANCE_SCHEMA_VERSION", "StageRecord", "StageName", "STAGE_NAMES"]

PROVENANCE_SCHEMA_VERSION = "1.0"

# every stage's one name, in run order: a closed set (the registry, flows/stages/__init__.py,
# declares each of them once, and a test holds the two together)
StageName = Literal["denoise", "targets", "registration", "refine", "merge", "segment", "weld", "mesh", "export",
                    "volume", "stress", "report", "qa_report"]
STAGE_NAMES: tuple[str, ...] = StageName.__args__


class StageRecord(StrictModel):
    schema_version: Literal["1.0"] = PROVENANCE_SCHEMA_VERSION
    sample_id: str
    stage: StageName
    item: str | None = Field(default=None, description="the pass, for per-pass stages")
    cache_key: str = Field(pattern=r"^[0-9a-f]{64}$")
    inputs: dict[str, str] = Field(description="name -> sha256")
    outputs: dict[str, str] = Field(description="name -> sha256")
    parameters: dict[str, Any]
    code_version: str
    host: str
    started: datetime
    finished: datetime
    metrics: dict[str, Any] = {}
    cached: bool = Field(default=False, description="the outputs were already in the store; nothing ran")
    flow_run_id: str | None = None

    @field_validator("started", "finished")
    @classmethod
    def _aware(cls, value: datetime) -> datetime:
        if value.tzinfo is None:
            raise ValueError("times must carry a timezone")
        return value
