"""No import cycle anywhere in the package: every module imports on its own in a fresh interpreter,
and the graph of lsbench-internal imports (function-level imports included, since a lazy import
only hides a cycle) has no cycle."""
from __future__ import annotations

import ast
import pkgutil
import subprocess
import sys
from pathlib import Path

import lsbench

ROOT = Path(lsbench.__file__).resolve().parent


def all_modules() -> list[str]:
    return ["lsbench"] + sorted(m.name for m in pkgutil.walk_packages([str(ROOT)], "lsbench."))


def module_file(name: str) -> Path:
    rel = Path(*name.split(".")[1:])
    pkg = ROOT / rel / "__init__.py"
    return pkg if pkg.is_file() else (ROOT / rel).with_suffix(".py")


def imports_of(name: str, modules: set[str]) -> set[str]:
    """lsbench modules that `name` imports anywhere in its file. `from P import x` counts as an
    import of P.x when that is a module, else of P. A package's own submodules imported by its
    __init__ are not edges back (importing P.x runs P's __init__ first by Python's rules)."""
    path = module_file(name)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        out |= {t for t in targets if t in modules and t != name}
    return out


def test_every_module_imports_on_its_own():
    for name in all_modules():
        if name == "lsbench.__main__":  # runs the command line when imported
            continue
        proc = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, f"import {name}: {proc.stderr.strip().splitlines()[-1:]}"


def test_no_import_cycle():
    modules = set(all_modules())
    graph = {m: imports_of(m, modules) for m in modules}
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append(" -> ".join(path[path.index(n):] + [n]))
            elif n not in state:
                visit(n, path + [n])
        state[m] = 2

    for m in sorted(modules):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)
