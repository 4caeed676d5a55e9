"""The import graph follows the layers of docs/architecture.md.

Imports point down only: the kernel (the modules at the top of ``bforest_core``) imports nothing of
the subpackages; ``pipeline`` imports the kernel; ``report`` reads runs through the pipeline;
``cli`` may use everything; ``testing`` (the conformance kit) stands on the kernel alone. The core
never imports a plugin, and a plugin imports itself and the core's public face (``bforest_core``,
its kernel modules and the conformance kit), never another plugin nor the core's pipeline, report
or cli. Every import counts, also those inside functions; so do dynamic loads
(``importlib.import_module``, ``__import__``) of the project's modules, which only the registry
makes (through entry points). A private name (``_x``) is imported only within its layer (or
package): another layer uses the public names. No module imports itself round a circle of imports
(in the core or a plugin), also not through an import inside a function; only imports under ``if
TYPE_CHECKING:``, which never run, are left out of that.
"""

from __future__ import annotations

import ast
import re
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
#: what a plugin may import of the core: its public face
PLUGIN_ALLOWED = {"facade", "kernel", "testing"}
#: the one module that loads plugins (through entry points)
REGISTRY = "registry"
#: a package that extends a plugin through that plugin's own extension interface (a growth form of
#: SOT: ``bforest_sot.forms``) may import it; the bundled plugins never import each other
EXTENDS = {"bforest_example_sot_form": {"bforest_sot"}}
#: the pipeline modules the report reads a run through: its files (store) and the definitions of
#: what it shows (the posterior, the fidelity table's limits) ...
REPORT_READS = {"store", "posterior", "fidelity"}
#: ... and the report modules that rebuild what was computed but not kept, with the stages that
#: computed it: a run's target, its answer's model seeds and tree, its clones' table
#: (``report/run_view.py``), a stand's plan and its synthetic plot (``report/stand.py``)
REBUILDS = {
    "report.run_view": REPORT_READS | {"seeds", "target", "scoring", "clones"},
    "report.stand": REPORT_READS | {"stand", "synthetic"},
}


def module_name(path: Path, top: Path) -> str:
    rel = path.relative_to(top).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _dynamic_target(node: ast.AST) -> str | None:
    """The target of ``importlib.import_module(...)``/``import_module(...)``/``__import__(...)``:
    the module name when it is a string constant, ``"?"`` when it is computed; None for any other
    expression."""
    if not isinstance(node, ast.Call) or not node.args:
        return None
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    if name not in ("import_module", "__import__"):
        return None
    arg = node.args[0]
    return arg.value if isinstance(arg, ast.Constant) and isinstance(arg.value, str) else "?"


def _type_checking(node: ast.AST) -> bool:
    """An ``if TYPE_CHECKING:`` block (its imports never run)."""
    t = node.test if isinstance(node, ast.If) else None
    return (
        isinstance(t, ast.Name)
        and t.id == "TYPE_CHECKING"
        or isinstance(t, ast.Attribute)
        and t.attr == "TYPE_CHECKING"
    )


def _nodes(tree: ast.AST, runtime: bool):
    """Every node of ``tree`` (``runtime``: leaving out the bodies of ``if TYPE_CHECKING:``)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        if runtime and _type_checking(node):
            todo += node.orelse
        else:
            todo += ast.iter_child_nodes(node)


def imports(path: Path, name: str, runtime: bool = False) -> list[tuple[int, str, list[str], bool]]:
    """``(line, absolute module, names imported from it, dynamic)`` of every import in a file
    (relative imports resolved; ``dynamic``: a call of ``import_module``/``__import__``;
    ``runtime``: imports under ``if TYPE_CHECKING:`` left out)."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    out = []
    for node in _nodes(ast.parse(path.read_text(encoding="utf-8")), runtime):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, [], False) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
                if node.module is None:  # from . import x: x may be a module
                    out += [(node.lineno, f"{mod}.{a.name}", [], False) for a in node.names]
                    continue
            else:
                mod = node.module
            out.append((node.lineno, mod, [a.name for a in node.names], False))
        elif (target := _dynamic_target(node)) is not None:
            out.append((node.lineno, target, [], True))
    return out


