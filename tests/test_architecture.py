"""The import graph, read from the source with ``ast`` (nothing is imported), against docs/architecture.md.

Checks on the real tree, each failing with the full list of offenders:

* no import cycle among modules;
* no upward import against the layer order
  kernels < io < core (heightmap, camera, mesh, scene) < lod, surface < measure < rendering < fit
  < experiments < cli (``terrainwarp/__init__.py`` is the public facade: it may import anything, and
  anything below ``cli`` importing it imports upward);
* no ``from X import _private`` (or ``module._private``) across modules;
* kernels/ imports only itself, relatively (it is installed as ``terrainwarp.kernels``);
* no function in terrainwarp/ longer than 80 lines, and none in kernels/ longer than 100, counted from its first
  decorator (a ``wp.func_native`` snippet is its function's body);
* imports inside a function only for the heavy optional libraries.

Every import counts, including those inside functions and under ``if TYPE_CHECKING:`` (a type-only
import is still a dependency of the design). The checker itself is tested on small synthetic packages
built in ``tmp_path`` (a cycle, an upward import, a private import, ...), so a check that silently stops
finding anything fails too.
"""

from __future__ import annotations

import ast
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = "terrainwarp"
MAX_FUNCTION_LINES = 80
MAX_KERNEL_FUNCTION_LINES = 100  # kernels/: Warp kernels, functions and native snippets

# Lowest first. Packages listed together share a layer (they may import each other; cycles are still
# refused). The facade terrainwarp/__init__ is handled apart (see `layer_of`).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("terrainwarp.kernels",),
    ("terrainwarp.io",),
    ("terrainwarp.heightmap", "terrainwarp.camera", "terrainwarp.mesh", "terrainwarp.scene", "terrainwarp.runtime",
     "terrainwarp.schemes"),
    ("terrainwarp.lod", "terrainwarp.surface"),
    ("terrainwarp.measure",),
    ("terrainwarp.rendering",),
    ("terrainwarp.fit", "terrainwarp.diff"),
    ("terrainwarp.experiments",),
    ("terrainwarp.cli",),
)
FACADE = PKG
TOP_LAYER = len(LAYERS) - 1

# Imports allowed inside a function body: heavy optional libraries, imported only when used. optax is
# JAX's optimiser library (importing it imports JAX); cloudpickle is the serialiser of dask/distributed; optuna
# and cma are the optional extra 'tune' (the fit's black-box baselines).
LAZY_OK = frozenset({"jax", "optax", "matplotlib", "rasterio", "affine", "dask", "distributed", "cloudpickle",
                     "pyvista", "skimage", "scipy", "pymartini", "pydelatin", "OpenImageIO", "tqdm", "moderngl",
                     "optuna", "cma"})


# -- reading the tree --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Import:
    """One imported name: ``target`` is the absolute dotted module it resolves to (for ``from M import n``
    that is ``M.n`` when ``M.n`` is a module of the tree, else ``M``); ``name`` is ``n`` (None for a plain
    ``import M``)."""

    target: str
    name: str | None
    line: int
    level: int  # 0 for an absolute import
    in_function: bool
    type_only: bool = False  # under `if TYPE_CHECKING:`


@dataclass
class Module:
    name: str  # dotted, e.g. terrainwarp.io.geotiff; kernels/x.py is terrainwarp.kernels.x
    path: Path
    is_package: bool
    tree: ast.Module
    imports: list[Import] = field(default_factory=list)

    @property
    def package(self) -> str:
        return self.name if self.is_package else self.name.rpartition(".")[0]

    @property
    def in_kernels(self) -> bool:
        return self.name == f"{PKG}.kernels" or self.name.startswith(f"{PKG}.kernels.")


def _dotted(path: Path, base: Path, prefix: str) -> tuple[str, bool]:
    parts = list(path.relative_to(base).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join([prefix, *parts]), is_package


def _function_ranges(tree: ast.Module) -> list[tuple[int, int]]:
    return [(n.lineno, n.end_lineno or n.lineno) for n in ast.walk(tree)
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)]


