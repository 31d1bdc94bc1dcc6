"""docs/architecture.md §4 conventions of nmjax.data.voxelize, against hand values and a loop
reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmjax.data.normalize import normalize_sequence
from nmjax.data.voxelize import voxel_indices, voxelize
from nmjax.metrics import voxel_points


def reference_voxelize(points: np.ndarray, grid: int) -> np.ndarray:
    """One point at a time, with Python floats: the formula as written in docs/architecture.md
    §4."""
    out = np.zeros((grid, grid, grid), dtype=np.float32)
    for p in points:
        idx = [min(max(math.floor((float(c) + 1.0) / (2.0 / grid + 1e-5)), 0), grid - 1) for c in p]
        out[idx[0], idx[1], idx[2]] = 1.0
    return out


def test_min_corner_and_far_end_of_longest_side():
    grid = 16
    # Box spans x in [2, 6] (longest, 4), y in [-1, 1], z in [0, 3]; two frames.
    frame0 = np.array([[2.0, -1.0, 0.0], [6.0, 1.0, 3.0], [4.0, 0.0, 1.5]])
    frame1 = np.array([[3.0, 0.5, 2.0], [5.0, -0.5, 1.0], [2.5, 0.0, 0.5]])
    points, _ = normalize_sequence(np.stack([frame0, frame1]))
    assert points.dtype == np.float32
    np.testing.assert_allclose(points[0, 0], [-1.0, -1.0, -1.0], atol=1e-6)
    # Far end of the longest side: 2 * 4 / (4 + 1e-5) - 1, just below 1.
    np.testing.assert_allclose(points[0, 1, 0], 2 * 4 / (4 + 1e-5) - 1, rtol=1e-6)
    # Shorter sides are not centred: y spans 2 of the 4 units, i.e. [-1, 0).
    np.testing.assert_allclose(points[0, 1, 1], 2 * 2 / (4 + 1e-5) - 1, atol=1e-6)
    cells = voxel_indices(points, grid)
    np.testing.assert_array_equal(cells[0, 0], [0, 0, 0])
    assert cells[0, 1, 0] == grid - 1
    grids = voxelize(points, grid)
    assert grids.shape == (2, grid, grid, grid) and grids.dtype == np.float32
    assert grids[0, 0, 0, 0] == 1.0
    assert grids[0, grid - 1].sum() >= 1.0


def test_joints_follow_the_same_map():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(3, 50, 3)) * [3.0, 1.0, 0.5] + [10.0, -2.0, 4.0]
    joints = rng.normal(size=(3, 7, 3))
    p_norm, j_norm = normalize_sequence(points, joints)
    bmin = points.reshape(-1, 3).min(axis=0)
    longest = (points.reshape(-1, 3).max(axis=0) - bmin).max()
    np.testing.assert_allclose(j_norm, 2 * (joints - bmin) / (longest + 1e-5) - 1, rtol=1e-5)
    np.testing.assert_allclose(p_norm, 2 * (points - bmin) / (longest + 1e-5) - 1, atol=1e-5)
    assert j_norm.dtype == np.float32


def test_batched_sequences_use_their_own_box():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, size=(4, 30, 3))
    b = rng.uniform(5, 9, size=(4, 30, 3))
    batched, _ = normalize_sequence(np.stack([a, b]))
    np.testing.assert_allclose(batched[0], normalize_sequence(a)[0], atol=1e-6)
    np.testing.assert_allclose(batched[1], normalize_sequence(b)[0], atol=1e-6)


def test_voxel_points_on_linspace_grid():
    grid = 5
    voxels = np.zeros((grid, grid, grid), dtype=np.float32)
    voxels[0, 0, 0] = 1.0
    voxels[4, 2, 1] = 1.0
    voxels[1, 1, 1] = 0.3  # below the threshold
    pts = voxel_points(voxels)
    np.testing.assert_allclose(pts, [[-1.0, -1.0, -1.0], [1.0, 0.0, -0.5]])
    assert voxel_points(np.zeros((3, 3, 3))).shape == (0, 3)


@pytest.mark.parametrize(
    "bad, match",
    [(np.zeros((5, 3)), r"\(\.\.\., T, N, 3\)"), (np.zeros((2, 0, 3)), "no frames or no points")],
)
def test_bad_points(bad, match):
    with pytest.raises(ValueError, match=match):
        normalize_sequence(bad)


def test_bad_joints_and_grid():
    with pytest.raises(ValueError, match="leading"):
        normalize_sequence(np.zeros((3, 4, 3)), np.zeros((2, 5, 3)))
    with pytest.raises(ValueError, match="grid"):
        voxelize(np.zeros((4, 3)), 0)
    with pytest.raises(ValueError, match="cubic"):
        voxel_points(np.zeros((2, 3, 3)))


coords = st.floats(-50.0, 50.0, allow_nan=False, width=32)


@settings(max_examples=40, deadline=None)
@given(
    data=st.lists(st.tuples(coords, coords, coords), min_size=2, max_size=40),
    frames=st.integers(1, 3),
    grid=st.sampled_from([2, 3, 8, 16, 64]),
)
def test_properties(data, frames, grid):
    pts = np.asarray(data, dtype=np.float32)
    seq = np.stack([pts + np.float32(t) for t in range(frames)])
    norm, _ = normalize_sequence(seq)
    # < 1 exactly in float64; the float32 cast may round the far end up to 1.0 for wide boxes.
    assert np.all(norm >= -1.0) and np.all(norm <= 1.0)
    np.testing.assert_allclose(norm.reshape(-1, 3).min(axis=0), -1.0, atol=1e-6)
    vox = voxelize(norm, grid)
    for t in range(frames):
        np.testing.assert_array_equal(vox[t], reference_voxelize(norm[t], grid))
        occupied = voxel_points(vox[t])
        assert occupied.shape[0] == int(vox[t].sum())
        cells = voxel_indices(norm[t], grid)
        assert np.unique(cells, axis=0).shape[0] == int(vox[t].sum())
    # The far end of the longest side always lands in the last cell.
    flat = norm.reshape(-1, 3)
    span = seq.reshape(-1, 3).max(axis=0) - seq.reshape(-1, 3).min(axis=0)
    if span.max() > 1e-2:  # below ~1e-3 the +1e-5 keeps the far end out of the last cell
        axis = int(np.argmax(span))
        assert voxel_indices(flat[:, axis : axis + 1], grid).max() == grid - 1
