"""The public namespace is one checked list (``terrainwarp.__all__``); the names that moved to their modules
still resolve, with a DeprecationWarning naming the new place; docs and examples use only public names."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys
import types
import warnings
from pathlib import Path

import pytest

import terrainwarp as tw

ROOT = Path(__file__).resolve().parents[1]

# the core the design names (issue 35), then the subpackages
CORE = ["Heightmap", "Camera", "Scene", "LodConfig", "render", "Frame", "fit_lod", "check_watertight",
        "compute_normals", "compute_curvature", "configure"]
SUBPACKAGES = ["diff", "experiments", "fit", "io", "kernels", "lod", "measure", "rendering", "schemes", "surface"]


def test_the_public_names_are_the_core_and_the_subpackages():
    assert tw.__all__ == [*CORE, *SUBPACKAGES, "__version__"]
    for name in tw.__all__:
        assert getattr(tw, name) is not None, name
    for name in SUBPACKAGES:
        assert isinstance(getattr(tw, name), types.ModuleType) and getattr(tw, name).__name__ == f"terrainwarp.{name}"


def test_nothing_else_public_lives_in_the_namespace():
    """Every attribute of ``terrainwarp`` without a leading underscore is in ``__all__`` or is a module (the core
    modules, bound when the package imports them): no second, hand-kept list can drift from it."""
    stray = [n for n in vars(tw) if not n.startswith("_") and n not in tw.__all__
             and not isinstance(getattr(tw, n), types.ModuleType)]
    assert stray == []
    assert set(tw.__all__) <= set(dir(tw))


def test_star_import_gives_the_list():
    ns: dict = {}
    exec("from terrainwarp import *", ns)  # noqa: S102 - the star import is what is tested
    assert {n for n in ns if n != "__builtins__"} == set(tw.__all__)


@pytest.mark.parametrize("old", sorted(tw._MOVED))
def test_moved_names_warn_and_resolve_to_the_new_place(old):
    module, new = tw._MOVED[old]
    with pytest.warns(DeprecationWarning, match=rf"terrainwarp\.{old} is deprecated.*{re.escape(module)}\.{new}"):
        got = getattr(tw, old)
    assert got is getattr(importlib.import_module(module), new)


def test_from_import_of_a_moved_name_warns():
    with pytest.warns(DeprecationWarning, match="terrainwarp.Terrain is deprecated"):
        from terrainwarp import Terrain  # noqa: F401
    with pytest.raises(ImportError):
        from terrainwarp import no_such_name  # noqa: F401


def test_the_reference_tessellator_is_named_as_the_reference():
    from terrainwarp.rendering import reference_tessellator

    assert tw._MOVED["tessellate_patch"] == ("terrainwarp.rendering", "reference_tessellate_patch")
    with pytest.warns(DeprecationWarning, match="use reference_tessellate_patch"):
        old = reference_tessellator.tessellate_patch
    assert old is tw.rendering.reference_tessellate_patch
    uv, tri = old([2, 2, 2, 2], [2, 2], "equal")
    assert uv.shape == (9, 2) and tri.shape == (8, 3)
    with pytest.raises(AttributeError):
        reference_tessellator.no_such_name  # noqa: B018


def test_deep_paths_made_short():
    """CDLOD, clipmaps, chunked LOD and release_buffers were reachable only by deep paths."""
    from terrainwarp.kernels.pool import release_buffers
    from terrainwarp.lod.cdlod import Cdlod
    from terrainwarp.lod.chunked import ChunkedLod
    from terrainwarp.lod.clipmaps import Clipmap

    assert (tw.lod.Cdlod, tw.lod.Clipmap, tw.lod.ChunkedLod) == (Cdlod, Clipmap, ChunkedLod)
    assert tw.rendering.release_buffers is release_buffers
    # the two rasterizers no longer share a name in one namespace: tw.rasterize is gone from the core
    assert "rasterize" not in tw.__all__ and tw.rendering.rasterize is not None


def test_subpackage_lists_resolve():
    for name in SUBPACKAGES:
        mod = getattr(tw, name)
        for n in getattr(mod, "__all__", []):
            assert hasattr(mod, n), f"terrainwarp.{name}.{n}"


def test_import_does_not_load_jax_and_diff_loads_on_first_use():
    code = ("import sys, terrainwarp as tw; a = 'jax' in sys.modules; d = tw.diff; "
            "print(a, 'jax' in sys.modules, d.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "True", "terrainwarp.diff"]


def _tw_names(text: str) -> set[str]:
    return set(re.findall(r"\btw\.([A-Za-z_][A-Za-z_0-9]*)", text))


def test_readme_examples_and_notebook_use_only_public_names_or_modules():
    texts = {p: p.read_text() for p in [ROOT / "README.md", *sorted((ROOT / "examples").glob("*.py"))]}
    nb = ROOT / "examples" / "terrainwarp.ipynb"
    texts[nb] = "\n".join("".join(c["source"]) for c in json.loads(nb.read_text())["cells"])
    modules = {n for n in vars(tw) if isinstance(getattr(tw, n), types.ModuleType)}  # tw.heightmap.X: by its module
    bad = {str(p.relative_to(ROOT)): sorted(_tw_names(t) - set(tw.__all__) - modules) for p, t in texts.items()}
    assert {k: v for k, v in bad.items() if v} == {}


def test_project_code_uses_no_deprecated_name():
    """pytest turns terrainwarp's DeprecationWarnings into errors (pyproject), so every test and example run
    shows no code uses a moved name; this checks that the filter is on."""
    with warnings.catch_warnings():
        filters = [f for f in warnings.filters if f[0] == "error" and f[1] is not None
                   and f[1].pattern.startswith("terrainwarp")]
    assert filters, warnings.filters[:5]
