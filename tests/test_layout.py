"""The house: the floors' import contract, the linter, sizes a reader can hold, no private name borrowed.

The contracts and the linter's rules live in pyproject.toml ([tool.importlinter], [tool.ruff]); docs/guide.md
("The house") draws the same floors.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ashc_cli"
BIN = Path(sys.executable).parent

#: A module or function a reader can hold; the debts below may shrink, never grow, and leave the list when paid.
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 100
MODULE_DEBTS = {
}
FUNCTION_DEBTS = {
}


def _tool(name: str) -> str:
    found = BIN / name
    return str(found) if found.exists() else (shutil.which(name) or pytest.fail(f"{name} is not installed (it is in the test extra)"))


def test_floors_import_one_way_and_stages_stay_apart():
    proc = subprocess.run([_tool("lint-imports")], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "2 kept, 0 broken" in proc.stdout


def test_a_broken_floor_is_caught(tmp_path):
    # the contract can fail: a design module importing the CLI is reported
    probe = PACKAGE / "design" / "_layout_probe.py"
    probe.write_text("from ashc_cli import cli  # noqa: F401\n")
    try:
        proc = subprocess.run([_tool("lint-imports"), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    finally:
        probe.unlink()
    assert proc.returncode != 0 and "ashc_cli.design._layout_probe -> ashc_cli.cli" in proc.stdout


def _cycles(package: str) -> list[list[str]]:
    """The import cycles among a package's modules (strongly connected components of grimp's graph, imports inside
    functions included, those under ``if TYPE_CHECKING`` left out), each sorted."""
    import grimp

    graph = grimp.build_graph(package, exclude_type_checking_imports=True, cache_dir=None)
    index: dict = {}
    low: dict = {}
    stack: list = []
    on: set = set()
    found = []
    for root in sorted(graph.modules):          # Tarjan's algorithm, iterative (the graph has hundreds of modules)
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.find_modules_directly_imported_by(w)))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_no_import_cycle():
    # The floors contract cannot see a cycle inside one floor (problem/spec.py <-> problem/spec_checks.py was one).
    assert _cycles("ashc_cli") == []


def test_a_cycle_is_caught(tmp_path, monkeypatch):
    pkg = tmp_path / "cyclepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from cyclepkg import b\n")
    (pkg / "b.py").write_text("def f():\n    from cyclepkg import a\n    return a\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from cyclepkg import d\n")
    (pkg / "d.py").write_text("from cyclepkg import c\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert _cycles("cyclepkg") == [["cyclepkg.a", "cyclepkg.b"]]


def test_ruff_passes():
    proc = subprocess.run([_tool("ruff"), "check", "--no-cache", "ashc_cli", "tests", "bench", "docs"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-4000:]


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE).as_posix(), path.read_text()


def test_modules_and_functions_a_reader_can_hold():
    too_long, paid = [], []
    for rel, text in _modules():
        lines = text.count("\n")
        limit = MODULE_DEBTS.get(rel, MAX_MODULE_LINES)
        if lines > limit:
            too_long.append(f"{rel}: {lines} lines (at most {limit})")
        if rel in MODULE_DEBTS and lines <= MAX_MODULE_LINES:
            paid.append(rel)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                key, length = f"{rel}:{node.name}", node.end_lineno - node.lineno + 1
                limit = FUNCTION_DEBTS.get(key, MAX_FUNCTION_LINES)
                if length > limit:
                    too_long.append(f"{key}: {length} lines (at most {limit})")
    paid += [key for key in FUNCTION_DEBTS if not _still_long(key)]
    assert not too_long, too_long
    assert not paid, f"paid debts, take them off the lists: {paid}"


#: Arguments beyond this travel in a named bundle (docs/guide.md, "Compiled closed loops").
MAX_PARAMETERS = 12


def _parameters(node: ast.FunctionDef) -> int:
    """The parameters a function takes (self and cls not counted; *args and **kwargs count one each)."""
    a = node.args
    count = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
    return count - (1 if a.args and a.args[0].arg in ("self", "cls") else 0)


def _long_signatures(text: str, rel: str) -> list[str]:
    return [f"{rel}:{node.name} takes {_parameters(node)}" for node in ast.walk(ast.parse(text))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _parameters(node) > MAX_PARAMETERS]


def test_no_function_takes_more_than_twelve_parameters():
    found = [line for rel, text in _modules() for line in _long_signatures(text, rel)]
    assert not found, found


def test_a_long_signature_is_caught():
    text = "def run(a, b, c, d, e, f, g, h, i, j, k, l, m):\n    pass\n\n\nclass C:\n    def ok(self, a, b, c, d, e, f, g, h, i, j, k, l):\n        pass\n"
    assert _long_signatures(text, "probe.py") == ["probe.py:run takes 13"]


def _still_long(key: str) -> bool:
    rel, name = key.split(":")
    tree = ast.parse((PACKAGE / rel).read_text())
    return any(isinstance(n, ast.FunctionDef) and n.name == name and n.end_lineno - n.lineno + 1 > MAX_FUNCTION_LINES for n in ast.walk(tree))


def _is_module(dotted: str) -> bool:
    path = ROOT.joinpath(*dotted.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def test_no_private_name_is_borrowed_across_modules():
    borrowed = []
    for rel, text in _modules():
        tree = ast.parse(text)
        modules = set()        # local names bound to ashc modules: `from ashc_cli.design import pipeline`
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ashc_cli"):
                borrowed += [f"{rel}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                modules |= {a.asname or a.name for a in node.names if _is_module(f"{node.module}.{a.name}")}
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules:
                if node.attr.startswith("_") and not node.attr.startswith("__"):
                    borrowed.append(f"{rel}: {node.value.id}.{node.attr}")
    assert not borrowed, borrowed


def test_every_exception_class_lives_in_errors():
    strays = []
    for rel, text in _modules():
        if rel == "errors.py":
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and any(getattr(b, "id", getattr(b, "attr", "")).endswith(("Error", "Exception")) for b in node.bases):
                strays.append(f"{rel}: {node.name}")
    assert not strays, strays


def _is_private_module(rel: str) -> bool:
    """A module whose file name starts with ``_`` (not ``__init__``): its package's implementation, not public API."""
    name = rel.rsplit("/", 1)[-1]
    return name.startswith("_") and not name.startswith("__")


