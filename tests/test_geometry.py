"""Frames, cell indexing and poses (evgrid.geometry)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from evgrid.geometry import SE2, SE3, GridSpec, matrix_to_quaternion, quaternion_to_matrix

SPEC = GridSpec()


def test_default_grid_is_the_papers():
    assert SPEC.shape == (512, 512)
    assert SPEC.resolution == pytest.approx(0.078125)


def test_cell_convention_hand_computed():
    # row 0 is the front edge, column 0 the left edge; the ego origin is the corner of 4 cells
    assert tuple(int(v) for v in SPEC.xy_to_cell(19.99, 19.99)) == (0, 0)
    assert tuple(int(v) for v in SPEC.xy_to_cell(-19.99, -19.99)) == (511, 511)
    assert tuple(int(v) for v in SPEC.xy_to_cell(0.01, 0.01)) == (255, 255)
    assert tuple(int(v) for v in SPEC.xy_to_cell(-0.01, 0.01)) == (256, 255)
    # 10 m ahead: 128 cells in front of the centre line
    assert tuple(int(v) for v in SPEC.xy_to_cell(10.0 + 1e-9, 0.0 + 1e-9)) == (127, 255)
    x, y = SPEC.cell_to_xy(0, 511)
    assert (x, y) == pytest.approx((20 - 0.5 * SPEC.resolution, -20 + 0.5 * SPEC.resolution))


def test_grid_spec_validation():
    with pytest.raises(ValueError, match="even"):
        GridSpec(n_cells=511)
    with pytest.raises(ValueError, match="length_m"):
        GridSpec(length_m=-1.0)
    assert GridSpec.from_dict(GridSpec(256, 20.0).to_dict()) == GridSpec(256, 20.0)


@given(st.floats(-19.9, 19.9), st.floats(-19.9, 19.9))
def test_cell_roundtrip(x, y):
    r, c = SPEC.xy_to_cell(x, y)
    cx, cy = SPEC.cell_to_xy(r, c)
    assert abs(cx - x) <= SPEC.resolution / 2 + 1e-9
    assert abs(cy - y) <= SPEC.resolution / 2 + 1e-9
    u, v = SPEC.xy_to_uv(x, y)
    assert abs(u - r) <= 0.5 + 1e-9 and abs(v - c) <= 0.5 + 1e-9


@given(st.floats(-200, 200), st.floats(-200, 200))
def test_map_cells_align_with_local_cells_at_identity(x, y):
    # away from cell edges, where the two float expressions may round to either side
    edge = min(abs(v / SPEC.resolution - round(v / SPEC.resolution)) for v in (x, y))
    assume(edge > 1e-9)
    r, c = SPEC.xy_to_cell(x, y)
    R, C = SPEC.map_xy_to_cell(x, y)
    assert (R, C) == (r - 256, c - 256)
    mx, my = SPEC.map_cell_to_xy(R, C)
    lx, ly = SPEC.cell_to_xy(r, c)
    assert (mx, my) == pytest.approx((lx, ly))


def test_se2_compose_inverse_apply():
    a = SE2(1.0, 2.0, math.pi / 2)
    # rotate (1, 0) by 90 degrees then translate
    np.testing.assert_allclose(a.apply(np.array([[1.0, 0.0]])), [[1.0, 3.0]], atol=1e-12)
    ident = a @ a.inverse()
    assert (ident.x, ident.y, ident.yaw) == pytest.approx((0, 0, 0), abs=1e-12)
    b = SE2(-3.0, 0.5, 0.3)
    np.testing.assert_allclose((a @ b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    with pytest.raises(ValueError, match="finite"):
        SE2(float("nan"), 0, 0)


@given(
    st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
        lambda q: sum(v * v for v in q) > 0.01
    )
)
def test_quaternion_roundtrip(q):
    r = quaternion_to_matrix(q)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(r)), r, atol=1e-9)


def test_se3_from_nuscenes_quaternion_and_planar_part():
    yaw = 0.7
    q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]  # [w, x, y, z] about z
    p = SE3.from_quaternion(q, [10.0, -2.0, 0.5])
    assert p.yaw == pytest.approx(yaw)
    s = p.to_se2()
    assert (s.x, s.y, s.yaw) == pytest.approx((10.0, -2.0, yaw))
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 2.0]])
    np.testing.assert_allclose(p.inverse().apply(p.apply(pts)), pts, atol=1e-12)
    np.testing.assert_allclose((p @ p.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(SE3.from_matrix(p.matrix()).matrix(), p.matrix())
    np.testing.assert_allclose(SE3.from_se2(s, 0.5).matrix(), p.matrix(), atol=1e-12)


def test_se3_rejects_bad_input():
    with pytest.raises(ValueError, match="orthonormal"):
        SE3(np.ones((3, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="3x3"):
        SE3(np.eye(2), np.zeros(3))
    with pytest.raises(ValueError, match="quaternion"):
        SE3.from_quaternion([0, 0, 0, 0], [0, 0, 0])


def test_composition_skips_validation_but_equals_the_checked_pose(monkeypatch):
    # Poses composed from valid poses are built unchecked (a mapping update composes tens of
    # them); the public constructor still validates user data.
    a = SE3.from_quaternion([math.cos(0.2), 0.0, 0.0, math.sin(0.2)], [1.0, -2.0, 0.3])
    b = SE3.from_quaternion([math.cos(-0.6), 0.0, math.sin(-0.6), 0.0], [0.5, 4.0, -1.0])
    calls = []
    checked = SE3.__post_init__
    monkeypatch.setattr(SE3, "__post_init__", lambda self: (calls.append(1), checked(self))[1])
    c = a @ b.inverse()
    d = SE3.identity() @ SE3.from_se2(c.to_se2())
    assert calls == []
    assert c == SE3(c.rotation, c.translation) and len(calls) == 1
    assert (
        d.rotation.shape == (3, 3)
        and d.translation.shape == (3,)
        and d.rotation.dtype == np.float64
    )
    with pytest.raises(ValueError, match="finite"):
        SE3.from_se2(SE2(0.0, 0.0, 0.0), float("inf"))
    with pytest.raises(ValueError, match="finite"):
        SE3(np.eye(3), np.array([0.0, np.nan, 0.0]))
