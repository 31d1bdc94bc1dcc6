"""The task output formats (`nmjax.tasks.outputs`): each writer read back by its reader, and the
one folder-kind rule that `nmjax view` and `nmjax export` share."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nmjax import run_folder, tasks, view
from nmjax.export import sources
from nmjax.tasks import outputs

PARENTS = [0, 0, 1, 1]
K = len(PARENTS)
RIG = {"frame_rate": np.float64(12.5), "up_axis": np.int64(1), "keep": np.array([1, 1, 0, 1], bool)}


def keypoints(rng, *shape):
    return rng.uniform(-0.8, 0.8, (*shape, K, 4)).astype(np.float32)


def test_generate_is_read_back_as_written_with_its_voxels(tmp_path):
    rng = np.random.default_rng(0)
    samples = keypoints(rng, 2, 3, 5)
    occupancy = rng.uniform(size=(2, 3, 5, 4, 4, 4)) >= 0.5
    path = outputs.write_generate(
        tmp_path,
        RIG,
        keypoints=samples,
        observed=samples[:, 0],
        observed_frames=np.array([5, 4], np.int32),
        names=["a", "b"],
        parents=PARENTS,
        cond=2,
        voxels=occupancy,
    )
    assert path == tmp_path / tasks.GENERATE_FILE
    arrays = outputs.read_generate(tmp_path)
    np.testing.assert_array_equal(arrays["keypoints"], samples)
    np.testing.assert_array_equal(arrays["observed_frames"], [5, 4])
    assert arrays["names"].tolist() == ["a", "b"] and arrays["parents"].tolist() == PARENTS
    assert int(arrays["cond"]) == 2
    rate, up, keep = outputs.rig_format(arrays, K)
    assert (rate, up) == (12.5, 1) and keep.tolist() == RIG["keep"].tolist()
    with np.load(tmp_path / outputs.GENERATE_VOXELS_FILE) as z:
        assert z["voxels"].dtype == np.uint8
        np.testing.assert_array_equal(z["voxels"], occupancy)
    assert outputs.folder_kind(tmp_path) == "generate"


def test_interpolate_keeps_its_methods_in_order_and_refuses_others(tmp_path):
    rng = np.random.default_rng(1)
    motions = {m: keypoints(rng, 1, 4) for m in ("Slerp", "Ours", "Lerp")}
    common = {"truth": motions["Ours"], "names": ["s"], "parents": PARENTS}
    with pytest.raises(ValueError, match=r"unknown interpolation methods \['Cubic'\]"):
        outputs.write_interpolate(tmp_path, RIG, {"Cubic": motions["Ours"]}, **common)
    outputs.write_interpolate(tmp_path, RIG, motions, **common)
    arrays = outputs.read_interpolate(tmp_path)
    assert outputs.interpolated_methods(arrays) == ["Ours", "Lerp", "Slerp"]
    for method, motion in motions.items():
        np.testing.assert_array_equal(arrays[method], motion)
    assert outputs.interpolation_methods(vrnn=False) == ["Ours", "Lerp", "Slerp"]
    assert outputs.interpolation_methods(vrnn=True) == list(outputs.INTERPOLATION_METHODS)
    assert outputs.folder_kind(tmp_path) == "interpolate"


def test_retarget_meshes_and_arrays_are_read_back(tmp_path):
    rng = np.random.default_rng(2)
    meshes = rng.normal(size=(3, 5, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    outputs.write_retarget(
        tmp_path,
        RIG,
        meshes,
        faces,
        source="walk",
        source_keypoints=keypoints(rng, 3),
        target_keypoints=keypoints(rng),
        joints=rng.normal(size=(3, K, 3)),
        skin_weights=np.full((5, K), 1.0 / K, np.float32),
        parents=PARENTS,
        rotations=np.broadcast_to(np.eye(3), (3, K, 3, 3)),
        rest_rotations=np.broadcast_to(np.eye(3), (K, 3, 3)),
        rest_joints=rng.normal(size=(K, 3)),
        rest_vertices=meshes[0],
    )
    assert sorted(p.name for p in tmp_path.glob("frame_*.obj")) == [
        tasks.RETARGET_FRAME.format(t) for t in range(3)
    ]
    read = outputs.read_retarget(tmp_path)
    np.testing.assert_allclose(read["vertices"], meshes, atol=1e-6)  # .obj keeps 6 decimals
    np.testing.assert_array_equal(read["faces"], faces)
    assert read["source"] == "walk" and read["parents"].tolist() == PARENTS
    arrays = outputs.read_retarget_arrays(tmp_path)
    assert arrays["rotations"].dtype == np.float32 and arrays["faces"].dtype == np.int64
    assert outputs.folder_kind(tmp_path) == "retarget"
    (tmp_path / tasks.RETARGET_FRAME.format(2)).unlink()
    with pytest.raises(ValueError, match="2 frame meshes but 3 frames of joints"):
        outputs.read_retarget(tmp_path)


def test_older_files_get_the_rig_defaults_and_missing_arrays_are_named(tmp_path):
    rate, up, keep = outputs.rig_format({}, K)
    assert (rate, up) == (outputs.DEFAULT_FRAME_RATE, outputs.DEFAULT_UP_AXIS)
    assert keep.tolist() == [True] * K
    with pytest.raises(FileNotFoundError, match="generate.npz not found; write it with"):
        outputs.read_generate(tmp_path)
    np.savez(tmp_path / tasks.INTERPOLATE_FILE, names=np.array(["s"]))
    with pytest.raises(ValueError, match="interpolate.npz lacks truth, parents"):
        outputs.read_interpolate(tmp_path)


def test_one_folder_kind_rule_for_view_and_export(tmp_path):
    assert outputs.folder_kind(tmp_path / "missing") is None
    assert outputs.folder_kind(tmp_path) is None
    skel, dyn, gen = tmp_path / "skel", tmp_path / "dyn", tmp_path / "gen"
    for folder, config in ((skel, {"seed": 0}), (dyn, {"skel_run": str(skel)})):
        folder.mkdir()
        (folder / run_folder.CONFIG_FILE).write_text(json.dumps(config))
    # A task output written into a run folder does not make it an output folder.
    np.savez(dyn / tasks.RETARGET_FILE, joints=np.zeros((1, K, 3)))
    gen.mkdir()
    np.savez(gen / tasks.GENERATE_FILE, keypoints=np.zeros((1, 1, 1, K, 4)))
    for folder, kind in ((skel, "skel"), (dyn, "dyn"), (gen, "generate")):
        assert outputs.folder_kind(folder) == kind
        assert sources.kind(folder) == kind  # `nmjax export`
    assert view.folder_kind(skel) == "skel" and view.folder_kind(dyn) == "dyn"
    with pytest.raises(FileNotFoundError, match="an `nmjax generate` output, which `nmjax view`"):
        view.folder_kind(gen)
    with pytest.raises(FileNotFoundError, match="holds no config.json, retarget.npz"):
        sources.kind(tmp_path)
    with pytest.raises(FileNotFoundError, match="holds neither config.json"):
        view.folder_kind(tmp_path)