def _resolve(mod: Module, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = mod.package.split(".")
    base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
    return ".".join([*base, node.module] if node.module else base)


def _type_checking_ranges(tree: ast.Module) -> list[tuple[int, int]]:
    def is_tc(test: ast.expr) -> bool:
        return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
            isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")

    return [(n.lineno, n.end_lineno or n.lineno) for n in ast.walk(tree) if isinstance(n, ast.If) and is_tc(n.test)]


def _collect_imports(mod: Module, known: set[str]) -> None:
    ranges = _function_ranges(mod.tree)
    tc_ranges = _type_checking_ranges(mod.tree)

    def inside(line: int) -> bool:
        return any(a < line <= b for a, b in ranges)

    def type_only(line: int) -> bool:
        return any(a < line <= b for a, b in tc_ranges)

    for node in ast.walk(mod.tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                mod.imports.append(Import(a.name, None, node.lineno, 0, inside(node.lineno), type_only(node.lineno)))
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(mod, node)
            for a in node.names:
                sub = f"{src}.{a.name}"
                target = sub if sub in known else src
                mod.imports.append(Import(target, a.name, node.lineno, node.level, inside(node.lineno),
                                          type_only(node.lineno)))
    mod.imports.sort(key=lambda i: i.line)


def scan(root: Path) -> dict[str, Module]:
    """Every module of ``root/terrainwarp`` and ``root/kernels`` (as terrainwarp.kernels), parsed."""
    files: list[tuple[Path, str, bool]] = []
    for base, prefix in ((root / PKG, PKG), (root / "kernels", f"{PKG}.kernels")):
        for p in sorted(base.rglob("*.py")) if base.is_dir() else []:
            files.append((p, *_dotted(p, base, prefix)))
    mods = {name: Module(name, p, is_pkg, ast.parse(p.read_text(), filename=str(p)))
            for p, name, is_pkg in files}
    known = set(mods)
    for m in mods.values():
        _collect_imports(m, known)
    return mods


def internal(target: str, mods: dict[str, Module]) -> str | None:
    """The module of the tree that ``target`` names (its longest known prefix), or None when external."""
    if target != PKG and not target.startswith(PKG + "."):
        return None
    parts = target.split(".")
    while parts:
        name = ".".join(parts)
        if name in mods:
            return name
        parts.pop()
    return None


def graph(mods: dict[str, Module]) -> dict[str, set[str]]:
    g: dict[str, set[str]] = {m: set() for m in mods}
    for m in mods.values():
        for imp in m.imports:
            t = internal(imp.target, mods)
            if t is not None and t != m.name:
                g[m.name].add(t)
    return g


def _where(m: Module, line: int, root: Path) -> str:
    return f"{m.path.relative_to(root)}:{line}"


# -- the checks (each returns every offender as one line) ---------------------------------------------
def find_cycles(mods: dict[str, Module]) -> list[str]:
    """Strongly connected components of more than one module (Tarjan), each as its members in order."""
    g = graph(mods)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[str] = []

    def visit(v: str) -> None:  # recursion depth is bounded by the module count (~100)
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
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
                out.append(" <-> ".join(sorted(comp)))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def layer_of(name: str) -> int | None:
    """Layer index of a module; the facade counts as the top layer; None for a module in no layer."""
    if name == FACADE:
        return TOP_LAYER
    for i, group in enumerate(LAYERS):
        if any(name == p or name.startswith(p + ".") for p in group):
            return i
    return None


def upward_imports(mods: dict[str, Module], root: Path) -> list[str]:
    out = []
    for m in sorted(mods.values(), key=lambda m: m.name):
        if m.name == FACADE:
            continue  # the public facade re-exports from every layer
        lm = layer_of(m.name)
        if lm is None:
            out.append(f"{m.path.relative_to(root)}: module {m.name} is in no layer (add it to LAYERS and to "
                       "docs/architecture.md)")
            continue
        for imp in m.imports:
            t = internal(imp.target, mods)
            lt = layer_of(t) if t is not None else None
            if t is not None and t != m.name and lt is not None and lt > lm:
                out.append(f"{_where(m, imp.line, root)}: {m.name} (layer {lm}) imports {t} (layer {lt})")
    return list(dict.fromkeys(out))  # one line per import statement, not per name it imports


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports(mods: dict[str, Module], root: Path) -> list[str]:
    """``from X import _name``, ``import X._mod`` and ``X._name`` on an imported module X of the tree,
    where X is another module."""
    out = []
    for m in sorted(mods.values(), key=lambda m: m.name):
        aliases: dict[str, str] = {}  # local name -> module of the tree it is bound to
        for node in ast.walk(m.tree):
            if isinstance(node, ast.ImportFrom):
                src = _resolve(m, node)
                for a in node.names:
                    sub = f"{src}.{a.name}"
                    if sub in mods:
                        aliases[a.asname or a.name] = sub
                    if internal(src, mods) not in (None, m.name) and _is_private(a.name):
                        out.append(f"{_where(m, node.lineno, root)}: {m.name} takes {a.name} from {src}")
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if internal(a.name, mods) is None:
                        continue
                    if any(_is_private(p) for p in a.name.split(".")):
                        out.append(f"{_where(m, node.lineno, root)}: {m.name} imports private module {a.name}")
                    if a.asname:
                        aliases[a.asname] = a.name
        for node in ast.walk(m.tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and _is_private(node.attr)
                    and aliases[node.value.id] != m.name):
                out.append(f"{_where(m, node.lineno, root)}: {m.name} uses {aliases[node.value.id]}.{node.attr}")
    return out


def kernel_host_imports(mods: dict[str, Module], root: Path) -> list[str]:
    """Inside kernels/: any absolute import of the package (host or kernels), and any relative import that
    climbs out of kernels/."""
    out = []
    for m in sorted(mods.values(), key=lambda m: m.name):
        if not m.in_kernels:
            continue
        for imp in m.imports:
            top = imp.target.split(".")[0]
            if imp.level == 0 and top in (PKG, "kernels"):
                what = "the host" if not imp.target.startswith((f"{PKG}.kernels", "kernels")) else "kernels"
                out.append(f"{_where(m, imp.line, root)}: absolute import of {imp.target} ({what}); "
                           "kernels/ imports itself relatively and never the host")
            elif imp.level > 0 and not (imp.target == f"{PKG}.kernels" or imp.target.startswith(f"{PKG}.kernels.")):
                out.append(f"{_where(m, imp.line, root)}: relative import reaches the host ({imp.target})")
    return out


def long_functions(mods: dict[str, Module], root: Path, limit: int = MAX_FUNCTION_LINES,
                   kernel_limit: int = MAX_KERNEL_FUNCTION_LINES) -> list[str]:
    """Functions longer than ``limit`` lines in terrainwarp/ and ``kernel_limit`` in kernels/, from the first
    decorator (or the def line) to the last line: a ``wp.func_native`` function's C++ snippet, its decorator's
    argument, counts."""
    out = []
    for m in sorted(mods.values(), key=lambda m: m.name):
        most = kernel_limit if m.in_kernels else limit
        for node in ast.walk(m.tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([d.lineno for d in node.decorator_list] + [node.lineno])
                n = (node.end_lineno or node.lineno) - first + 1
                if n > most:
                    out.append(f"{_where(m, first, root)}: {node.name} is {n} lines")
    return out


def heavy_modules(mods: dict[str, Module]) -> set[str]:
    """Modules of the tree that import a heavy optional library when they are imported: at module level
    (not inside a function, not under ``if TYPE_CHECKING:``), directly or through another such module.
    Importing one of them lazily is importing the heavy library lazily (e.g. the JAX-only fit.diffpath)."""
    heavy: set[str] = set()
    changed = True
    while changed:
        changed = False
        for m in mods.values():
            if m.name in heavy:
                continue
            for imp in m.imports:
                if imp.in_function or imp.type_only:
                    continue
                t = internal(imp.target, mods)
                if (t is None and imp.target.split(".")[0] in LAZY_OK) or (t is not None and t in heavy):
                    heavy.add(m.name)
                    changed = True
                    break
    return heavy


def function_imports(mods: dict[str, Module], root: Path) -> list[str]:
    """Imports inside a function body, in terrainwarp/ and kernels/, other than the heavy optional
    libraries and the modules of the tree that import them at load time (see :func:`heavy_modules`)."""
    out = []
    heavy = heavy_modules(mods)
    for m in sorted(mods.values(), key=lambda m: m.name):
        for imp in m.imports:
            t = internal(imp.target, mods)
            ok = imp.target.split(".")[0] in LAZY_OK if t is None else t in heavy
            if imp.in_function and not ok:
                out.append(f"{_where(m, imp.line, root)}: {imp.target}" + (f" ({imp.name})" if imp.name else ""))
    return out


def _fail_if(offenders: list[str], what: str) -> None:
    if offenders:
        pytest.fail(f"{len(offenders)} {what}:\n  " + "\n  ".join(offenders), pytrace=False)


# -- the real tree -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tree() -> dict[str, Module]:
    return scan(ROOT)


def test_tree_is_read(tree):
    assert f"{PKG}.heightmap" in tree and f"{PKG}.kernels.raster" in tree and FACADE in tree
    assert sum(len(m.imports) for m in tree.values()) > 100


def test_no_import_cycles(tree):
    _fail_if(find_cycles(tree), "import cycles (modules that import each other, directly or not)")


def test_no_upward_imports(tree):
    _fail_if(upward_imports(tree, ROOT), "imports against the layer order "
             "kernels < io < core < lod, surface < measure < rendering < fit < experiments < cli")


def test_no_private_names_across_modules(tree):
    _fail_if(private_imports(tree, ROOT), "private names taken from another module")


def test_kernels_import_only_themselves_relatively(tree):
    _fail_if(kernel_host_imports(tree, ROOT), "imports in kernels/ that are absolute or reach the host")


def test_functions_are_short(tree):
    _fail_if(long_functions(tree, ROOT), f"functions longer than {MAX_FUNCTION_LINES} lines in terrainwarp/ or "
             f"{MAX_KERNEL_FUNCTION_LINES} in kernels/")


def test_imports_at_the_top(tree):
    _fail_if(function_imports(tree, ROOT), "imports inside functions that are not heavy optional libraries "
             f"({', '.join(sorted(LAZY_OK))})")


# -- the checker, on synthetic packages ------------------------------------------------------------
def _package(tmp_path: Path, files: dict[str, str]) -> dict[str, Module]:
    """A tree under tmp_path: keys are paths relative to it (terrainwarp/..., kernels/...)."""
    base = {"terrainwarp/__init__.py": "", "terrainwarp/io/__init__.py": "", "terrainwarp/lod/__init__.py": "",
            "kernels/__init__.py": ""}
    for rel, text in {**base, **files}.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return scan(tmp_path)


def test_clean_synthetic_package_passes(tmp_path):
    mods = _package(tmp_path, {
        "terrainwarp/heightmap.py": "from .io.files import save\nfrom .kernels import noise\n",
        "terrainwarp/io/files.py": "import numpy as np\n\n\ndef save():\n    import rasterio\n",
        "terrainwarp/lod/quadtree.py": "from ..heightmap import Heightmap\nfrom . import bintree\n",
        "terrainwarp/lod/bintree.py": "from ..kernels.noise import fbm\n",
        "terrainwarp/cli.py": "import terrainwarp as tw\nfrom .lod import quadtree\n",
        "kernels/noise.py": "import warp as wp\nfrom .sampling import sample\n",
        "kernels/sampling.py": "import numpy as np\n",
    })
    assert "terrainwarp.lod.bintree" in graph(mods)["terrainwarp.lod.quadtree"]
    assert graph(mods)["terrainwarp.heightmap"] == {"terrainwarp.io.files", "terrainwarp.kernels.noise"}
    for check in (upward_imports, private_imports, kernel_host_imports, long_functions, function_imports):
        assert check(mods, tmp_path) == [], check.__name__
    assert find_cycles(mods) == []


def test_checker_finds_a_cycle(tmp_path):
    mods = _package(tmp_path, {
        "terrainwarp/lod/a.py": "from . import b\n",
        "terrainwarp/lod/b.py": "def f():\n    from .c import x\n",  # inside a function: still an edge
        "terrainwarp/lod/c.py": "from terrainwarp.lod.a import y\n",
        "terrainwarp/io/x.py": "from .y import z\n",
        "terrainwarp/io/y.py": "from .x import w\n",
    })
    assert find_cycles(mods) == ["terrainwarp.io.x <-> terrainwarp.io.y",
                                 "terrainwarp.lod.a <-> terrainwarp.lod.b <-> terrainwarp.lod.c"]


def test_checker_finds_upward_imports(tmp_path):
    mods = _package(tmp_path, {
        "terrainwarp/io/geotiff.py": "from ..heightmap import Heightmap\n",
        "terrainwarp/heightmap.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                    "    from .lod.quadtree import Terrain\n",
        "terrainwarp/lod/quadtree.py": "import terrainwarp\n",
        "terrainwarp/lod/bintree.py": "from .. import Heightmap\n",  # the facade sits on top
        "terrainwarp/stray.py": "",
    })
    out = upward_imports(mods, tmp_path)
    assert len(out) == 5, out
    assert ("terrainwarp/io/geotiff.py:1: terrainwarp.io.geotiff (layer 1) imports terrainwarp.heightmap "
            "(layer 2)") in out
    assert any("heightmap.py:3" in s and "terrainwarp.lod.quadtree" in s for s in out)
    assert any("quadtree.py:1" in s and "imports terrainwarp (layer" in s for s in out)
    assert any("bintree.py:1" in s and "imports terrainwarp (layer" in s for s in out)
    assert any("terrainwarp.stray is in no layer" in s for s in out)


def test_checker_finds_private_names(tmp_path):
    mods = _package(tmp_path, {
        "terrainwarp/io/files.py": "_SECRET = 1\n\n\ndef _helper():\n    return _SECRET\n",
        "terrainwarp/io/geotiff.py": "from .files import _helper, atomic\nfrom . import files\nx = files._SECRET\n",
        "terrainwarp/lod/_impl.py": "",
        "terrainwarp/lod/quadtree.py": "import terrainwarp.lod._impl\nfrom ..io.files import __doc__\n",
    })
    out = private_imports(mods, tmp_path)
    assert out == [
        "terrainwarp/io/geotiff.py:1: terrainwarp.io.geotiff takes _helper from terrainwarp.io.files",
        "terrainwarp/io/geotiff.py:3: terrainwarp.io.geotiff uses terrainwarp.io.files._SECRET",
        "terrainwarp/lod/quadtree.py:1: terrainwarp.lod.quadtree imports private module terrainwarp.lod._impl",
    ]


def test_checker_finds_kernels_reaching_the_host(tmp_path):
    mods = _package(tmp_path, {
        "kernels/raster.py": "from terrainwarp.mesh import Mesh\nfrom terrainwarp.kernels.noise import f\n"
                             "from kernels import sampling\nfrom .. import heightmap\n",
        "kernels/noise.py": "from .sampling import g\n",
        "kernels/sampling.py": "",
    })
    out = kernel_host_imports(mods, tmp_path)
    assert len(out) == 4, out
    assert "kernels/raster.py:1" in out[0] and "(the host)" in out[0]
    assert "kernels/raster.py:2" in out[1] and "(kernels)" in out[1]
    assert "kernels/raster.py:3" in out[2]
    assert "kernels/raster.py:4" in out[3] and "reaches the host" in out[3]


def test_checker_finds_long_functions_and_imports_inside_functions(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(80))
    snippet = "".join(f"x{i} = {i};\n" for i in range(98))
    mods = _package(tmp_path, {
        "terrainwarp/lod/quadtree.py": f"def select():\n{body}\n\ndef short():\n    import json\n"
                                       "    from ..io import files\n    import jax.numpy as jnp\n",
        "kernels/raster.py": f"def kernel_helper():\n{body}\n\n"  # 81 lines: within kernels/' 100
                             f'@wp.func_native("""\n{snippet}""")\ndef native() -> int: ...\n',  # 101 with its snippet
    })
    assert long_functions(mods, tmp_path) == ["kernels/raster.py:84: native is 101 lines",
                                              "terrainwarp/lod/quadtree.py:1: select is 81 lines"]
    assert function_imports(mods, tmp_path) == ["terrainwarp/lod/quadtree.py:85: json",
                                                "terrainwarp/lod/quadtree.py:86: terrainwarp.io (files)"]


def test_lazy_import_of_a_module_that_imports_a_heavy_library_is_allowed(tmp_path):
    mods = _package(tmp_path, {
        "terrainwarp/fit/__init__.py": "",
        "terrainwarp/fit/diffpath.py": "import jax.numpy as jnp\n",
        "terrainwarp/fit/relaxed.py": "from .diffpath import jnp\n",  # heavy through diffpath
        "terrainwarp/fit/typed.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import jax\n",
        "terrainwarp/fit/lod_fit.py": "def fit():\n    from .diffpath import x\n    from .relaxed import y\n"
                                      "    from .typed import z\n    from . import typed\n",
    })
    assert heavy_modules(mods) == {"terrainwarp.fit.diffpath", "terrainwarp.fit.relaxed"}
    assert function_imports(mods, tmp_path) == ["terrainwarp/fit/lod_fit.py:4: terrainwarp.fit.typed (z)",
                                                "terrainwarp/fit/lod_fit.py:5: terrainwarp.fit.typed (typed)"]


def test_every_package_is_in_the_wheel():
    # an editable install finds an unlisted subpackage on disk; a wheel built from pyproject.toml would not
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {"terrainwarp." + ".".join(p.parent.relative_to(ROOT / "terrainwarp").parts)
               for p in (ROOT / "terrainwarp").rglob("__init__.py") if p.parent != ROOT / "terrainwarp"}
    assert on_disk | {"terrainwarp", "terrainwarp.kernels"} == listed, sorted(on_disk ^ (listed - {"terrainwarp",
                                                                                                 "terrainwarp.kernels"}))
