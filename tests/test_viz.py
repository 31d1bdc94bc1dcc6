"""nmjax.viz: every picture is written atomically, in the format and size its callers rely on."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from nmjax import evaluate, viz
from nmjax.skeleton import skeleton_from_parents

PNG = b"\x89PNG\r\n\x1a\n"
PARENTS = (0, 0, 1, 2, 0, 4)


@pytest.fixture
def motion():
    rng = np.random.default_rng(0)
    return rng.uniform(-0.8, 0.8, (2, 7, len(PARENTS), 4)).astype(np.float32)


def only_file(folder):
    """The single file in `folder`: a temporary file left by a writer would be a second one."""
    (path,) = folder.iterdir()
    return path


def test_strongest_edges_pick_each_rows_largest_other_entry():
    affinity = np.array([[[0.0, 0.2, 0.9], [0.5, 9.0, 0.1], [0.3, 0.7, 0.0]]])
    assert viz.strongest_edges(affinity) == [(0, 2, 0.9), (1, 0, 0.5), (2, 1, 0.7)]


def test_plot_keypoints_and_draw_skeleton_write_pngs(tmp_path, motion):
    voxels = (np.random.default_rng(1).random((16, 16, 16)) > 0.9).astype(np.float32)
    affinity = np.random.default_rng(2).random((2, len(PARENTS), len(PARENTS)))
    viz.plot_keypoints(tmp_path / "kp" / "keypoints.png", voxels, motion[0, 0], affinity, "step 1")
    assert only_file(tmp_path / "kp").read_bytes()[:8] == PNG
    keep = np.array([True, True, True, False, True, True])
    skeleton = skeleton_from_parents(PARENTS)
    path = tmp_path / "sk" / "skeleton.png"
    viz.draw_skeleton(path, skeleton, motion[0, 0], voxels, keep, title="K=6")
    assert only_file(tmp_path / "sk") == path and path.read_bytes()[:8] == PNG


def test_plot_motion_shows_observed_over_generated(tmp_path, motion):
    path = tmp_path / "motion.png"
    viz.plot_motion(path, motion[0], motion[1], PARENTS, t_cond=3, columns=4)
    image = iio.imread(path)
    # figsize (2.2 * 4, 4.6) inches at 80 dpi
    assert only_file(tmp_path) == path and image.shape[:2] == (368, 704)


def test_motion_pictures_are_a_gif_of_every_frame_and_a_strip(tmp_path, motion):
    cloud = np.random.default_rng(3).uniform(-1, 1, (7, 20, 3))
    motions = list(motion[..., :3])
    viz.write_motion_pictures(tmp_path / "m", motions, ["a", "b"], PARENTS, clouds=[cloud, None])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.gif", "m.png"]
    gif = iio.imread(tmp_path / "m.gif")
    strip = iio.imread(tmp_path / "m.png")
    frames, height, width = gif.shape[:3]
    assert frames == 7 and width > height > 0  # two panels side by side
    assert strip.shape[:2] == (6 * height, width)  # six frames spread over the motion, stacked


def test_evaluation_plots_write_one_png_each(tmp_path):
    summary = evaluate.summarize_per_rate({"Ours": {3: {"a": 1.0, "b": 2.0}, 5: {"a": 3.0}}})
    viz.plot_mcd(tmp_path / "mcd" / "mcd.png", summary, title="M-CD")
    assert only_file(tmp_path / "mcd").read_bytes()[:8] == PNG
    entry = {"mean": 1.0, "ci95": 0.1}
    measures = ("diversity", "set_diversity", "bone_error", "set_distance")
    gen = {
        "methods": {m: {str(n): dict.fromkeys(measures, entry) for n in (25, 100)} for m in "ab"},
        "real": {str(n): {"set_diversity": entry, "bone_error": entry} for n in (25, 100)},
    }
    path = tmp_path / "gen" / "generation.png"
    viz.plot_generation(path, gen, reference=evaluate.REFERENCE, title="generation")
    assert only_file(tmp_path / "gen") == path and path.read_bytes()[:8] == PNG
