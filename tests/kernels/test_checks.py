"""The one validation helper (terrainwarp.kernels.checks): one exception type per kind of error, the argument
named, "expected X, got Y"."""

import numpy as np
import pytest

from terrainwarp.kernels.checks import (
    MAX_VIEWPORT,
    check_choice,
    check_pixels,
    check_triangle_shape,
    check_triangles,
    check_viewport,
)


def test_check_triangles_returns_contiguous_int32_and_checks_each_kind():
    tri = np.array([[0, 1, 2], [2, 1, 3]], dtype=np.int64)[:, ::-1]  # not contiguous, not int32
    out = check_triangles("triangles", tri, 4)
    assert out.dtype == np.int32 and out.flags.c_contiguous and out.tolist() == [[2, 1, 0], [3, 1, 2]]
    with pytest.raises(ValueError, match=r"^faces: expected shape \(m, 3\), got \(4,\)$"):
        check_triangles("faces", np.arange(4), 4)
    with pytest.raises(TypeError, match=r"^triangles: expected integer vertex indices, got dtype float32$"):
        check_triangles("triangles", np.zeros((1, 3), np.float32), 4)
    with pytest.raises(ValueError, match=r"^triangles: expected indices in \[0, 3\), got \[0, 3\]$"):
        check_triangles("triangles", [[0, 1, 3]], 3)
    with pytest.raises(ValueError, match=r"got \[-1, 1\]"):
        check_triangles("triangles", [[0, 1, -1]])
    assert check_triangles("triangles", np.zeros((0, 3), np.float64), 0).shape == (0, 3)  # empty: any dtype


def test_check_triangle_shape_for_arrays_not_on_the_host():
    check_triangle_shape("t", (5, 3), np.int32)
    with pytest.raises(ValueError, match=r"^t: expected shape \(m, 3\), got \(5, 4\)$"):
        check_triangle_shape("t", (5, 4), np.int32)
    with pytest.raises(TypeError, match="dtype float64"):
        check_triangle_shape("t", (5, 3), np.float64)


def test_check_viewport_one_rule_for_both_sides():
    assert check_viewport(np.int64(640), 1) == (640, 1)
    assert check_pixels("w", MAX_VIEWPORT) == MAX_VIEWPORT
    with pytest.raises(ValueError, match=rf"^height: expected 1\.\.{MAX_VIEWPORT} pixels, got 0$"):
        check_viewport(64, 0)
    with pytest.raises(ValueError, match=r"^camera.width: expected 1\.\.16384 pixels, got 16385$"):
        check_viewport(16385, 64, names=("camera.width", "camera.height"))
    for bad in (64.0, True, "64"):
        with pytest.raises(TypeError, match=r"^width: expected an integer number of pixels"):
            check_viewport(bad, 64)


def test_check_choice_type_and_value():
    assert check_choice("spacing", "equal", ("equal", "fractional_odd")) == "equal"
    with pytest.raises(ValueError, match=r"^spacing: expected one of \['equal'\], got 'odd'$"):
        check_choice("spacing", "odd", ["equal"])
    with pytest.raises(TypeError, match=r"^spacing: expected one of"):
        check_choice("spacing", 1, ["equal"])
