"""The import graph follows the layers of docs/architecture.md.

Imports point down only: the kernel (the modules at the top of ``bforest_core``) imports nothing of
the subpackages; ``pipeline`` imports the kernel; ``report`` reads runs through the pipeline;
``cli`` may use everything; ``testing`` (the conformance kit) stands on the kernel alone. The core
never imports a plugin, and a plugin imports the core and itself, never another plugin. Every
import counts, also those inside functions.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = "bforest_core"

#: layer -> layers it may import ("facade" is bforest_core/__init__.py, the public face)
ALLOWED = {
    "kernel": {"kernel"},
    "pipeline": {"kernel", "pipeline"},
    "facade": {"kernel", "pipeline", "facade"},
    "report": {"kernel", "pipeline", "report", "facade"},
    "testing": {"kernel", "testing"},
    "cli": {"kernel", "pipeline", "report", "testing", "cli", "facade"},
}
SUBPACKAGES = ("pipeline", "report", "cli", "testing")


def module_name(path: Path, top: Path) -> str:
    rel = path.relative_to(top).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imported_modules(path: Path, name: str) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a file, relative imports resolved."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
                if node.module is None:  # from . import x: x may be a module
                    out += [(node.lineno, f"{mod}.{a.name}") for a in node.names]
                    continue
            else:
                mod = node.module
            out.append((node.lineno, mod))
    return out


def _module_or_package(mod: str, top: Path) -> str:
    """``pkg.name`` from ``from pkg import name``: the module if it is one, else the package."""
    path = top.joinpath(*mod.split("."))
    if "." not in mod or path.with_suffix(".py").exists() or (path / "__init__.py").exists() or not top.joinpath(
            *mod.split(".")[:-1]).is_dir():
        return mod
    return mod.rpartition(".")[0]


def core_layer(module: str, core: str = CORE) -> str | None:
    """Layer of a module of the core (None for modules outside it)."""
    parts = module.split(".")
    if parts[0] != core:
        return None
    if len(parts) == 1:
        return "facade"
    if parts[1] in SUBPACKAGES:
        return parts[1]
    return "kernel"


def violations(core_dir: Path, plugin_dirs: list[Path]) -> list[str]:
    """Every import that breaks the layering, as ``file:line: problem``."""
    out = []
    core = core_dir.name
    for f in sorted(core_dir.rglob("*.py")):
        name = module_name(f, core_dir.parent)
        mine = core_layer(name, core)
        for line, mod in imported_modules(f, name):
            mod = _module_or_package(mod, core_dir.parent)
            top = mod.split(".")[0]
            where = f"{f.relative_to(core_dir.parent)}:{line}"
            if top.startswith("bforest_") and top != core:
                out.append(f"{where}: the core imports the plugin {mod}")
                continue
            theirs = core_layer(mod, core)
            if theirs is not None and theirs not in ALLOWED[mine]:
                out.append(f"{where}: {mine} imports {theirs} ({mod})")
    for pdir in plugin_dirs:
        own = pdir.name
        for f in sorted(pdir.rglob("*.py")):
            name = module_name(f, pdir.parent)
            for line, mod in imported_modules(f, name):
                top = mod.split(".")[0]
                if top.startswith("bforest_") and top not in (own, core):
                    out.append(f"{f.relative_to(pdir.parent)}:{line}: plugin {own} imports plugin {mod}")
    return out


def plugin_packages() -> list[Path]:
    dirs = sorted(p for p in (ROOT / "plugins").iterdir() if (p / "__init__.py").exists())
    example = ROOT / "docs" / "examples" / "bforest-example-ssm" / "bforest_example_ssm"
    return dirs + ([example] if example.exists() else [])


def test_the_project_keeps_its_layers():
    found = violations(ROOT / CORE, plugin_packages())
    assert not found, "imports against the layering:\n" + "\n".join(found)


# ------------------------------------------------------------------ the check itself can fail
def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


GOOD = {
    "bforest_core/__init__.py": "from .tree import Tree\nfrom .pipeline.fit import fit\n",
    "bforest_core/tree.py": "import numpy as np\n",
    "bforest_core/pipeline/__init__.py": "",
    "bforest_core/pipeline/fit.py": "from ..tree import Tree\nfrom .store import x\n",
    "bforest_core/pipeline/store.py": "x = 1\n",
    "bforest_core/report/__init__.py": "from ..pipeline.store import x\nfrom .. import __version__\n",
    "bforest_core/cli/__init__.py": "from ..report import y\n",
    "plugins/bforest_a/__init__.py": "import bforest_core as bf\nfrom .m import z\n",
    "plugins/bforest_a/m.py": "z = 1\n",
}


@pytest.mark.parametrize("rel, text, expected", [
    ("bforest_core/tree.py", "def f():\n    from .pipeline.fit import fit\n", "kernel imports pipeline"),
    ("bforest_core/pipeline/store.py", "from ..report import y\n", "pipeline imports report"),
    ("bforest_core/pipeline/store.py", "import bforest_core.cli\n", "pipeline imports cli"),
    ("bforest_core/pipeline/store.py", "from .. import fit\n", "pipeline imports facade"),
    ("bforest_core/tree.py", "import bforest_a\n", "the core imports the plugin bforest_a"),
    ("plugins/bforest_a/m.py", "from bforest_b.x import y\n", "plugin bforest_a imports plugin bforest_b.x"),
])
def test_the_check_finds_each_kind_of_violation(tmp_path, rel, text, expected):
    _write(tmp_path, GOOD)
    assert violations(tmp_path / "bforest_core", [tmp_path / "plugins" / "bforest_a"]) == []
    _write(tmp_path, {rel: text})
    found = violations(tmp_path / "bforest_core", [tmp_path / "plugins" / "bforest_a"])
    assert len(found) == 1 and expected in found[0], found