def test_a_private_module_is_imported_only_by_its_own_package():
    strays = []
    for rel, text in _modules():
        package = rel.rsplit("/", 1)[0] if "/" in rel else ""
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ashc_cli"):
                parts = node.module.split(".")[1:]
                if parts and parts[-1].startswith("_") and not parts[-1].startswith("__") and "/".join(parts[:-1]) != package:
                    strays.append(f"{rel}: {node.module}")
    assert not strays, strays


def _public_functions():
    """Module-level public functions of the public modules (a private module's functions are not API)."""
    for rel, text in _modules():
        if _is_private_module(rel):
            continue
        for node in ast.parse(text).body:
            if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
                yield rel, node


def _documented_names(doc: str) -> list[str]:
    """The names a numpydoc Parameters section lists (``a, b : type`` lines at the section's indentation)."""
    lines = doc.splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Parameters" and lines[i + 1].strip().startswith("---"))
    except StopIteration:
        return []
    names = []
    for line in lines[start + 2:]:
        if not line.strip():
            continue
        if line.strip().startswith("---"):          # the next section's underline: the previous line was its title
            names.pop()
            break
        if not line.startswith(" "):
            head = line.split(" : ")[0] if " : " in line else line.strip()
            names += [n.strip().lstrip("*") for n in head.split(",") if n.strip()]
    return names


def _is_command(node: ast.FunctionDef) -> bool:
    """A typer command: its docstring is its --help, its parameters are documented by their options (docs/cli.md)."""
    return any(isinstance(d, ast.Call) and isinstance(d.func, ast.Attribute) and d.func.attr == "command" for d in node.decorator_list)


