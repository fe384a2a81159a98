"""PNG bytes and pictures for notebooks (terrainwarp.io.display): decoded back to the same pixels."""

from __future__ import annotations

import io

import numpy as np
import pytest

from terrainwarp.io.display import depth_picture, html_table, id_picture, png_bytes


def _decode(data: bytes) -> np.ndarray:
    import matplotlib.image as mpimg

    return np.round(mpimg.imread(io.BytesIO(data), format="png") * 255).astype(np.uint8)


@pytest.mark.parametrize("shape", [(1, 1, 3), (7, 5, 3), (48, 64, 3), (9, 4)])
def test_png_bytes_decode_to_the_same_pixels(shape):
    a = np.random.default_rng(len(shape) * 10 + shape[0]).integers(0, 256, shape, dtype=np.uint8)
    data = png_bytes(a)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert np.array_equal(_decode(data), a)
    assert png_bytes(a) == data  # deterministic


@pytest.mark.parametrize("bad", [np.zeros((4, 4, 3), np.float32), np.zeros((4, 4, 4), np.uint8),
                                 np.zeros((0, 4, 3), np.uint8), np.zeros(5, np.uint8)])
def test_png_bytes_refuses_what_it_cannot_encode(bad):
    with pytest.raises(ValueError, match="image: expected a non-empty"):
        png_bytes(bad)


def test_depth_picture_is_bright_near_and_grey_on_background():
    d = np.array([[0.2, 0.5, 0.9, 1.0]], np.float32)
    p = depth_picture(d)
    assert p.shape == (1, 4, 3) and p.dtype == np.uint8
    assert p[0, 0, 0] > p[0, 1, 0] > p[0, 2, 0] and tuple(p[0, 3]) == (24, 26, 32)
    assert tuple(depth_picture(np.ones((2, 2), np.float32))[1, 1]) == (24, 26, 32)  # nothing drawn


def test_id_picture_gives_each_id_its_own_stable_colour():
    ids = np.array([[-1, 0, 1], [2, 1, 0]], np.int32)
    p = id_picture(ids)
    assert tuple(p[0, 0]) == (24, 26, 32)
    assert np.array_equal(p[0, 1], p[1, 2]) and np.array_equal(p[0, 2], p[1, 1])
    assert len({tuple(c) for c in p.reshape(-1, 3)}) == 4


def test_html_table_escapes_and_formats():
    t = html_table(("a", "b<"), [(1.23456789, {"k": 0.5, "n": 3}), ("<x>", float("nan"))], caption="c & d")
    assert t.startswith("<table><caption>c &amp; d</caption>") and "<th>b&lt;</th>" in t
    assert "<td>1.235</td>" in t and "<td>k=0.5, n=3</td>" in t and "<td>&lt;x&gt;</td>" in t and "nan" in t
