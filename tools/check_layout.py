"""Check the package layout: the layer order, no import cycles, no private names across
packages, small modules.

The rules of docs/architecture.md, checked on the source text (nothing is imported):

* a module imports only from its own layer and the layers below it, in the order of the
  "Layers, bottom up" diagram of docs/architecture.md, read from the doc itself so that
  the doc and the check cannot drift apart: each line of the diagram that starts in its
  first column is one layer, top first, named by its leading ``folder/`` and
  ``module.py`` words; every name must exist and every module of src/edgemodbus must be
  placed (``__init__.py`` is the package's own).  Imports under ``if TYPE_CHECKING:``
  count too (the doc allows no exception); ALLOWED_UPWARD lists the few upward imports
  kept for now, each with its reason;
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
LAYER_DOC = Path("docs") / "architecture.md"
LAYER_HEADING = "## Layers, bottom up"
LAYER_NAME = re.compile(r"[A-Za-z_]\w*(/|\.py)")

# Upward imports kept for now: (importing module, imported module) -> why.  An entry that
# no longer matches an import is reported, so the list only shrinks.
ALLOWED_UPWARD: dict[tuple[str, str], str] = {
    ("edgemodbus.cli", "edgemodbus"):
        "--version without an installed distribution reads the package's __version__ "
        "(cli/__init__.py _version); the package's __init__ imports no cli/",
}


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


def _typing_only(tree: ast.Module) -> set[int]:
    """The ids of the import nodes under ``if TYPE_CHECKING:`` (or typing.TYPE_CHECKING)."""
    found: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in (
                "TYPE_CHECKING", "typing.TYPE_CHECKING"):
            found.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return found


def imports(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, str, int]]:
    """(imported module, imported name or "", line) for every edgemodbus import in ``path``."""
    return [(target, name, line) for target, name, line, _ in typed_imports(module, path, modules)]


def typed_imports(
    module: str, path: Path, modules: dict[str, Path]
) -> list[tuple[str, str, int, bool]]:
    """imports(), each with whether it is under ``if TYPE_CHECKING:`` only."""
    tree = ast.parse(path.read_text(), str(path))
    typing_only = _typing_only(tree)
    is_package = path.name == "__init__.py"
    found: list[tuple[str, str, int, bool]] = []
    for node in ast.walk(tree):
        typed = id(node) in typing_only
        if isinstance(node, ast.Import):
            found += [(a.name, "", node.lineno, typed) for a in node.names
                      if a.name.startswith(PACKAGE)]
        elif isinstance(node, ast.ImportFrom):
            source = resolve(module, is_package, node.level, node.module)
            if not source.startswith(PACKAGE):
                continue
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                if sub in modules:  # ``from . import codec`` names a module
                    found.append((sub, "", node.lineno, typed))
                else:
                    found.append((source, alias.name, node.lineno, typed))
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


def layers_of(doc: str) -> list[tuple[str, ...]] | None:
    """The layers of the "Layers, bottom up" diagram, top first, each as the names that
    open its line (``cli/``, ``driver.py  descriptor.py``: the words before the first gap
    of three spaces or more, where the description column starts); None without that
    diagram.  A word there that is no ``folder/`` or ``module.py`` is kept as it is, for
    layer_problems to report."""
    lines = doc.splitlines()
    if LAYER_HEADING not in lines:
        return None
    fences = [i for i in range(lines.index(LAYER_HEADING), len(lines))
              if lines[i].startswith("```")][:2]
    if len(fences) < 2:
        return None
    layers: list[tuple[str, ...]] = []
    for line in lines[fences[0] + 1:fences[1]]:
        if not line.startswith(" ") or line.startswith("  "):
            continue  # a description going on under its layer's line
        layers.append(tuple(re.split(r" {3,}", line.strip(), maxsplit=1)[0].split()))
    return layers


def layer_key(path: Path, package: Path) -> str:
    """The diagram's name of the layer of the module at ``path``: ``poll/`` for
    poll/planner.py and poll/__init__.py, ``driver.py``, ``__init__.py`` for the
    package's own."""
    first = path.relative_to(package).parts[0]
    return first if first.endswith(".py") else f"{first}/"


def layer_problems(
    top: Path, allowed: dict[tuple[str, str], str] = ALLOWED_UPWARD
) -> list[str]:
    """Imports from a higher layer than the importer's, in the order of the diagram of
    docs/architecture.md, but for those ``allowed``; names of the diagram that name
    nothing; modules it misses; ``allowed`` entries that match no import."""
    doc_path = top / LAYER_DOC
    layers = layers_of(doc_path.read_text()) if doc_path.is_file() else None
    if not layers:
        return [f"{LAYER_DOC}: no {LAYER_HEADING!r} diagram to check the layer order against"]
    root = top / "src"
    package = root / PACKAGE
    modules = {module_name(p, root): p for p in package.rglob("*.py")}
    rank: dict[str, int] = {}
    problems: list[str] = []
    for index, names in enumerate(layers):
        for name in names:
            if not LAYER_NAME.fullmatch(name):
                problems.append(f"{LAYER_DOC}: {name!r} opens line {index + 1} of the layer "
                                "diagram: a layer is named by folder/ and module.py words")
                continue
            if name in rank:
                problems.append(f"{LAYER_DOC}: {name} is in two layers of the diagram")
            rank[name] = index
            if not ((package / name).exists() or (top / name).exists()):
                problems.append(f"{LAYER_DOC}: {name} in the layer diagram names nothing in "
                                f"src/{PACKAGE}/ (nor at the top)")
    unplaced = sorted({layer_key(p, package) for p in modules.values()} - set(rank))
    problems += [f"src/{PACKAGE}/{key}: not in the layer diagram of {LAYER_DOC} (place it "
                 "there)" for key in unplaced]
    found = {m: typed_imports(m, p, modules) for m, p in modules.items()}
    for module, path in sorted(modules.items()):
        key = layer_key(path, package)
        where = path.relative_to(top)
        seen: set[tuple[str, int]] = set()
        for target, _name, line, typed in found[module]:
            if target not in modules or (target, line) in seen:
                continue
            seen.add((target, line))
            other = layer_key(modules[target], package)
            if key not in rank or other not in rank or rank[other] >= rank[key]:
                continue
            if (module, target) in allowed:
                continue
            how = " (under TYPE_CHECKING, which counts too)" if typed else ""
            problems.append(f"{where}:{line}: {module} (layer {key}) imports {target} of "
                            f"layer {other}, above it in {LAYER_DOC}{how}")
    used = {(m, i[0]) for m, imported in found.items() for i in imported}
    problems += [f"tools/check_layout.py: ALLOWED_UPWARD lists {m} -> {t}, an import that "
                 "is no longer there" for m, t in sorted(set(allowed) - used)]
    return problems


def main() -> int:
    problems = check(TOP) + layer_problems(TOP) + c_problems(TOP)
    for problem in problems:
        print(problem)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
