"""Settings have one home, the config models (schemas/reconstruction.py): every stage passes the
fields it uses explicitly, and no task function keeps a default of its own for them."""

from __future__ import annotations

import ast
import importlib
import inspect

import pytest
from pydantic import BaseModel

from flows.stages import STAGES
from schemas.reconstruction import ReconstructionConfig

DEFAULTS = ReconstructionConfig()


def _settings_calls(stage):
    """(task function, parameter, config field) for every keyword argument the stage body fills
    from a field of its settings model."""
    model = stage.settings_of(DEFAULTS)
    fields = set(type(model).model_fields) if isinstance(model, BaseModel) and stage.settings != "*" else set()
    found = []
    for module in map(importlib.import_module, stage.body_modules):  # the surfaces variant's too
        for node in ast.walk(ast.parse(inspect.getsource(module))):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
                continue
            function = getattr(module, node.func.id, None)
            if function is None or not getattr(function, "__module__", "").startswith("tasks."):
                continue
            for keyword in node.keywords:
                value = keyword.value
                if isinstance(value, ast.Attribute) and value.attr in fields:
                    found.append((function, keyword.arg, value.attr))
    return model, found


@pytest.mark.parametrize("stage", [s for s in STAGES if s.settings not in (None, "*")], ids=lambda s: s.name)
def test_task_functions_take_the_stage_settings_without_defaults_of_their_own(stage):
    model, calls = _settings_calls(stage)
    assert calls, f"stage {stage.name} passes none of its settings to a task function"
    for function, parameter, field in calls:
        default = inspect.signature(function).parameters[parameter].default
        assert default is inspect.Parameter.empty, (
            f"{function.__module__}.{function.__name__}({parameter}={default!r}) keeps a default of its own; "
            f"the config's is {stage.settings}.{field} = {getattr(model, field)!r}")


@pytest.mark.parametrize("stage", [s for s in STAGES if s.settings not in (None, "*")], ids=lambda s: s.name)
def test_every_setting_of_a_stage_reaches_its_body(stage):
    """A field no stage reads would be a setting that silently does nothing."""
    model, calls = _settings_calls(stage)
    body = "".join(inspect.getsource(importlib.import_module(m)) for m in stage.body_modules)
    unused = [f for f in type(model).model_fields if f".{f}" not in body]
    assert not unused, f"stage {stage.name}: settings {unused} are never read"
