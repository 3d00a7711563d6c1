"""The package's architecture is enforced, not hoped for.

* The import-linter contracts of ``pyproject.toml`` (each folder of ``src/pocoloco`` imports only the
  folders below it; the methods' folders are independent) hold, and would fail on an upward import
  (checked on a copy of the package with one injected).
* No import cycles between modules, no private names imported across modules, no function-local
  imports of pocoloco modules (they hid cycles) except of the data-generation extra.
* No module longer than ~600 lines without a reason at its top.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "pocoloco"
#: the only pocoloco modules another module may import inside a function: those of the optional
#: ``synth`` extra (newton, warp, open3d at import time: the rest runs without it) and the anny
#: adapter (``import pocoloco.body`` stays instant; anny parses its assets on first use)
OPTIONAL_EXTRA_MODULES = {"pocoloco.synth.pipeline", "pocoloco.synth.cloth_sim", "pocoloco.synth.capture",
                          "pocoloco.synth.sdf", "pocoloco.synth.garments", "pocoloco.synth.motion", "pocoloco.synth.aero",
                          "pocoloco.synth.vbd_chebyshev", "pocoloco.synth.bend_friction",
                          "pocoloco.synth.tension_field",
                          "pocoloco.body.anny_body", "pocoloco.body"}  # fmt: skip
MAX_LINES = 650
REASON_MARK = "Why this module is long:"


def _lint_imports(cwd: Path, pythonpath: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-c", "from importlinter.cli import lint_imports_command; "
                                                                  "lint_imports_command()"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run([*cmd, "--no-cache"], cwd=cwd, capture_output=True, text=True, env=env, timeout=300)


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(parts), path))
    return out


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module name of a ``from ... import`` (relative ones resolved)."""
    if not node.level:
        return node.module or ""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


# -------------------------------------------------------------------------------- import-linter
def test_layer_contracts_hold():
    r = _lint_imports(ROOT, ROOT / "src")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "2 kept, 0 broken" in r.stdout


@pytest.mark.parametrize("victim, injected, broken", [
    ("ops/knn.py", "import pocoloco.cli  # noqa", "layers"),               # the lowest layer reaching the top
    ("data/dataset.py", "from pocoloco.methods import load_method  # noqa", "layers"),
    ("methods/pop/losses.py", "import pocoloco.methods.closet.losses  # noqa", "methods"),
    ("methods/pop/data.py", "import pocoloco.methods.hybrid.regions  # noqa", "methods"),
])  # fmt: skip
def test_contracts_fail_on_an_upward_import(tmp_path, victim, injected, broken):
    """The contracts are not vacuous: one injected import into a copy of the package breaks them."""
    shutil.copytree(SRC, tmp_path / "src" / "pocoloco", ignore=shutil.ignore_patterns("assets", "__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / "src" / "pocoloco" / victim
    target.write_text(target.read_text() + f"\n{injected}\n")
    r = _lint_imports(tmp_path, tmp_path / "src")
    assert r.returncode != 0 and "BROKEN" in r.stdout, r.stdout[-2000:]
    assert broken in r.stdout


# ------------------------------------------------------------------------------------ the AST
def test_no_import_cycles_between_modules():
    """Tarjan's strongly connected components of the module import graph (module-level imports)."""
    names = {m for m, _ in _modules()}
    graph: dict[str, set[str]] = {m: set() for m in names}
    for module, path in _modules():
        for node in ast.parse(path.read_text()).body:  # module level only
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(module, path, node)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in names else base for a in node.names]
            for t in targets:
                while t and t not in names:
                    t = t.rpartition(".")[0]
                if t and t != module and not module.startswith(t + "."):  # a package importing itself via a child
                    graph[module].add(t)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_no_private_names_used_across_modules():
    """Neither ``from pocoloco.x import _private`` nor ``x._private`` on an imported pocoloco module."""
    names = {m for m, _ in _modules()}
    private = lambda n: n.startswith("_") and not n.startswith("__")  # noqa: E731
    bad = []
    for module, path in _modules():
        tree = ast.parse(path.read_text())
        aliases = {}  # local name -> pocoloco module it is bound to
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and _resolve(module, path, node).startswith("pocoloco"):
                base = _resolve(module, path, node)
                bad += [f"{module}: from {base} import {a.name}" for a in node.names if private(a.name)]
                aliases.update({a.asname or a.name: f"{base}.{a.name}" for a in node.names
                                if f"{base}.{a.name}" in names})  # fmt: skip
            elif isinstance(node, ast.Import):
                aliases.update({a.asname: a.name for a in node.names if a.asname and a.name.startswith("pocoloco")})
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and private(node.attr) and isinstance(node.value, ast.Name) \
                    and node.value.id in aliases:  # fmt: skip
                bad.append(f"{module}: {node.value.id}.{node.attr} ({aliases[node.value.id]})")
    assert not bad, bad


def test_no_function_local_imports_of_pocoloco_modules():
    """Imports inside functions hid cycles; only the optional data-generation extra and anny are lazy."""
    bad = []
    for module, path in _modules():
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom):
                    target = _resolve(module, path, node)
                    if node.module is None:  # from . import submodule
                        target = f"{target}.{node.names[0].name}"
                elif isinstance(node, ast.Import):
                    target = node.names[0].name
                else:
                    continue
                if target.startswith("pocoloco") and target not in OPTIONAL_EXTRA_MODULES:
                    bad.append(f"{module}.{fn.name}: imports {target}")
    assert not bad, bad


def test_long_modules_say_why():
    long = []
    for module, path in _modules():
        text = path.read_text()
        n = text.count("\n")
        doc = ast.get_docstring(ast.parse(text)) or ""
        if n > MAX_LINES and REASON_MARK not in doc:
            long.append(f"{module}: {n} lines")
    assert not long, f"modules over {MAX_LINES} lines need '{REASON_MARK} ...' in their docstring: {long}"


def test_the_library_never_imports_the_cli():
    bad = []
    for module, path in _modules():
        if module.startswith(("pocoloco.cli", "pocoloco.__main__")):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [_resolve(module, path, node)] if isinstance(node, ast.ImportFrom) else [])  # fmt: skip
            bad += [f"{module} imports {n}" for n in names if n == "pocoloco.cli" or n.startswith("pocoloco.cli.")]
    assert not bad, bad


def test_declared_dependencies_match_the_imports():
    """deptry: every import of the package is declared, and every declared dependency is imported."""
    exe = Path(sys.executable).with_name("deptry")
    if not exe.exists():
        pytest.skip("deptry is not installed (pip install -e '.[dev]')")
    r = subprocess.run([str(exe), "src"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
