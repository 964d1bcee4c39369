"""docs/configuration.md is what tools/gen_config_reference.py writes from the models
today, documents every key the loader knows and no key it does not; the tool refuses a
key without a meaning."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import ClassVar

import pytest
from pydantic import Field

from edgemodbus.config import Model

TOP = Path(__file__).resolve().parents[2]
TOOL = TOP / "tools" / "gen_config_reference.py"
PAGE = TOP / "docs" / "configuration.md"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_config_reference", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_committed_reference_is_up_to_date() -> None:
    out = subprocess.run([sys.executable, str(TOOL), "--check"], capture_output=True,
                         text=True, timeout=60, check=False, cwd=TOP)
    assert out.returncode == 0, out.stderr


def test_every_key_of_the_models_is_documented_and_no_other() -> None:
    """Read back from the page's tables (not from the tool's own lists): the keys under
    each section heading are the model's fields' JSON keys."""
    tool = _tool()
    documented: dict[str, set[str]] = {}
    heading = ""
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        if line.startswith("### "):
            heading = line[4:]
            documented[heading] = set()
        elif (key := re.match(r"^\| `([^`]+)` \|", line)) is not None:
            documented[heading].add(key.group(1))
    expected: dict[str, set[str]] = {}
    for title, sections in (("The device file", tool.DEVICE), ("The gateway file", tool.GATEWAY)):
        for section in sections:
            name = section.path if section.path != "(top level)" else f"{title}: top level"
            expected[name] = {f.alias or n for n, f in section.model.model_fields.items()}
    assert documented == expected


def test_a_key_without_a_meaning_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A new field without a description (and not in DESCRIPTIONS) makes the tool fail
    naming it; a description of a key that is gone too."""
    tool = _tool()

    class Extra(Model):
        _where: ClassVar[str] = "extra"
        documented: int = Field(default=1, description="a key with its meaning")
        new_key: int = 2

    monkeypatch.setattr(tool, "GATEWAY", (*tool.GATEWAY, tool.Section("extra", Extra, "x")))
    monkeypatch.setitem(tool.DESCRIPTIONS, "metrics.gone", "a key that no longer exists")
    _, problems = tool.render()
    assert problems == [
        "extra.newKey: no description (add one to the field or to DESCRIPTIONS)",
        "DESCRIPTIONS['metrics.gone']: no such key in the models",
    ]
    assert tool.main(["gen", "--check"]) == 1


def test_defaults_and_ranges_come_from_the_models() -> None:
    text = PAGE.read_text(encoding="utf-8")
    assert "| `baudRate` | integer | `9600` | 1200..921600 |" in text
    assert "| `qos` | integer | `0` | 0 or 1 or 2 |" in text
    assert "| `path` | text | required |" in text  # mqtt.storeAndForward.path
