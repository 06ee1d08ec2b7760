"""The house's limits, as specs: no function in the package (tests aside) longer than 100 lines, with more than 25
branches or more than 12 parameters, and no module importing another module's private name. A function past them
is split, a long parameter list becomes a settings record, a private helper another module needs becomes public."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1]
SKIP = {"tests", ".venv", "logs", "build", "msdgrasp.egg-info", "__pycache__"}
MAX_LINES, MAX_BRANCHES, MAX_PARAMS = 100, 25, 12
#: the branch points counted: if, for, while, try, except, with and conditional expressions (and their async forms)
BRANCH_NODES = (ast.If, ast.For, ast.AsyncFor, ast.While, ast.Try, ast.ExceptHandler, ast.With, ast.AsyncWith,
                ast.IfExp)


def package_sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if not SKIP & set(p.relative_to(PACKAGE).parts))


def branches(fn: ast.AST) -> int:
    """Branch points of a function, nested functions included: statements above, each extra operand of a boolean
    operator, and each for and if of a comprehension."""
    n = 0
    for node in ast.walk(fn):
        if isinstance(node, BRANCH_NODES):
            n += 1
        elif isinstance(node, ast.BoolOp):
            n += len(node.values) - 1
        elif isinstance(node, ast.comprehension):
            n += 1 + len(node.ifs)
    return n


def parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = fn.args
    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
    first = (a.posonlyargs + a.args)[:1]
    return n - (1 if first and first[0].arg in ("self", "cls") else 0)


def functions() -> list[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    out = []
    for path in package_sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out.append((f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name}", node))
    return out


def private_imports(tree: ast.AST) -> list[str]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            found += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")
                      and not a.name.startswith("__")]
            if node.module and any(part.startswith("_") and not part.startswith("__")
                                   for part in node.module.split(".")):
                found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names if any(part.startswith("_") and not part.startswith("__")
                                                        for part in a.name.split(".")[1:])]
    return found


def test_the_counters_see_what_they_count():
    src = "def f(self, a, b=1, *c, d, **e):\n    if a and b or d:\n        return [x for x in c if x]\n" \
          "    try:\n        pass\n    except ValueError:\n        pass\n    return 1 if a else 2\n"
    fn = ast.parse(src).body[0]
    assert parameters(fn) == 5  # self aside
    assert branches(fn) == 1 + 2 + 2 + 1 + 1 + 1  # if, two boolean operands, comprehension for+if, try, except, ifexp


def test_the_private_import_finder_finds_each_form():
    tree = ast.parse("from msdgrasp.a import _b, c, __version__\nimport msdgrasp._y\nfrom ._z import w\n")
    assert private_imports(tree) == ["msdgrasp.a._b", "msdgrasp._y", "_z"]


@pytest.mark.parametrize("limit, measure, name", [(MAX_LINES, lambda f: f.end_lineno - f.lineno + 1, "lines"),
                                                  (MAX_BRANCHES, branches, "branches"),
                                                  (MAX_PARAMS, parameters, "parameters")])
def test_no_function_passes_the_house_limits(limit, measure, name):
    over = [f"{where}: {measure(fn)} {name}" for where, fn in functions() if measure(fn) > limit]
    assert not over, f"over {limit} {name}: " + "; ".join(over)


def test_no_module_imports_another_modules_private_name():
    found = {str(p.relative_to(PACKAGE)): private_imports(ast.parse(p.read_text())) for p in package_sources()}
    assert not {k: v for k, v in found.items() if v}
