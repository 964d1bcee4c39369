"""Check the package layout: no import cycles, no private names across packages, small modules.

The rules of docs/architecture.md, checked on the source text (nothing is imported):

* the graph of imports between edgemodbus modules has no cycle (imports under
  ``if TYPE_CHECKING:`` count too: a cycle for the type checker is a cycle for a reader);
* a name starting with ``_`` is imported only from a module of the same package
  (private modules such as ``_ffi`` may be imported: their names are what they export);
* no module is longer than MAX_LINES lines;
* tests, benchmarks and tools use only public names of the package;
* our C (csrc/, not csrc/fuzz/) has no include cycle between its modules (emb_x.c and
  emb_x.h are one module; ``#include "emb_*.h"`` is an edge), and its leaves (C_LEAVES:
  CRC, clock and fd waits; the reply check; the link state) include nothing of ours.

Exit status 1 with one line per violation, 0 when the tree is clean.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

TOP = Path(__file__).resolve().parents[1]
CLIENTS = ("tests", "bench", "tools")
PACKAGE = "edgemodbus"
MAX_LINES = 500
C_LEAVES = ("emb_util", "emb_check", "emb_link")
C_INCLUDE = re.compile(r'^\s*#\s*include\s+"(emb_\w+)\.h"', re.MULTILINE)


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def resolve(current: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute module named by ``from <level dots><target> import ...`` in ``current``."""
    if level == 0:
        return target or ""
    base = current.split(".")
    if not is_package:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def package_of(module: str, modules: dict[str, Path]) -> str:
    path = modules[module]
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def imports(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, str, int]]:
    """(imported module, imported name or "", line) for every edgemodbus import in ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    found: list[tuple[str, str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, "", node.lineno) for a in node.names if a.name.startswith(PACKAGE)]
        elif isinstance(node, ast.ImportFrom):
            source = resolve(module, is_package, node.level, node.module)
            if not source.startswith(PACKAGE):
                continue
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                if sub in modules:  # ``from . import codec`` names a module
                    found.append((sub, "", node.lineno))
                else:
                    found.append((source, alias.name, node.lineno))
    return found


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def check(top: Path) -> list[str]:
    """Every violation in the tree at ``top`` (its src/edgemodbus and client folders)."""
    root = top / "src"
    modules = {module_name(p, root): p for p in (root / PACKAGE).rglob("*.py")}
    problems: list[str] = []
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in sorted(modules.items()):
        lines = len(path.read_text().splitlines())
        if lines > MAX_LINES:
            problems.append(f"{path.relative_to(top)}: {lines} lines (at most {MAX_LINES})")
        for target, name, line in imports(module, path, modules):
            if target not in modules:
                continue
            # A package's __init__ importing its own modules is how it exports them, not a
            # cycle; a module importing its own package's __init__ is.
            if not (path.name == "__init__.py" and target.startswith(module + ".")):
                graph[module].add(target)
            if name.startswith("_") and package_of(target, modules) != package_of(module, modules):
                problems.append(
                    f"{path.relative_to(top)}:{line}: imports private name {name!r} "
                    f"from {target} (another package)"
                )
    for folder in CLIENTS:
        for path in sorted((top / folder).rglob("*.py")):
            for target, name, line in imports(folder, path, modules):
                if name.startswith("_"):
                    where = f"{path.relative_to(top)}:{line}"
                    problems.append(f"{where}: imports private name {name!r} from {target}")
    graph = {m: {t for t in ts if t != m} for m, ts in graph.items()}
    cycle = find_cycle(graph)
    if cycle:
        problems.append("import cycle: " + " -> ".join(cycle))
    return problems


def c_problems(top: Path) -> list[str]:
    """Include cycles between the C modules of csrc/, and leaves that include ours."""
    csrc = top / "csrc"
    graph: dict[str, set[str]] = {}
    problems: list[str] = []
    for path in sorted([*csrc.glob("emb_*.c"), *csrc.glob("emb_*.h")]):
        module = path.stem
        included = set(C_INCLUDE.findall(path.read_text())) - {module}
        graph.setdefault(module, set()).update(included)
        if module in C_LEAVES and included:
            problems.append(f"{path.relative_to(top)}: a leaf of our C includes "
                            f"{', '.join(sorted(i + '.h' for i in included))}")
    cycle = find_cycle(graph)
    if cycle:
        problems.append("C include cycle: " + " -> ".join(cycle))
    return problems


def main() -> int:
    problems = check(TOP) + c_problems(TOP)
    for problem in problems:
        print(problem)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
