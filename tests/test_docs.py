"""The API reference builds with no warning (Sphinx, warnings as errors, as ``make docs``), every public name is
in it, and its scene-file and command-line pages are made from the code, so they cannot go stale."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest
from sphinx.util.inventory import InventoryFile

from terrainwarp.cli import build_parser
from terrainwarp.scene import SCENE_FILE, LodConfig, Scene

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))
import twdocs  # noqa: E402


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("docs")
    r = subprocess.run([sys.executable, "-m", "sphinx", "-E", "-a", "-W", "--keep-going", "-q", "-b", "html",
                        str(ROOT / "docs"), str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and "WARNING" not in r.stderr and "ERROR" not in r.stderr, r.stderr[-4000:]
    return out


def _inventory(out: Path) -> dict[str, set[str]]:
    with open(out / "objects.inv", "rb") as f:
        inv = InventoryFile.load(f, "", lambda base, uri: uri)
    return {kind: set(entries) for kind, entries in inv.items()}


def test_every_public_name_is_in_the_reference(built):
    """Each name of each module's public list (``__all__``) is documented: under that module, or, re-exported,
    where the same object is documented (found by identity, not by the docs tool's own choice)."""
    inv = _inventory(built)
    documented = set().union(*(v for k, v in inv.items() if k.startswith("py:")))
    mods = twdocs.modules()
    assert set(mods) <= inv["py:module"], sorted(set(mods) - inv["py:module"])
    missing = []
    for m in mods:
        mod = importlib.import_module(m)
        for n in twdocs.public(m):
            obj = getattr(mod, n)
            homes = [d for d in documented if d.rsplit(".", 1)[-1] == n and d.rsplit(".", 1)[0] in mods
                     and getattr(importlib.import_module(d.rsplit(".", 1)[0]), n, None) is obj]
            if f"{m}.{n}" not in documented and not homes and getattr(obj, "__name__", "") not in inv["py:module"]:
                missing.append(f"{m}.{n}")
    assert missing == []
    assert len(documented) > 500  # classes, functions, methods, attributes of ~70 modules
    for core in ("terrainwarp.rendering.pipeline.render", "terrainwarp.heightmap.Heightmap",
                 "terrainwarp.schemes.register_scheme", "terrainwarp.rendering.sources.MeshSource"):
        assert core in documented


def _text(page: Path) -> str:
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", page.read_text()))


def test_the_scene_file_page_lists_every_table_and_key(built):
    text = _text(built / "scene_format.html")
    for table, keys in SCENE_FILE.items():
        assert f"[{table}]" in text
        for k in keys:
            assert f" {k} " in text, (table, k)
    assert set(SCENE_FILE["lod"]) == set(LodConfig.__dataclass_fields__)
    assert all(spec.doc for keys in SCENE_FILE.values() for spec in keys.values())  # LodConfig's docstring too


def test_the_command_line_page_has_every_command_and_option(built):
    text = _text(built / "cli.html")
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, p in sub.choices.items():
        assert f"terrainwarp {name}" in text
        for a in p._actions:
            for opt in a.option_strings:
                assert opt in text, (name, opt)


def test_the_architecture_page_and_the_custom_scheme_are_in(built):
    assert "The dependency rule" in _text(built / "architecture.html")
    assert "class BandsSource ( tw . rendering . SourceBase )" in _text(built / "custom_scheme.html")


@pytest.mark.parametrize("table", [t for t in SCENE_FILE if "." not in t])  # sub-tables: below
def test_the_loader_takes_exactly_the_documented_keys(table, tmp_path):
    """The scene file's keys come from SCENE_FILE: an unknown key is refused with the documented list."""
    data = {"heightmap": {"fbm": {"rows": 17}}, table: {"no_such_key": 1}} if table != "heightmap" else \
        {"heightmap": {"fbm": {"rows": 17}, "no_such_key": 1}}
    with pytest.raises(ValueError, match=re.escape(f"{table}: unknown key(s) ['no_such_key']; expected some of "
                                                   f"{sorted(SCENE_FILE[table])}")):
        sc = Scene.from_dict(data)
        sc.path_info()  # [path] is read when the path is flown
    cam = {"position": [0, 9, 0], "target": [1, 0, 1], "bogus": 1}
    with pytest.raises(ValueError, match=re.escape(f"path.cameras[0]: unknown key(s) ['bogus']; expected some of "
                                                   f"{sorted(SCENE_FILE['path.cameras'])}")):
        Scene.from_dict({"heightmap": {"fbm": {"rows": 17}}, "path": {"kind": "cameras", "cameras": [cam]}})
    with pytest.raises(ValueError, match=re.escape(f"heightmap.fbm: unknown key(s) ['bogus']; expected some of "
                                                   f"{sorted(SCENE_FILE['heightmap.fbm'])}")):
        Scene.from_dict({"heightmap": {"fbm": {"bogus": 1}}})
