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


# ----------------------------------------------------------------------------- layer order

_DOC = """# arch

## Layers, bottom up

```
 __init__.py  app/  tool.py   the top: its description may name mqtt/ or x.py
                   and go on under it (cli/ here is no layer)
 mid/              the middle
 low.py  base.py
```

- prose after the diagram: `sim/` here is no layer either
"""


def test_the_layer_order_is_read_from_the_diagram_of_the_doc() -> None:
    assert _tool().layers_of(_DOC) == [
        ("__init__.py", "app/", "tool.py"), ("mid/",), ("low.py", "base.py")]
    assert _tool().layers_of("# arch\n\n## Layers\n\n```\n a/\n```\n") is None


def _layered(tmp_path: Path, files: dict[str, str], doc: str = _DOC) -> Path:
    return _tree(tmp_path, {
        "docs/architecture.md": doc,
        "src/edgemodbus/__init__.py": "",
        "src/edgemodbus/app/__init__.py": "",
        "src/edgemodbus/tool.py": "",
        "src/edgemodbus/mid/__init__.py": "",
        "src/edgemodbus/mid/core.py": "",
        "src/edgemodbus/low.py": "",
        "src/edgemodbus/base.py": "",
        **files,
    })


def test_imports_down_the_layers_and_within_one_pass(tmp_path: Path) -> None:
    top = _layered(tmp_path, {
        "src/edgemodbus/app/run.py": "from ..mid.core import go\nfrom .. import tool, low\n",
        "src/edgemodbus/tool.py": "import edgemodbus.app.run\n",  # its own layer
        "src/edgemodbus/mid/core.py": "from edgemodbus.base import b\nfrom . import x\n",
        "src/edgemodbus/low.py": "from .base import b\n",
        "src/edgemodbus/base.py": "from .low import c\n",  # one layer: no order between them
    })
    assert _tool().layer_problems(top, allowed={}) == []


def test_an_upward_import_is_found_with_the_module_the_import_and_both_layers(
    tmp_path: Path,
) -> None:
    top = _layered(tmp_path, {
        "src/edgemodbus/mid/core.py": "from ..app import helper\n",
        "src/edgemodbus/base.py": (
            "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n"
            "    from edgemodbus.mid.core import Thing\n"
            "def f() -> None:\n"
            "    import edgemodbus.tool\n"
        ),
    })
    assert _tool().layer_problems(top, allowed={}) == [
        "src/edgemodbus/base.py:3: edgemodbus.base (layer base.py) imports edgemodbus.mid.core "
        "of layer mid/, above it in docs/architecture.md (under TYPE_CHECKING, which counts "
        "too)",
        "src/edgemodbus/base.py:5: edgemodbus.base (layer base.py) imports edgemodbus.tool of "
        "layer tool.py, above it in docs/architecture.md",
        "src/edgemodbus/mid/core.py:1: edgemodbus.mid.core (layer mid/) imports edgemodbus.app "
        "of layer app/, above it in docs/architecture.md",
    ]


def test_the_allow_list_keeps_an_upward_import_and_reports_a_stale_entry(
    tmp_path: Path,
) -> None:
    top = _layered(tmp_path, {"src/edgemodbus/low.py": "from .mid import core\n"})
    allowed = {
        ("edgemodbus.low", "edgemodbus.mid.core"): "kept for a test",
        ("edgemodbus.base", "edgemodbus.app"): "an import that is gone",
    }
    assert _tool().layer_problems(top, allowed) == [
        "tools/check_layout.py: ALLOWED_UPWARD lists edgemodbus.base -> edgemodbus.app, an "
        "import that is no longer there"
    ]


def test_a_diagram_that_misses_a_module_or_names_nothing_is_reported(tmp_path: Path) -> None:
    doc = _DOC.replace(" mid/              the middle\n",
                       " mid/              the middle\n gone/  Oops     no such folder\n")
    top = _layered(tmp_path, {"src/edgemodbus/extra/__init__.py": "",
                              "src/edgemodbus/loose.py": ""}, doc)
    assert _tool().layer_problems(top, allowed={}) == [
        "docs/architecture.md: gone/ in the layer diagram names nothing in src/edgemodbus/ "
        "(nor at the top)",
        "docs/architecture.md: 'Oops' opens line 3 of the layer diagram: a layer is named by "
        "folder/ and module.py words",
        "src/edgemodbus/extra/: not in the layer diagram of docs/architecture.md (place it "
        "there)",
        "src/edgemodbus/loose.py: not in the layer diagram of docs/architecture.md (place it "
        "there)",
    ]
    (top / "docs/architecture.md").write_text("# arch\n")
    assert _tool().layer_problems(top, allowed={}) == [
        "docs/architecture.md: no '## Layers, bottom up' diagram to check the layer order "
        "against"
    ]


def test_the_repository_follows_the_layer_order_of_its_doc() -> None:
    assert _tool().layer_problems(TOOL.parents[1]) == []