def imported_modules(path: Path, name: str) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a file, relative imports resolved."""
    return [(line, mod) for line, mod, _, _ in imports(path, name)]


def _module_or_package(mod: str, top: Path) -> str:
    """``pkg.name`` from ``from pkg import name``: the module if it is one, else the package."""
    path = top.joinpath(*mod.split("."))
    if (
        "." not in mod
        or path.with_suffix(".py").exists()
        or (path / "__init__.py").exists()
        or not top.joinpath(*mod.split(".")[:-1]).is_dir()
    ):
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


def _dynamic_problem(where: str, mod: str, dynamic: bool) -> str | None:
    """A dynamic load of the project's modules (or of a computed name) outside the registry."""
    if dynamic and (mod == "?" or mod.split(".")[0].startswith("bforest")):
        what = "a computed module name" if mod == "?" else mod
        return f"{where}: dynamic import of {what} outside the registry (import it, or register it)"
    return None


def _report_reads(name: str, mod: str, core: str) -> str | None:
    """A report module importing a pipeline module it does not read runs through (None: allowed)."""
    stage = mod.removeprefix(f"{core}.pipeline").lstrip(".")
    if stage in REBUILDS.get(name.removeprefix(f"{core}."), REPORT_READS):
        return None
    return (
        f"the report imports {mod}: it reads a run through pipeline.{', pipeline.'.join(sorted(REPORT_READS))}, "
        f"and rebuilds what was computed in {' and '.join(sorted(REBUILDS))} only"
    )


def violations(core_dir: Path, plugin_dirs: list[Path]) -> list[str]:
    """Every import that breaks the layering, as ``file:line: problem``."""
    out = []
    core = core_dir.name
    for f in sorted(core_dir.rglob("*.py")):
        name = module_name(f, core_dir.parent)
        mine = core_layer(name, core)
        for line, mod, names, dynamic in imports(f, name):
            where = f"{f.relative_to(core_dir.parent)}:{line}"
            if dynamic and name == f"{core}.{REGISTRY}":
                continue  # the registry is where plugins are loaded
            problem = _dynamic_problem(where, mod, dynamic)
            if problem or mod == "?":
                out += [problem] if problem else []
                continue
            mod = _module_or_package(mod, core_dir.parent)
            top = mod.split(".")[0]
            if top.startswith("bforest_") and top != core:
                out.append(f"{where}: the core imports the plugin {mod}")
                continue
            theirs = core_layer(mod, core)
            if theirs is not None and theirs not in ALLOWED[mine]:
                out.append(f"{where}: {mine} imports {theirs} ({mod})")
            elif mine == "report" and theirs == "pipeline" and _report_reads(name, mod, core) is not None:
                out.append(f"{where}: {_report_reads(name, mod, core)}")
            elif theirs is not None and theirs != mine and any(map(_private, names)):
                out.append(
                    f"{where}: {mine} imports the private name(s) {', '.join(filter(_private, names))} "
                    f"of {theirs} ({mod})"
                )
    for pdir in plugin_dirs:
        own = pdir.name
        for f in sorted(pdir.rglob("*.py")):
            name = module_name(f, pdir.parent)
            for line, mod, names, dynamic in imports(f, name):
                where = f"{f.relative_to(pdir.parent)}:{line}"
                problem = _dynamic_problem(where, mod, dynamic)
                if problem or mod == "?":
                    out += [problem] if problem else []
                    continue
                top = mod.split(".")[0]
                if top.startswith("bforest_") and top not in (own, core, *EXTENDS.get(own, ())):
                    out.append(f"{where}: plugin {own} imports plugin {mod}")
                elif top == core:
                    layer = core_layer(_module_or_package(mod, core_dir.parent), core)
                    if layer not in PLUGIN_ALLOWED:
                        out.append(
                            f"{where}: plugin {own} imports the core's {layer} ({mod}); plugins use the "
                            "public face (bforest_core, its kernel modules, bforest_core.testing)"
                        )
                    elif any(map(_private, names)):
                        out.append(
                            f"{where}: plugin {own} imports the private name(s) "
                            f"{', '.join(filter(_private, names))} of the core ({mod})"
                        )
    return out


