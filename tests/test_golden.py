"""Golden hashes of the demo scene's outputs (the bundled SRTM DEM, default camera, 96 x 72 viewport).

Only stages whose code has settled are kept: the heights as loaded, the Sobel normal map the pipeline
shades with, three-normal curvature, the camera-relative grid mesh, an fBm window and the D3D11
reference tessellator. The rasterizer, LOD selection and the frame tessellator are still being changed
and are covered by their own tests and by the two-run determinism test of tests/test_stability.py.

A change that moves one of these hashes is either a bug or a deliberate change of the numbers; after a
deliberate one, regenerate them with ONE command (it rewrites the GOLDEN block of this file in place):

    .venv/bin/python tests/test_golden.py --regenerate
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp.camera import relative_origin
from terrainwarp.io.files import digest
from terrainwarp.kernels.displacement import grid_mesh
from terrainwarp.kernels.noise import fbm
from terrainwarp.kernels.normals import sobel_normals
from terrainwarp.rendering.reference_tessellator import reference_tessellate_patch


def compute() -> dict[str, str]:
    """The demo scene's stable stage outputs, hashed (cpu device)."""
    hm = tw.Heightmap.example("jacksboro")
    cam = tw.Camera.default_for(hm, 96, 72)
    pos, uv, tri = grid_mesh(hm.heights, hm.dx, hm.dz, relative_origin(hm.origin, cam.position))
    tess = []
    for outer, inner, sp in (([3, 5, 7, 2], [4, 6], "equal"), ([2.5, 7.3, 1.1, 9.9], [5.5, 3.2], "fractional_odd"),
                             ([63.99, 1, 64, 17], [30.5, 2.2], "fractional_even")):
        tess += list(reference_tessellate_patch(outer, inner, sp))
    return {
        "heights": digest(hm.heights, np.array([hm.dx, hm.dz])),
        "camera": digest(cam.view_matrix(relative=True), cam.proj_matrix()),
        "normal_map": digest(sobel_normals(hm.heights, hm.dx, hm.dz, border="clamp")),
        "curvature": digest(tw.compute_curvature(hm, "three_normal")),
        "grid_mesh": digest(pos, uv, tri),
        "fbm": digest(fbm(64, 48, seed=5, row0=1000, col0=-300)),
        "reference_tessellate_patch": digest(*tess),
    }


# BEGIN GOLDEN (written by: .venv/bin/python tests/test_golden.py --regenerate)
GOLDEN = {
    "heights": "e5fd79883289cec4ec5c931854205852b770dc29d6628eb060422a5d0d84f383",
    "camera": "14ee1ac8e154d15e3e04eefdb4ac0b56839a4b55a2bfc6497e19a23ea7635822",
    "normal_map": "c3950de1b3e68af38426e978bfec9d528c68cb08955eccfeeb65bc00b26349f0",
    "curvature": "6978eb095c6127978e99a2ac92859adae6422ba596b3c6e98b85df5af8ac33dd",
    "grid_mesh": "7de11fc97edeb3763c571f210e9f9cdff4882185abb53853b87df6ecb1373fae",
    "fbm": "eca3b63d593761e3d9362e914e1659958cf26124f790a4135e95bfbf7e6e582e",
    "reference_tessellate_patch": "b4d0029bf43673f31484953152a14583a5bd504021839554c0b22d2ea1b9bde8",
}
# END GOLDEN


@pytest.mark.parametrize("stage", sorted(GOLDEN))
def test_golden_hash(stage, golden_now):
    assert golden_now[stage] == GOLDEN[stage], (
        f"{stage}: output changed; if deliberate, run: .venv/bin/python tests/test_golden.py --regenerate")


def test_golden_covers_every_stage(golden_now):
    assert set(GOLDEN) == set(golden_now)


@pytest.fixture(scope="module")
def golden_now():
    return compute()


def _regenerate() -> None:
    path = Path(__file__)
    body = "".join(f'    "{k}": "{v}",\n' for k, v in compute().items())
    text = path.read_text()
    block = r"(# BEGIN GOLDEN[^\n]*\nGOLDEN = \{\n).*?(\}\n# END GOLDEN)"
    new = re.sub(block, lambda m: m.group(1) + body + m.group(2), text, flags=re.S)
    path.write_text(new)
    print(f"wrote {len(body.splitlines())} golden hashes to {path}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--regenerate"]:
        print("usage: python tests/test_golden.py --regenerate", file=sys.stderr)
        raise SystemExit(2)
    _regenerate()
