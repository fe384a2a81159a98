"""The reference's generated parts: one API page per module (written before Sphinx reads the sources), the
scene-file format from :data:`terrainwarp.scene.SCENE_FILE` and the command line from its parser.

An object is documented once, in the module that defines it; a module that re-exports it lists it with a
link there. So every public name (a module's ``__all__``) is in the reference, and no target is ambiguous.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import re
from pathlib import Path

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective


def modules() -> list[str]:
    """Every module of terrainwarp and of its kernels (mapped in as ``terrainwarp.kernels``), the facade first."""
    import terrainwarp

    found = {"terrainwarp.kernels"}
    for pkg in (terrainwarp, terrainwarp.kernels):
        found |= {m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")}
    return ["terrainwarp", *sorted(found)]


def public(module: str) -> list[str]:
    """A module's public names: its ``__all__``; without one, the functions and classes it defines whose names
    have no leading underscore (the kernels' host wrappers)."""
    mod = importlib.import_module(module)
    if hasattr(mod, "__all__"):
        return [n for n in mod.__all__ if not n.startswith("__")]
    return [n for n, o in vars(mod).items() if not n.startswith("_") and (inspect.isfunction(o) or inspect.isclass(o))
            and o.__module__ == module]


def home(module: str, name: str, mods: list[str]) -> str:
    """The documented module an object of ``module.__all__`` lives in: where its class or function was defined,
    else (data, a module) the first module listing the same object that is not a package; else ``module``."""
    obj = getattr(importlib.import_module(module), name)
    if inspect.ismodule(obj):
        return obj.__name__
    owner = getattr(obj, "__module__", None)
    top_level = getattr(obj, "__qualname__", name) == name
    if isinstance(owner, str) and owner in mods and name in public(owner) and top_level:
        return owner
    for m in mods:
        mm = importlib.import_module(m)
        if not hasattr(mm, "__path__") and name in public(m) and getattr(mm, name) is obj:
            return m
    return module


def _kind(obj: object) -> str:
    if inspect.ismodule(obj):
        return "mod"
    if isinstance(obj, type):
        return "class"
    return "func" if callable(obj) else "data"


def _directive(module: str, name: str, obj: object) -> list[str]:
    """The autodoc directive of one public object: a class with its documented members, a function, or data
    (its value shown when it is short)."""
    if inspect.isclass(obj):
        return [f".. autoclass:: {module}.{name}", "   :members:", ""]
    if callable(obj):
        return [f".. autofunction:: {module}.{name}", ""]
    short = len(repr(obj)) <= 80
    return [f".. autodata:: {module}.{name}", *([] if short else ["   :no-value:"]), ""]


def write_api(app) -> None:
    """docs/api/<module>.rst for every module, and docs/api/index.rst."""
    out = Path(app.srcdir) / "api"
    out.mkdir(exist_ok=True)
    mods = modules()
    for m in mods:
        mod = importlib.import_module(m)
        names = public(m)
        own = [n for n in names if home(m, n, mods) == m]
        elsewhere = [(n, home(m, n, mods)) for n in names if home(m, n, mods) != m]
        lines = [m, "=" * len(m), "", f".. automodule:: {m}", ""]
        for n in own:
            lines += _directive(m, n, getattr(mod, n))
        if elsewhere:
            lines += [".. rubric:: Also here (documented where they are defined)", ""]
            for n, h in elsewhere:
                obj = getattr(mod, n)
                target = h if _kind(obj) == "mod" else f"{h}.{n}"
                lines.append(f"* :py:{_kind(obj)}:`{n} <{target}>`")
            lines.append("")
        subs = [s for s in mods if s.rpartition(".")[0] == m]
        if subs:
            lines += [".. toctree::", "   :maxdepth: 1", "", *[f"   {s}" for s in subs], ""]
        _write(out / f"{m}.rst", "\n".join(lines))
    _write(out / "index.rst", "\n".join(["API reference", "=============", "",
                                         "Every module, from the facade down; each object is documented in the "
                                         "module that defines it.", "", ".. toctree::", "   :maxdepth: 2", "",
                                         "   terrainwarp", ""]))


def _write(path: Path, text: str) -> None:
    """Write only when the text changed (Sphinx rereads a source whose file is newer)."""
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


class SceneFormat(SphinxDirective):
    """Every table of a scene file and its keys, from :data:`terrainwarp.scene.SCENE_FILE`."""

    def run(self):
        from terrainwarp.scene import SCENE_FILE

        lines = []
        for table, keys in SCENE_FILE.items():
            title = f"[{table}]"
            lines += [title, "-" * len(title), "", ".. list-table::", "   :header-rows: 1", "   :widths: 18 16 22 44",
                      "", "   * - key", "     - type", "     - default", "     - meaning"]
            for k, spec in keys.items():
                lines += [f"   * - ``{k}``", f"     - {spec.type}", f"     - {_literal(spec.default)}",
                          f"     - {spec.doc}"]
            lines.append("")
        return self.parse(lines)

    def parse(self, lines: list[str]):
        node = nodes.section()
        self.state.nested_parse(StringList(lines, "scene-format"), self.content_offset, node, match_titles=True)
        return node.children


def _literal(default: str) -> str:
    return "-" if default == "-" else (f"``{default}``" if default[:1] in '"[0123456789-tf' else default)


class CommandLine(SceneFormat):
    """``terrainwarp --help`` and each command's ``--help``, as the parser prints them (100 columns)."""

    def run(self):
        from terrainwarp.cli import build_parser

        os.environ["COLUMNS"] = "100"
        parser = build_parser()
        sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        lines = [".. code-block:: text", "", *_indented(parser.format_help()), ""]
        for name, p in sub.choices.items():
            title = f"terrainwarp {name}"
            lines += [title, "-" * len(title), "", ".. code-block:: text", "", *_indented(p.format_help()), ""]
        return self.parse(lines)


def _indented(text: str) -> list[str]:
    return ["   " + ln if ln.strip() else "" for ln in text.splitlines()]


def _tidy_docstring(app, what, name, obj, options, lines) -> None:
    """Two fixes to what autodoc reads: data without a doc comment of its own gets no text (not its type's:
    ``dict``'s docstring is not a constant's), and an ``Attributes`` entry naming several fields (``dx, dz:``,
    which napoleon makes one ``:ivar:`` whose first name would read as a type) becomes one entry per field."""
    own = getattr(type(obj), "__doc__", None)
    if what == "data" and own and " ".join(" ".join(lines).split()) == " ".join(own.split()):
        lines.clear()
        return
    out: list[str] = []
    group: list[str] | None = None
    for line in lines:
        m = _IVAR_GROUP.match(line)
        if m:
            group = [n.strip() for n in m.group(1).split(",")]
            out.append(f":ivar {group[0]}: {m.group(2)}")
            continue
        if group and line.startswith(" ") and line.strip():
            out.append(line)
            continue
        if group:
            out += _repeat(out, group)
            group = None
        out.append(line)
    if group:
        out += _repeat(out, group)
    lines[:] = out


def _repeat(out: list[str], group: list[str]) -> list[str]:
    """The entry just written for ``group[0]`` again for each other name of the group."""
    start = max(i for i, ln in enumerate(out) if ln.startswith(f":ivar {group[0]}: "))
    entry = out[start:]
    return [ln.replace(f":ivar {group[0]}: ", f":ivar {n}: ", 1) for n in group[1:] for ln in entry]


_IVAR_GROUP = re.compile(r"^:ivar ((?:\w+, )+\w+): (.*)$")


def setup(app):
    app.connect("builder-inited", write_api)
    app.connect("autodoc-process-docstring", _tidy_docstring)
    app.add_directive("terrainwarp-scene-format", SceneFormat)
    app.add_directive("terrainwarp-cli", CommandLine)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