def import_graph(dirs: list[Path]) -> dict[str, dict[str, str]]:
    """Module -> {imported module of the project: where (``file:line``)}, over the packages
    ``dirs`` (the core and the plugins), every import that runs counted, also inside functions.
    ``from package import name`` imports the package, and the module ``name`` when it is one."""
    graph: dict[str, dict[str, str]] = {}
    for top in dirs:
        for f in sorted(top.rglob("*.py")):
            name = module_name(f, top.parent)
            edges = graph.setdefault(name, {})
            for line, mod, names, dynamic in imports(f, name, runtime=True):
                if dynamic or not mod.split(".")[0].startswith("bforest"):
                    continue
                where = f"{f.relative_to(top.parent)}:{line}"
                base = top.parent if mod.split(".")[0] == top.name else None
                for target in [mod] + [f"{mod}.{n}" for n in names]:
                    if base is None or _is_module(target, base):
                        edges.setdefault(target, where)
    return graph


def _is_module(mod: str, base: Path) -> bool:
    path = base.joinpath(*mod.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def import_circles(dirs: list[Path]) -> list[str]:
    """Every circle of imports among the modules of ``dirs``: ``a -> b (where) -> a (where)``.

    One circle per strongly connected set of modules (Tarjan's algorithm), shown along a
    shortest way back to its first module."""
    graph = import_graph(dirs)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # recursion depth: the longest import chain (a few dozen)
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1 or v in graph.get(v, {}):
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for group in groups:
        first = group[0]
        came: dict[str, str | None] = {first: None}  # breadth first from `first` to a module importing it
        todo, end = [first], None
        while end is None:
            v = todo.pop(0)
            if first in graph.get(v, {}):
                end = v
            for w in graph.get(v, {}):
                if w in group and w not in came:
                    came[w] = v
                    todo.append(w)
        chain = []
        while end is not None:
            chain.append(end)
            end = came[end]
        path = chain[::-1] + [first]
        steps = " -> ".join(f"{b} ({graph[a][b]})" for a, b in zip(path, path[1:]))
        out.append(f"import circle: {path[0]} -> {steps}")
    return out


def plugin_packages() -> list[Path]:
    dirs = sorted(p for p in (ROOT / "plugins").iterdir() if (p / "__init__.py").exists())
    examples = [
        ROOT / "docs" / "examples" / "bforest-example-ssm" / "bforest_example_ssm",
        ROOT / "docs" / "examples" / "bforest-example-sot-form" / "bforest_example_sot_form",
    ]
    return dirs + [e for e in examples if e.exists()]


def test_the_project_keeps_its_layers():
    found = violations(ROOT / CORE, plugin_packages())
    assert not found, "imports against the layering:\n" + "\n".join(found)


def test_no_module_imports_itself_round_a_circle():
    found = import_circles([ROOT / CORE, *plugin_packages()])
    assert not found, "\n".join(found)


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
    "bforest_core/registry.py": "import importlib\nmod = importlib.import_module('bforest_a.m')\n",
    "bforest_core/testing/__init__.py": "from ..tree import Tree\nfrom ._base import _x\n",
    "bforest_core/testing/_base.py": "_x = 1\n",
    "plugins/bforest_a/__init__.py": "import bforest_core as bf\nfrom .m import z\nfrom bforest_core.testing import check\n",
    "plugins/bforest_a/m.py": "from ._own import _q\nfrom bforest_core.tree import Tree\nz = 1\n",
    "plugins/bforest_a/_own.py": "_q = 1\n",
}
#: a module of each layer of the planted project, and what a module of that layer imports
MODULE = {
    "kernel": ("bforest_core/tree.py", "bforest_core.tree"),
    "pipeline": ("bforest_core/pipeline/store.py", "bforest_core.pipeline.store"),
    "report": ("bforest_core/report/__init__.py", "bforest_core.report"),
    "cli": ("bforest_core/cli/__init__.py", "bforest_core.cli"),
    "testing": ("bforest_core/testing/_base.py", "bforest_core.testing._base"),
    "facade": ("bforest_core/__init__.py", "bforest_core"),
}
LAYER_RULES = [(mine, theirs) for mine in ALLOWED for theirs in ALLOWED if theirs not in ALLOWED[mine]]


