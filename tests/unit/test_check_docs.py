"""tools/check_docs.py finds each kind of broken link and the page no one links, in a
tree made for the test, and the repository's own pages have none (make lint runs it)."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

TOP = Path(__file__).resolve().parents[2]
TOOL = TOP / "tools" / "check_docs.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("check_docs", TOOL)
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


GOOD = {
    "README.md": "# Title\n\nSee [the index](docs/index.md) and [a file](LICENSE).\n",
    "LICENSE": "MIT\n",
    "docs/index.md": "# Index\n\n- [Guide](guide.md#first-steps-5-minutes)\n",
    "docs/guide.md": "# Guide\n\n## First steps (5 minutes)\n\n[up](../README.md#title)\n",
}


def test_a_tree_whose_links_resolve_passes() -> None:
    assert _tool().check(TOP) == [], "the repository's pages have broken links"


def test_good_tree(tmp_path: Path) -> None:
    assert _tool().check(_tree(tmp_path, GOOD)) == []


def test_a_missing_file_a_missing_anchor_and_an_unlinked_page(tmp_path: Path) -> None:
    top = _tree(tmp_path, {
        **GOOD,
        "docs/guide.md": "# Guide\n\n[gone](gone.md) [bad anchor](index.md#nowhere)\n"
                         "[self](#guide) [self bad](#nope)\n",
        "docs/orphan.md": "# Orphan\n",
    })
    assert _tool().check(top) == [
        "docs/guide.md:3: link 'gone.md': no such file docs/gone.md",
        "docs/guide.md:3: link 'index.md#nowhere': docs/index.md has no heading #nowhere "
        "(its anchors: index)",
        "docs/guide.md:4: link '#nope': docs/guide.md has no heading #nope (its anchors: "
        "guide)",
        "docs/index.md:3: link 'guide.md#first-steps-5-minutes': docs/guide.md has no "
        "heading #first-steps-5-minutes (its anchors: guide)",
        "docs/orphan.md: not linked from README.md or docs/index.md: add a line for it to "
        "docs/index.md",
    ]


def test_code_external_links_and_reference_definitions(tmp_path: Path) -> None:
    """Links in fenced blocks and inline code are text; http(s) is never followed; a
    reference definition is a link; a link out of the repository is refused."""
    top = _tree(tmp_path / "repo", {
        **GOOD,
        "docs/guide.md": "# Guide\n\n## First steps (5 minutes)\n```md\n[x](missing.md)\n```\n"
                         "`[y](missing.md)`\n"
                         "[web](https://example.invalid/x) [mail](mailto:a@b.invalid)\n"
                         "[ref]: nothing.md\n[out](../../outside.md)\n",
    })
    (tmp_path / "outside.md").write_text("# Out\n")
    assert _tool().check(top) == [
        "docs/guide.md:9: link 'nothing.md': no such file docs/nothing.md",
        "docs/guide.md:10: link '../../outside.md' leaves the repository",
    ]


def test_anchors_follow_github() -> None:
    tool = _tool()
    text = ("# Batched: `mode: \"batch\"`\n## Entity addresses (40001)\n## Notes\n## Notes\n"
            "```\n# not a heading\n```\n")
    assert tool.anchors(text) == {"batched-mode-batch", "entity-addresses-40001", "notes",
                                  "notes-1"}


def test_a_missing_index_is_named(tmp_path: Path) -> None:
    files = {k: v for k, v in GOOD.items() if k != "docs/index.md"}
    files["README.md"] = "# Title\n\n[guide](docs/guide.md#first-steps-5-minutes)\n"
    assert _tool().check(_tree(tmp_path, files)) == [
        "docs/index.md: missing (the index of the pages under docs/)"]
