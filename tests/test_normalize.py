"""The episodic normalisation box (nmjax.data.normalize) against the formulas each caller wrote
on its own before it had one definition: the whole-crop box (training, evaluation), the box of a
clip's first frames (`dyn_inputs.clip_voxels`) and the box of one mesh (`nmjax retarget`)."""

from __future__ import annotations

import numpy as np
import pytest

from nmjax.data.normalize import apply_box, normalization_box, normalize_sequence, undo_box


@pytest.fixture
def cloud():
    rng = np.random.default_rng(7)
    return (rng.normal(size=(6, 40, 3)) * [2.0, 0.5, 1.0] + [3.0, -1.0, 8.0]).astype(np.float32)


def test_the_box_of_the_first_frames_is_the_clip_formula(cloud):
    box = np.asarray(cloud[:2], np.float64).reshape(-1, 3)
    bmin = box.min(axis=0)
    scale = 2.0 / (float(np.max(box.max(axis=0) - bmin)) + 1e-5)
    expected = ((np.asarray(cloud, np.float64) - bmin) * scale - 1.0).astype(np.float32)
    np.testing.assert_array_equal(normalize_sequence(cloud, box_frames=2)[0], expected)
    # Frames after the box's may leave the cube; a box over every frame is the plain map.
    assert normalize_sequence(cloud, box_frames=2)[0][2:].max() > -1.0
    for frames in (None, len(cloud), len(cloud) + 3):
        np.testing.assert_array_equal(
            normalize_sequence(cloud, box_frames=frames)[0], normalize_sequence(cloud)[0]
        )


def test_one_mesh_box_is_the_retarget_formula_and_undo_inverts_it(cloud):
    vertices = np.asarray(cloud[0], np.float64)  # (V, 3), one pose
    bmin = vertices.min(axis=0)
    scale = 2.0 / (float(np.max(vertices.max(axis=0) - bmin)) + 1e-5)
    box_min, box_scale = normalization_box(vertices[None])
    assert box_min.shape == (1, 1, 3) and box_scale.shape == (1, 1, 1)
    mapped = apply_box(vertices, box_min[0, 0], box_scale[0, 0])
    np.testing.assert_array_equal(mapped, (vertices - bmin) * scale - 1.0)
    assert mapped.shape == vertices.shape and mapped.dtype == np.float64
    back = undo_box(mapped, box_min[0, 0], box_scale[0, 0])
    np.testing.assert_allclose(back, vertices, atol=1e-9)


def test_the_whole_crop_box_is_the_sequence_formula(cloud):
    flat = np.asarray(cloud, np.float64).reshape(-1, 3)
    bmin = flat.min(axis=0)
    longest = (flat.max(axis=0) - bmin).max()
    expected = (2.0 * (np.asarray(cloud, np.float64) - bmin) / (longest + 1e-5) - 1.0).astype(
        np.float32
    )
    np.testing.assert_allclose(normalize_sequence(cloud)[0], expected, atol=1e-6)