@pytest.mark.parametrize("mine, theirs", LAYER_RULES, ids=[f"{m}->{t}" for m, t in LAYER_RULES])
def test_the_check_finds_every_upward_import(tmp_path, mine, theirs):
    """Each pair of layers the rules forbid, planted as an import inside a function."""
    _write(tmp_path, GOOD)
    _write(tmp_path, {MODULE[mine][0]: f"def f():\n    import {MODULE[theirs][1]}\n"})
    found = violations(tmp_path / "bforest_core", [tmp_path / "plugins" / "bforest_a"])
    assert len(found) == 1 and f"{mine} imports {theirs}" in found[0], found


@pytest.mark.parametrize(
    "rel, text, expected",
    [
        ("bforest_core/tree.py", "import bforest_a\n", "the core imports the plugin bforest_a"),
        ("plugins/bforest_a/m.py", "from bforest_b.x import y\n", "plugin bforest_a imports plugin bforest_b.x"),
        # dynamic loads outside the registry: in the core, in a plugin, of a computed name
        (
            "bforest_core/pipeline/store.py",
            "import importlib\nm = importlib.import_module('bforest_a.m')\n",
            "dynamic import of bforest_a.m outside the registry",
        ),
        (
            "plugins/bforest_a/m.py",
            "m = __import__('bforest_core.cli')\n",
            "dynamic import of bforest_core.cli outside the registry",
        ),
        (
            "bforest_core/report/__init__.py",
            "from importlib import import_module\nm = import_module('bforest_' + 'a')\n",
            "dynamic import of a computed module name outside the registry",
        ),
        # the report reads runs through the store (and rebuilds trees in run_view only)
        (
            "bforest_core/report/__init__.py",
            "def f():\n    from ..pipeline.fit import fit\n",
            "the report imports bforest_core.pipeline.fit: it reads a run through pipeline.fidelity",
        ),
        # plugins use the core's public face only
        (
            "plugins/bforest_a/m.py",
            "from bforest_core.pipeline.store import x\n",
            "plugin bforest_a imports the core's pipeline",
        ),
        (
            "plugins/bforest_a/m.py",
            "def f():\n    import bforest_core.report\n",
            "plugin bforest_a imports the core's report",
        ),
        ("plugins/bforest_a/m.py", "from bforest_core.cli import main\n", "plugin bforest_a imports the core's cli"),
        # private names across layers, and from a plugin into the core
        (
            "bforest_core/cli/__init__.py",
            "from ..pipeline.store import _secret\n",
            "cli imports the private name(s) _secret of pipeline",
        ),
        (
            "bforest_core/pipeline/store.py",
            "from ..tree import _helper, Tree\n",
            "pipeline imports the private name(s) _helper of kernel",
        ),
        (
            "plugins/bforest_a/m.py",
            "from bforest_core.tree import _helper\n",
            "plugin bforest_a imports the private name(s) _helper of the core",
        ),
    ],
)
def test_the_check_finds_each_kind_of_violation(tmp_path, rel, text, expected):
    _write(tmp_path, GOOD)
    assert violations(tmp_path / "bforest_core", [tmp_path / "plugins" / "bforest_a"]) == []
    _write(tmp_path, {rel: text})
    found = violations(tmp_path / "bforest_core", [tmp_path / "plugins" / "bforest_a"])
    assert len(found) == 1 and expected in found[0], found