def test_every_public_function_has_a_docstring_and_its_parameters_exist():
    missing, wrong, undocumented = [], [], []
    for rel, node in _public_functions():
        doc = ast.get_docstring(node)
        if not doc:
            missing.append(f"{rel}:{node.name}")
            continue
        args = {a.arg for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs}
        args |= {a.arg for a in (node.args.vararg, node.args.kwarg) if a is not None}
        documented = _documented_names(doc)
        wrong += [f"{rel}:{node.name}({name})" for name in documented if name not in args]
        if args - {"self", "cls"} and not documented and not _is_command(node):
            undocumented.append(f"{rel}:{node.name}")
    assert not missing, missing
    assert not wrong, f"documented parameters the function does not take: {wrong}"
    assert not undocumented, f"public functions without a numpydoc Parameters section: {undocumented}"


def test_the_parameters_parser_reads_numpydoc():
    doc = "Do it.\n\nParameters\n----------\na, b : int\n    The ends.\n*args : float\n    More.\n\nReturns\n-------\nint\n    The sum.\n"
    assert _documented_names(doc) == ["a", "b", "args"]
    assert _documented_names("No sections.") == []


def test_the_code_cites_the_papers_numbers_not_its_labels():
    import re

    from ashc_cli.paper import LABELS, cite

    # the camel-case labels ("SimuLocalRequire", "egLMI") wherever they stand, and any citation cite() rewrites
    camel = re.compile(r"\b(" + "|".join(sorted((re.escape(k) for k in LABELS if re.search(r"[a-z][A-Z]", k) and ":" not in k), key=len, reverse=True)) + r")\b")
    labelled = [f"{rel}: {sorted(set(camel.findall(text)))}" for rel, text in _modules()
                if rel != "paper.py" and (cite(text) != text or camel.search(text))]
    assert not labelled, f"LaTeX labels of the paper in {labelled}: write the paper's numbers (ashc_cli.paper.cite does most)"


def test_no_module_defines_a_name_twice():
    # the second definition silently replaces the first (ruff does not see it when the first is called later)
    twice = []
    for rel, text in _modules():
        names = [n.name for n in ast.parse(text).body if isinstance(n, (ast.FunctionDef, ast.ClassDef))]
        twice += [f"{rel}: {name}" for name in sorted(set(names)) if names.count(name) > 1]
    assert not twice, twice


def test_the_package_metadata_is_in_the_current_form():
    # A table license and a licence classifier made setuptools print about 60 lines of deprecation warnings on every
    # install (issue 39); PEP 639 wants an SPDX expression and the licence files.
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert not [c for c in project["classifiers"] if c.startswith("License ::")]


#: The engine's step: the stages, the error norm, the step-size rule (closedloop/rk.py); nothing else takes one.
RK_STEP = {"stage_input", "error_norm", "step_factor", "attempt", "_combine", "_combine_b"}


def _rk_steps_in(text: str) -> set[str]:
    """The names of the engine's step that a module's source reads or imports."""
    found = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Name) and node.id in RK_STEP:
            found.add(node.id)
        elif isinstance(node, ast.Attribute) and node.attr in RK_STEP:
            found.add(node.attr)
        elif isinstance(node, ast.ImportFrom):
            found |= {a.name for a in node.names if a.name in RK_STEP}
    return found


def test_only_the_engine_takes_a_runge_kutta_step():
    # one step driver (closedloop/rk.py): the tracking loops through rk.solve, falsify's holds through rk.hold,
    # the task plan's fixed step through rk.fixed_step
    steps = {rel: found for rel, text in _modules() if rel != "closedloop/rk.py" and (found := _rk_steps_in(text))}
    assert not steps, steps


def test_a_runge_kutta_step_outside_the_engine_is_caught():
    text = "from ashc_cli.closedloop.rk import error_norm, stage_input\n\ndef f(tab, s, h, y, K, out):\n    stage_input(tab, s, h, y, K, out)\n"
    assert _rk_steps_in(text) == {"error_norm", "stage_input"}
