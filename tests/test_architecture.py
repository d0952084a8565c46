"""The plugin boundary and the module rules of issue 12, checked on the source itself."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FRAMEWORK = ("swathflow", "tasks", "flows")
SENSOR_NAMES = ("pendulum", "pushbroom", "push-broom", "push_broom")


def _docstrings(tree) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ids.add(id(body[0].value))
    return ids


def _sensor_names_in(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    docs = _docstrings(tree)
    found = []
    for node in ast.walk(tree):
        text = None
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            text = node.value
        elif isinstance(node, ast.Name):
            text = node.id
        elif isinstance(node, ast.Attribute):
            text = node.attr
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            text = " ".join([getattr(node, "module", "") or ""] + [a.name for a in node.names])
        if text and any(n in text.lower() for n in SENSOR_NAMES):
            found.append(f"{path}:{node.lineno}: {text[:60]!r}")
    return found


def test_no_sensor_name_in_the_framework():
    """What differs between scanners is asked of the plugin: no code path in swathflow/, tasks/
    or flows/ names a built-in sensor (docstrings may use them as examples)."""
    found = [f for d in FRAMEWORK for p in sorted((ROOT / d).rglob("*.py"))
             for f in _sensor_names_in(p)]
    assert not found, "sensor names in the framework:\n" + "\n".join(found)


def test_the_check_sees_a_sensor_name(tmp_path):
    p = tmp_path / "x.py"
    p.write_text('"""pendulum in a docstring is fine."""\nif m == "pushbroom":\n    pass\n'
                 'from swathflow.sensors.pendulum import PendulumModel\n')
    assert len(_sensor_names_in(p)) == 2     # the string; the import (module and class)


@pytest.mark.parametrize("hook", ["line_columns", "directions", "check_lines",
                                  "calibration_strategy", "simulator"])
def test_every_registered_sensor_answers_the_hooks(hook):
    from swathflow.sensormodel import list_sensors
    for name, cls in list_sensors().items():
        value = getattr(cls, hook)
        if callable(value):
            value = value() if hook != "check_lines" else value({"time": [0.0, 1.0]})
        if hook == "line_columns":
            assert "time" in value, f"{name}: line_columns must include time"
        if hook == "simulator" and value is not None:
            assert hasattr(value, "PRESETS") and callable(value.simulate), name
        if hook == "calibration_strategy" and value is not None:
            assert callable(value.calibrate), name