@pytest.mark.parametrize(
    "files, circle",
    [
        # at module level, within the kernel
        (
            {"bforest_core/tree.py": "from .io import y\n", "bforest_core/io.py": "from .tree import Tree\n"},
            "bforest_core.io -> bforest_core.tree (bforest_core/io.py:1) -> bforest_core.io (bforest_core/tree.py:1)",
        ),
        # closed inside a function, within a layer (the layering allows both imports)
        (
            {
                "bforest_core/pipeline/fit.py": "from .store import x\n",
                "bforest_core/pipeline/store.py": "def f():\n    from .fit import g\n",
            },
            "bforest_core.pipeline.fit -> bforest_core.pipeline.store (bforest_core/pipeline/fit.py:1) -> "
            "bforest_core.pipeline.fit (bforest_core/pipeline/store.py:2)",
        ),
        # three modules of a plugin, one through `from . import name`
        (
            {
                "plugins/bforest_a/m.py": "from . import n\nz = 1\n",
                "plugins/bforest_a/n.py": "from .o import w\n",
                "plugins/bforest_a/o.py": "def f():\n    from bforest_a.m import z\n",
            },
            "bforest_a.m -> bforest_a.n (bforest_a/m.py:1) -> bforest_a.o (bforest_a/n.py:1) -> "
            "bforest_a.m (bforest_a/o.py:2)",
        ),
    ],
    ids=["module-level", "inside-a-function", "plugin"],
)
def test_the_check_finds_an_import_circle(tmp_path, files, circle):
    _write(tmp_path, GOOD)
    dirs = [tmp_path / "bforest_core", tmp_path / "plugins" / "bforest_a"]
    assert import_circles(dirs) == []
    _write(tmp_path, files)
    found = import_circles(dirs)
    assert found == [f"import circle: {circle}"], found


def test_an_import_for_type_checking_only_closes_no_circle(tmp_path):
    _write(tmp_path, GOOD)
    _write(
        tmp_path,
        {
            "bforest_core/tree.py": "from .io import y\n",
            "bforest_core/io.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .tree import Tree\ny = 1\n",
        },
    )
    assert import_circles([tmp_path / "bforest_core"]) == []
    (tmp_path / "bforest_core" / "io.py").write_text("from .tree import Tree\ny = 1\n")
    assert len(import_circles([tmp_path / "bforest_core"])) == 1


#: what the core must not spell: bundled optimiser, distance and summary plugins and their settings
#: (each plugin writes its own part of a recipe; the core names them in config.BUNDLED_KINDS only)
PLUGIN_WORDS = re.compile(r'"cma"|sigma0|surrogate|"sliced"|"tree-summary"')


def plugin_words(core_dir: Path) -> list[str]:
    """``file:line`` of every bundled plugin's name or setting in the core outside config.BUNDLED_KINDS."""
    out = []
    for f in sorted(core_dir.rglob("*.py")):
        text = f.read_text(encoding="utf-8")
        table = re.search(r"^BUNDLED_KINDS = \{.*?^\}", text, re.S | re.M) if f.name == "config.py" else None
        for m in PLUGIN_WORDS.finditer(text):
            if table is None or not table.start() <= m.start() < table.end():
                out.append(f"{f.relative_to(core_dir.parent)}:{text.count(chr(10), 0, m.start()) + 1}: {m.group()}")
    return out


def test_the_core_names_no_bundled_plugin_outside_its_table_of_default_kinds():
    found = plugin_words(ROOT / CORE)
    assert not found, "the core names a bundled plugin or its settings:\n" + "\n".join(found)


def test_the_plugin_word_check_can_fail(tmp_path):
    _write(tmp_path, {"bforest_core/config.py": 'BUNDLED_KINDS = {\n    "distance": ("sliced", "sliced"),\n}\n'})
    assert plugin_words(tmp_path / "bforest_core") == []
    _write(tmp_path, {"bforest_core/pipeline/recipe.py": 'L = ["sigma0 = 0.15", \'kind = "cma"\']\n'})
    assert plugin_words(tmp_path / "bforest_core") == [
        "bforest_core/pipeline/recipe.py:1: sigma0",
        'bforest_core/pipeline/recipe.py:1: "cma"',
    ]
