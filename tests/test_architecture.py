"""The shape of the library, checked from its source (fast: no module is imported, only parsed):

- the import graph of ``toggle_id`` (module-level imports, the package ``__init__`` a module passes through
  included) has no cycle;
- no module of ``toggle_id`` imports Hydra or OmegaConf (configs reach the library as plain values);
- no module of ``toggle_id`` outside the application layer ``toggle_id/app/`` imports it, at module level or inside
  a function (the jobs sit on the library, never the reverse), and every job ``jobs/run.py`` dispatches to is a
  function of that layer;
- no module is longer than its limit (the compiled integrators may be longer than the rest).

``python tests/test_architecture.py`` prints the graph (module-level imports, then the function-level ones) as
``docs/architecture.md`` shows it.
"""
from __future__ import annotations

import ast
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "toggle_id"

#: Longest module (lines) of the library, and of the compiled integrators.
MAX_LINES = 500
MAX_LINES_INTEGRATORS = 700
INTEGRATORS = frozenset({"toggle_id/kernels/rigid.py", "toggle_id/kernels/backlash.py"})
#: Modules still over MAX_LINES, each with what is to become of it (issue 15); none may be added.
KNOWN_OVER_LIMIT = {
}
#: Top-level packages the library must never import.
FORBIDDEN = ("hydra", "omegaconf")
#: The application layer (the jobs): only its own modules (and jobs/, tests/) import it.
APP = f"{PACKAGE}.app"


def module_files() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package."""
    out = {}
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_package(name: str, modules: dict[str, Path]) -> bool:
    return modules[name].name == "__init__.py"


def _resolve(importer: str, node: ast.ImportFrom | ast.Import, modules: dict[str, Path]) -> list[str]:
    """The package's modules one import statement names (``from a import b`` names ``a.b`` when b is a module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name in modules]
    if node.level:
        base = importer.split(".")
        if not _is_package(importer, modules):
            base = base[:-1]
        base = base[:len(base) - (node.level - 1)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if target not in modules:
        return []
    subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules]
    return subs if len(subs) == len(node.names) else [target, *subs]


