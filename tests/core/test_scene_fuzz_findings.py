"""What the fuzz suite (tests/fuzz_runner.py, issue 31) found in scene files, each input kept small: refused now
with a ValueError or TypeError naming the key."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from terrainwarp import Scene

SCENE = '[heightmap]\nfbm = {rows = 17, seed = 1, octaves = 3}\n[camera]\nwidth = 16\nheight = 12\n'


def _scene(tmp_path, extra: str) -> Scene:
    p = tmp_path / "s.toml"
    p.write_text(SCENE + extra)
    return Scene.load(p)


@pytest.mark.parametrize("value", ["1", "2.5", "true"])
def test_render_outputs_that_is_not_an_array_names_the_key(tmp_path, value):
    with pytest.raises((TypeError, ValueError)) as e:
        _scene(tmp_path, f"[render]\noutputs = {value}\n")
    assert str(e.value).startswith("render.outputs:"), str(e.value)


@pytest.mark.parametrize("n", [2**31, 2**63 - 1])
def test_a_path_of_billions_of_cameras_is_refused(tmp_path, n):
    p = tmp_path / "s.toml"
    p.write_text(SCENE + f"[path]\nn = {n}\n")
    # in a child under a 4 GiB address-space limit: without a bound, 2^31 cameras fail there fast, not here slowly
    code = textwrap.dedent(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
        from terrainwarp import Scene
        try:
            Scene.load({str(p)!r}).camera_path()
        except Exception as e:
            print(type(e).__name__ + ": " + str(e).splitlines()[0])
    """)
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    out = got.stdout.strip().splitlines()[-1]
    assert out.startswith("ValueError: path.n:"), out
