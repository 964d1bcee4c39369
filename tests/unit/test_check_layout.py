"""tools/check_layout.py finds each kind of layout violation in a tree made for the test,
and the real tree has none (make lint runs it too)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

TOOL = Path(__file__).resolve().parents[2] / "tools" / "check_layout.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("check_layout", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path


def test_private_names_only_within_their_package(tmp_path: Path) -> None:
    top = _tree(tmp_path, {
        "src/edgemodbus/__init__.py": "from .a import thing\n",
        "src/edgemodbus/a.py": "from .low import _helper\nthing = _helper\n",
        "src/edgemodbus/low.py": "def _helper() -> None: ...\n",
        "src/edgemodbus/pkg/__init__.py": "from .mod import x\n",
        "src/edgemodbus/pkg/mod.py": "from ..low import _helper as _h\nx = 1\n",
        "tests/test_a.py": "from edgemodbus.a import thing\n",
    })
    # a.py may take _helper from its own package; pkg/mod.py is in another one
    assert _tool().check(top) == [
        "src/edgemodbus/pkg/mod.py:1: imports private name '_helper' from edgemodbus.low "
        "(another package)"
    ]


def test_cycles_private_names_in_tests_and_long_modules_are_found(tmp_path: Path) -> None:
    top = _tree(tmp_path, {
        "src/edgemodbus/__init__.py": "",
        "src/edgemodbus/a.py": "from . import b\n",
        "src/edgemodbus/b.py": "def f() -> None:\n    from .a import g\n",
        "src/edgemodbus/long.py": "x = 1\n" * 501,
        "tests/test_x.py": "from edgemodbus.a import _secret\n",
    })
    problems = _tool().check(top)
    assert "src/edgemodbus/long.py: 501 lines (at most 500)" in problems
    assert "tests/test_x.py:1: imports private name '_secret' from edgemodbus.a" in problems
    assert "import cycle: edgemodbus.a -> edgemodbus.b -> edgemodbus.a" in problems
    assert len(problems) == 3


def test_the_repository_follows_its_layout_rules() -> None:
    assert _tool().check(TOOL.parents[1]) == []


def test_c_include_cycles_and_leaves_that_include_ours_are_found(tmp_path: Path) -> None:
    top = _tree(tmp_path, {
        "csrc/emb_io.c": '#include "emb_io.h"\n#include "emb_stream.h"\n',
        "csrc/emb_io.h": '#include <modbus.h>\n#include "emb_link.h"\n',
        "csrc/emb_stream.c": '#include "emb_stream.h"\n# include "emb_io.h" /* back */\n',
        "csrc/emb_stream.h": "",
        "csrc/emb_util.c": '#include "emb_util.h"\n#include "emb_check.h"\n',
        "csrc/emb_link.h": "#include <stdint.h>\n",
        "csrc/fuzz/fuzz_x.c": '#include "../emb_io.c"\n',
    })
    assert _tool().c_problems(top) == [
        "csrc/emb_util.c: a leaf of our C includes emb_check.h",
        "C include cycle: emb_io -> emb_stream -> emb_io",
    ]


def test_our_c_has_no_include_cycle() -> None:
    assert _tool().c_problems(TOOL.parents[1]) == []