def _type_checking(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and (
        (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
        or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"))


def _imports(tree: ast.Module) -> tuple[list[ast.stmt], list[ast.stmt]]:
    """(module-level import statements, those inside functions); ``if TYPE_CHECKING:`` blocks are skipped."""
    top, lazy = [], []

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if _type_checking(child):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                (lazy if in_function else top).append(child)
            walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(tree, False)
    return top, lazy


def import_graph(lazy: bool = False) -> dict[str, set[str]]:
    """Module -> the package's modules it imports at module level (``lazy``: inside functions instead). Importing
    ``a.b.c`` runs ``a/b/__init__.py`` first, so a module outside ``a.b`` also depends on that package."""
    modules = module_files()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m, path in modules.items():
        top, inner = _imports(ast.parse(path.read_text(encoding="utf-8")))
        for node in inner if lazy else top:
            for target in _resolve(m, node, modules):
                parts = target.split(".")
                for k in range(2, len(parts) + 1):
                    dep = ".".join(parts[:k])
                    if dep != m and not (dep != target and (m + ".").startswith(dep + ".")):
                        graph[m].add(dep)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first repeated last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state:
                found = visit(d)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def forbidden_imports() -> list[str]:
    """``file: module`` for every import (at any level) of a FORBIDDEN package in the library."""
    bad = []
    for m, path in module_files().items():
        top, inner = _imports(ast.parse(path.read_text(encoding="utf-8")))
        for node in top + inner:
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            if isinstance(node, ast.ImportFrom) and node.level:
                continue
            bad += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in FORBIDDEN]
    return bad


def _in_app(module: str) -> bool:
    return module == APP or module.startswith(APP + ".")


def app_imports() -> list[str]:
    """``module -> app module`` for every import of the application layer (at any level) by a module outside it."""
    bad = []
    for lazy in (False, True):
        for m, deps in import_graph(lazy).items():
            if not _in_app(m):
                bad += [f"{_short(m)} -> {_short(d)}" for d in sorted(deps) if _in_app(d)]
    return bad


def _literal(path: Path, name: str):
    """The literal value assigned to the module-level ``name`` in ``path`` (parsed, not imported)."""
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        targets = (node.targets if isinstance(node, ast.Assign) else
                   [node.target] if isinstance(node, ast.AnnAssign) else [])
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            return ast.literal_eval(node.value)
    raise LookupError(f"{path}: no module-level {name}")


def _functions(path: Path) -> set[str]:
    return {n.name for n in ast.parse(path.read_text(encoding="utf-8")).body if isinstance(n, ast.FunctionDef)}


def line_counts() -> dict[str, int]:
    """Lines of every module of the library and of the jobs (``jobs/`` stays thin: its modules keep the limit too)."""
    paths = [*module_files().values(), *sorted((ROOT / "jobs").glob("*.py"))]
    return {str(p.relative_to(ROOT)): len(p.read_text(encoding="utf-8").splitlines()) for p in paths}


def limit(path: str) -> int:
    return MAX_LINES_INTEGRATORS if path in INTEGRATORS else MAX_LINES


# ---- tests ----------------------------------------------------------------------------------------------------


def test_graph_sees_the_imports():
    g = import_graph()
    assert "toggle_id.kernels.slots" in g["toggle_id.kernels.rigid"]
    assert "toggle_id.kernels" in g["toggle_id.simulate"]  # through the package's __init__
    assert "toggle_id.ga_operators" in g["toggle_id.ga"]
    assert "toggle_id.ga" not in g["toggle_id.ga_operators"]  # its import sits under `if TYPE_CHECKING:`
    assert "toggle_id.app.common" in g["toggle_id.app.identify"]
    assert "toggle_id.evaluators" in import_graph(lazy=True)["toggle_id.app.common"]  # inside a function
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_library_never_imports_hydra():
    assert forbidden_imports() == []


def test_library_never_imports_the_app_layer():
    assert app_imports() == [], "the library imports the application layer (toggle_id/app/)"


def test_every_job_runs_an_app_function():
    dispatch = _literal(ROOT / "jobs" / "run.py", "JOBS")
    assert tuple(dispatch) == _literal(ROOT / PACKAGE / "app" / "common.py", "JOBS")
    modules = module_files()
    for job, (module, function) in dispatch.items():
        assert _in_app(module) and module in modules, f"job {job}: {module} is not a module of {APP}"
        assert function in _functions(modules[module]), f"job {job}: {module} has no function {function}"


def test_module_lengths():
    counts = line_counts()
    over = {p: n for p, n in counts.items() if n > limit(p) and p not in KNOWN_OVER_LIMIT}
    assert over == {}, f"modules over their limit ({MAX_LINES}, integrators {MAX_LINES_INTEGRATORS}): {over}"


def test_known_over_limit_list_is_current():
    counts = line_counts()
    stale = [p for p in KNOWN_OVER_LIMIT if counts.get(p, 0) <= limit(p)]
    assert stale == [], f"now within the limit or gone: remove {stale} from KNOWN_OVER_LIMIT"


# ---- the graph as docs/architecture.md shows it ---------------------------------------------------------------


def _short(m: str) -> str:
    return m[len(PACKAGE) + 1:] if m.startswith(PACKAGE + ".") else m


def render(graph: dict[str, set[str]]) -> str:
    """One line per module: ``module <- the package's modules it imports``, in an order where every module comes
    after what it imports (a topological order; alphabetical among equals)."""
    order, done = [], set()
    while len(order) < len(graph):
        ready = sorted(m for m in graph if m not in done and graph[m] <= done)
        if not ready:  # a cycle: list the rest as they are
            ready = sorted(m for m in graph if m not in done)
        order += ready
        done |= set(ready)
    if not graph.get(PACKAGE):  # the root package's __init__, which imports nothing
        order.remove(PACKAGE)
    width = max(len(_short(m)) for m in order)
    lines = []
    for m in order:
        deps = ", ".join(_short(d) for d in sorted(graph[m])) or "-"
        lines += textwrap.wrap(deps, 114, initial_indent=f"{_short(m):<{width}}  <- ",
                               subsequent_indent=" " * (width + 5), break_on_hyphens=False)
    return "\n".join(lines)


if __name__ == "__main__":
    top, lazy = import_graph(), import_graph(lazy=True)
    print(render(top))
    print()
    print("imports inside functions (run when called):")
    for m in sorted(lazy):
        if lazy[m]:
            print("\n".join(textwrap.wrap(", ".join(_short(d) for d in sorted(lazy[m])), 114,
                                           initial_indent=f"  {_short(m)} -> ", subsequent_indent="      ",
                                           break_on_hyphens=False)))
    sys.exit(0)
