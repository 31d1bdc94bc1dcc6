"""`nmjax view`: the drawing functions, the scene of each kind of folder checked through viser's
server-side handles, its one-line errors, recordings, and a real browser on the served page."""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time

import numpy as np
import pytest
from browser import Chromium, require_browser
from tiny_runs import PARENTS, make_runs

from nmjax import atomic, run_folder, tasks, view
from nmjax.cli import main as nmjax_main
from nmjax.train import trained

K = len(PARENTS)
# Nodes 2 and 4 fall below the pruning threshold (0.2): 3 and 5 then hang off node 1.
INTENSITIES = np.array([0.9, 0.8, 0.1, 0.7, 0.05, 0.6])
KEPT_BONES = [(0, 1), (1, 3), (1, 5)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def opened(folder, **options):
    viewer = view.open_view(folder, port=free_port(), **options)
    try:
        yield viewer
    finally:
        viewer.stop()


def one_error_line(argv, capsys) -> str:
    assert nmjax_main(["view", *argv]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("nmjax view")
    return lines[0]


# --- drawing functions ------------------------------------------------------------------------


def test_keypoint_colors_are_distinct_by_index_and_grey_when_pruned():
    keep = np.array([True, True, False, True])
    colors = view.keypoint_colors(4, keep)
    assert colors.dtype == np.uint8 and colors.shape == (4, 3)
    assert tuple(colors[2]) == view.GREY
    kept = colors[keep]
    assert len({tuple(c) for c in kept}) == 3 and view.GREY not in {tuple(c) for c in kept}


def test_keypoint_radii_grow_with_alpha_from_a_floor():
    radii = view.keypoint_radii(np.array([-1.0, 0.0, 0.5, 1.0, 2.0]), radius=2.0)
    np.testing.assert_allclose(radii, [0.6, 0.6, 1.3, 2.0, 2.0])


def test_bone_pairs_skip_the_root_and_pruned_children():
    np.testing.assert_array_equal(
        view.bone_pairs(PARENTS), [(0, 1), (1, 2), (2, 3), (1, 4), (4, 5)]
    )
    keep = INTENSITIES >= 0.2
    np.testing.assert_array_equal(view.bone_pairs([0, 0, 1, 1, 1, 1], keep), KEPT_BONES)
    assert view.bone_pairs([0], None).shape == (0, 2)


def test_affinity_pairs_take_the_stronger_direction_normalised():
    influence = np.array([[0.0, 0.2, 0.1], [0.4, 0.0, 0.05], [0.0, 0.3, 0.0]])
    pairs, strength = view.affinity_pairs(influence)
    np.testing.assert_array_equal(pairs, [(0, 1), (0, 2), (1, 2)])
    np.testing.assert_allclose(strength, [1.0, 0.25, 0.75])
    assert not view.affinity_pairs(np.zeros((3, 3)))[1].any()


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) (P, 4) applied to vectors (P, 3)."""
    w, u = q[:, :1], q[:, 1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def test_cylinders_span_their_segments_in_every_direction():
    rng = np.random.default_rng(0)
    starts = rng.normal(size=(6, 3))
    ends = starts + np.concatenate([rng.normal(size=(4, 3)), [[0, 0, 0.7], [0, 0, -0.7]]])
    centres, q, lengths = view.cylinder_transforms(starts, ends)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0)
    tip = rotate(q, np.tile([0.0, 0.0, 0.5], (6, 1))) * lengths[:, None]
    np.testing.assert_allclose(centres + tip, ends, atol=1e-9)
    np.testing.assert_allclose(centres - tip, starts, atol=1e-9)


def test_view_axes_put_up_towards_the_viewer_and_right_at_right_angles():
    for axis in range(3):
        up, towards, right = view.view_axes(axis)
        assert up[axis] == 1.0
        np.testing.assert_allclose(
            np.stack([up, towards, right]) @ np.stack([up, towards, right]).T, np.eye(3)
        )
    up, towards, right = view.view_axes(2)  # z up: seen from -y, x to the right
    np.testing.assert_array_equal(towards, [0, -1, 0])
    np.testing.assert_array_equal(right, [1, 0, 0])


# --- the tiny runs ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The suite's tiny runs, their phase-1 run given the files training writes at its end
    (affinity.npy, keypoint_stats.npz, the train split's keypoints: two sequences to choose
    from) and intensities that prune nodes 2 and 4."""
    from nmjax.skeleton import prune, skeleton_from_parents

    folders = make_runs(tmp_path_factory.mktemp("tiny-view"))
    skel = folders["skel"]
    trained.export_keypoints(skel, "train")
    tree = skeleton_from_parents(np.array(PARENTS))
    pruned, keep = prune(tree, INTENSITIES)  # as `extract_run_skeleton` stores them
    tree.save(
        skel / run_folder.SKELETON_FILE,
        intensities=INTENSITIES,
        pruned_parents=list(pruned.parents),
        keep=keep.tolist(),
    )
    affinity = np.random.default_rng(1).random((2, K, K)).astype(np.float32)
    affinity[:, np.arange(K), np.arange(K)] = 0.0
    atomic.save_npy(skel / run_folder.AFFINITY_FILE, affinity)
    atomic.save_npz(
        skel / run_folder.STATS_FILE,
        intensities=INTENSITIES.astype(np.float32),
        rest_positions=np.zeros((K, 3), np.float32),
        example_voxels=np.zeros((16, 16, 16), np.float32),
        example_keypoints=np.zeros((K, 4), np.float32),
    )
    return folders


def sequence_frames(tiny, split, name):
    from nmjax.data.datasets import load_sequences

    (seq,) = [s for s in load_sequences("synth-arm", split, tiny["data"]) if s.name == name]
    return trained.sequence_points(seq, 1)


def test_phase1_scene_follows_the_frame_slider(tiny):
    from nmjax.data.voxelize import voxelize
    from nmjax.metrics import voxel_points
    from nmjax.skeleton import influence

    trajectories = run_folder.load_trajectories(tiny["skel"], "train")
    assert len(trajectories) == 2
    with opened(tiny["skel"], split="train") as viewer:
        names = {
            "/body/points",
            "/body/voxels",
            "/keypoints",
            "/skeleton/bones",
            "/skeleton/root",
            "/truth/keypoints",
            "/truth/skeleton/bones",
            "/affinity",
        }
        assert names <= set(viewer.nodes)
        assert all(viewer.nodes[name].name == name for name in names)
        name = viewer.sequence.value
        assert name == sorted(trajectories)[0]
        keypoints = trajectories[name]
        points, joints = sequence_frames(tiny, "train", name)
        pose = viewer.pose
        grey = [tuple(c) == view.GREY for c in pose.keypoints.batched_colors]
        assert grey == list(INTENSITIES < 0.2)  # the pruned nodes 2 and 4
        np.testing.assert_array_equal(pose.pairs, KEPT_BONES)
        _, strength = view.affinity_pairs(
            influence(np.load(tiny["skel"] / run_folder.AFFINITY_FILE))
        )
        np.testing.assert_allclose(viewer.affinity.batched_opacities, strength, rtol=1e-6)
        for t in (4, len(keypoints) - 1, 0):
            viewer.frame.value = t
            x = keypoints[t]
            np.testing.assert_allclose(pose.keypoints.batched_positions, x[:, :3], atol=1e-6)
            np.testing.assert_allclose(
                pose.keypoints.batched_scales, view.keypoint_radii(x[:, 3]), rtol=1e-6
            )
            np.testing.assert_allclose(pose.bones.points, x[np.array(KEPT_BONES), :3], atol=1e-6)
            np.testing.assert_allclose(pose.root_marker.position, x[0, :3], atol=1e-6)
            np.testing.assert_allclose(viewer.body.points, points[t], atol=2e-3)  # float16
            np.testing.assert_allclose(
                viewer.truth.keypoints.batched_positions, joints[t], atol=1e-6
            )
            centres, _, lengths = view.cylinder_transforms(x[[0], :3], x[[1], :3])
            np.testing.assert_allclose(viewer.affinity.batched_positions[0], centres[0], atol=1e-6)
            np.testing.assert_allclose(viewer.affinity.batched_scales[0, 2], lengths[0], rtol=1e-5)

        viewer.body_mode.value = "voxels"
        assert viewer.voxels.visible and not viewer.body.visible
        cells = voxel_points(voxelize(points[0], 16))
        np.testing.assert_allclose(viewer.voxels.points, cells, atol=2e-3)
        viewer.toggles["skeleton"].value = False
        assert not pose.bones.visible and not pose.root_marker.visible and pose.keypoints.visible
        assert not viewer.affinity.visible  # off until asked for
        viewer.toggles["affinity"].value = True
        assert viewer.affinity.visible

        other = sorted(trajectories)[1]
        viewer.frame.value = 3
        viewer.sequence.value = other
        assert viewer.frame.value == 0 and viewer.frame.max == len(trajectories[other]) - 1
        np.testing.assert_allclose(
            pose.keypoints.batched_positions, trajectories[other][0, :, :3], atol=1e-6
        )

        viewer.fps.value = 30
        viewer.playing.value = True
        deadline = time.monotonic() + 5.0
        while viewer.frame.value == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert viewer.frame.value != 0
        port = viewer.server.get_port()
    assert not any(t.name == "nmjax-view-play" for t in threading.enumerate())
    view.check_port("127.0.0.1", port)  # released: free to listen on again


def test_phase1_scene_shows_the_refined_skeleton_of_a_refined_sequence(tiny, tmp_path):
    import shutil

    from nmjax.export.refine import refine_run
    from nmjax.skeleton_refine import RefineSettings

    run = tmp_path / "skel"
    shutil.copytree(tiny["skel"], run)
    names = sorted(run_folder.load_trajectories(run, "train"))
    settings = RefineSettings(iterations=2, surface_points=48, target_points=48)
    refine_run(run, seq=names[0], split="train", settings=settings, progress=False)
    refined = run_folder.read_refined(run, "train", names[0])
    with opened(run, split="train", seq=names[0]) as viewer:
        assert {"/refined/keypoints", "/refined/skeleton/bones"} <= set(viewer.nodes)
        pose = viewer.refined
        np.testing.assert_array_equal(pose.pairs, view.bone_pairs(refined["parents"]))
        for t in (0, 3):
            viewer.frame.value = t
            np.testing.assert_allclose(
                pose.keypoints.batched_positions, refined["positions"][t], atol=1e-6
            )
        assert pose.keypoints.visible
        viewer.toggles["refined skeleton"].value = False
        assert not pose.keypoints.visible and not pose.bones.visible
        viewer.toggles["refined skeleton"].value = True
        viewer.sequence.value = names[1]  # not refined: nothing of it drawn
        assert not pose.keypoints.visible and not pose.bones.visible


@pytest.mark.slow  # compiles generation, both interpolations and Slerp: ~10 s
def test_phase2_scene_shows_generation_and_interpolation(tiny):
    cond, gen, gap = 2, 3, 3
    trajectories = run_folder.load_trajectories(tiny["skel"], "test")
    options = dict(cond=cond, gen=gen, samples=2, gap=gap, trajectories=2)
    with opened(tiny["nm"], **options) as viewer:
        panels = ["observed", "sample_1", "sample_2"]
        methods = ["truth", "Ours", "VRNN", "Lerp", "Slerp"]  # VRNN: the run found beside
        prefixes = [f"/generate/{p}" for p in panels] + [f"/interpolate/{m}" for m in methods]
        for prefix in prefixes:
            for node in ("", "/keypoints", "/skeleton/bones", "/label"):
                assert prefix + node in viewer.nodes
        assert viewer.num_frames == cond + gen
        truth = trajectories[viewer.sequence.value]
        for t in range(cond + gen):
            viewer.frame.value = t
            at = {p: viewer.panels[p].keypoints.batched_positions for p in prefixes}
            np.testing.assert_allclose(at["/generate/observed"], truth[t, :, :3], atol=1e-6)
            if t < cond:  # a generated motion starts with the frames it was given
                np.testing.assert_allclose(at["/generate/sample_1"], truth[t, :, :3], atol=1e-6)
            i = min(t, gap)  # the interpolations hold their last frame
            lerp = truth[0, :, :3] + i / gap * (truth[gap, :, :3] - truth[0, :, :3])
            np.testing.assert_allclose(at["/interpolate/Lerp"], lerp, atol=1e-5)
            np.testing.assert_allclose(at["/interpolate/truth"], truth[i, :, :3], atol=1e-6)
            sample_bones = tuple(viewer.panels["/generate/sample_1"].bones.colors[0, 0])
            assert sample_bones == (view.GENERATED_BONE_COLOR if t >= cond else view.BONE_COLOR)
        viewer.toggles["interpolate: Slerp"].value = False
        assert not viewer.nodes["/interpolate/Slerp"].visible


def test_phase2_scene_draws_every_panel_from_the_task_outputs(tiny, monkeypatch):
    """The phase-2 scene of the test above without compiling the tasks: generation and
    interpolation give known motions (each panel its own offset of the sequence), and every
    panel draws its motion frame by frame, for the sequence the dropdown picks."""
    cond, gen, gap = 2, 3, 3
    trajectories = run_folder.load_trajectories(tiny["skel"], "test")
    asked = []

    def generate(self, name, cond, gen, samples, seed):
        asked.append(name)
        observed = trajectories[name][: cond + gen]
        return observed, np.stack([observed + 0.01 * (s + 1) for s in range(samples)])

    def interpolate(self, name, gap, trajectories_, seed):
        truth = trajectories[name][: gap + 1]
        return truth, {m: truth + 0.1 * (i + 1) for i, m in enumerate(self.methods)}

    monkeypatch.setattr(view.Phase2Data, "generate", generate)
    monkeypatch.setattr(view.Phase2Data, "interpolate", interpolate)
    options = dict(cond=cond, gen=gen, samples=2, gap=gap, trajectories=2)
    with opened(tiny["nm"], **options) as viewer:
        methods = ["Ours", "VRNN", "Lerp", "Slerp"]  # VRNN: the run found beside
        panels = {"/generate/observed": 0.0, "/generate/sample_1": 0.01}
        panels |= {"/generate/sample_2": 0.02, "/interpolate/truth": 0.0}
        panels |= {f"/interpolate/{m}": 0.1 * (i + 1) for i, m in enumerate(methods)}
        for prefix in panels:
            for node in ("", "/keypoints", "/skeleton/bones", "/label"):
                assert prefix + node in viewer.nodes
        assert viewer.num_frames == cond + gen
        for name in sorted(trajectories)[::-1]:  # the first shown, then the other picked
            viewer.sequence.value = name
            assert asked[-1] == name
            truth = trajectories[name][:, :, :3]
            for t in range(cond + gen):
                viewer.frame.value = t
                for prefix, offset in panels.items():
                    i = t if prefix.startswith("/generate") else min(t, gap)  # held at the end
                    drawn = viewer.panels[prefix].keypoints.batched_positions
                    np.testing.assert_allclose(drawn, truth[i] + offset, atol=1e-6, err_msg=prefix)
                sample = tuple(viewer.panels["/generate/sample_1"].bones.colors[0, 0])
                assert sample == (view.GENERATED_BONE_COLOR if t >= cond else view.BONE_COLOR)
                ours = tuple(viewer.panels["/interpolate/Ours"].bones.colors[0, 0])
                inside = 0 < t < gap
                assert ours == (view.GENERATED_BONE_COLOR if inside else view.BONE_COLOR)
        viewer.toggles["interpolate: Slerp"].value = False
        assert not viewer.nodes["/interpolate/Slerp"].visible


def test_retarget_scene_poses_the_mesh_per_frame(tmp_path):
    frames, parents = 3, np.array([0, 0, 1])
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    vertices = np.stack([base + [0.1 * t, 0.0, 0.0] for t in range(frames)])
    for t in range(frames):
        tasks.write_obj(tmp_path / tasks.RETARGET_FRAME.format(t), vertices[t], faces)
    joints = np.stack([base[:3] + [0.1 * t, 0.0, 0.0] for t in range(frames)]).astype(np.float32)
    source = np.concatenate([joints * 0.5, np.ones((frames, 3, 1), np.float32)], axis=-1)
    atomic.save_npz(
        tmp_path / tasks.RETARGET_FILE,
        source_keypoints=source,
        target_keypoints=source[0],
        joints=joints,
        skin_weights=np.ones((4, 3)) / 3,
        parents=parents,
        source=np.array("seq_000"),
    )
    with opened(tmp_path) as viewer:
        assert {"/target/mesh", "/target/keypoints", "/source/keypoints"} <= set(viewer.nodes)
        assert viewer.num_frames == frames
        for t in (2, 0):
            viewer.frame.value = t
            np.testing.assert_allclose(viewer.mesh.vertices, vertices[t], atol=1e-6)
            np.testing.assert_allclose(viewer.target.keypoints.batched_positions, joints[t])
            moved = viewer.source_pose.keypoints.batched_positions
            # The source moves 0.05 a frame; scaled to the mesh's size (1.2 / 0.6) that is 0.1.
            step = moved - viewer.source[0, :, :3]
            np.testing.assert_allclose(step, np.tile([0.1 * t, 0.0, 0.0], (3, 1)), atol=1e-6)
    (tmp_path / tasks.RETARGET_FRAME.format(0)).unlink()
    with pytest.raises(ValueError, match="3 frames of joints"):
        tasks.read_retarget(tmp_path)
    for t in (1, 2):
        (tmp_path / tasks.RETARGET_FRAME.format(t)).unlink()
    with pytest.raises(FileNotFoundError, match="unfinished retarget output"):
        view.open_view(tmp_path, port=free_port())


# --- the command --------------------------------------------------------------------------------


def test_a_bvh_file_is_named_for_what_view_shows(tmp_path, capsys):
    bvh = tmp_path / "rig.bvh"
    bvh.write_text("HIERARCHY\nROOT joint0\n")
    line = one_error_line(["--run", str(bvh)], capsys)
    assert "rig.bvh is a .bvh file" in line and ".glb / .gltf" in line
    assert "does not exist" not in line


def test_missing_unfinished_and_foreign_folders_are_one_line_errors(tiny, tmp_path, capsys):
    line = one_error_line(["--run", str(tmp_path / "nope")], capsys)
    assert "nope" in line and "does not exist" in line
    assert "holds neither" in one_error_line(["--run", str(tmp_path)], capsys)
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "config.json").write_text((tiny["skel"] / "config.json").read_text())
    line = one_error_line(["--run", str(unfinished)], capsys)
    assert "keypoints_test.npz" in line and "nmjax export-keypoints" in line
    line = one_error_line(["--run", str(tiny["skel"]), "--seq", "seq_999"], capsys)
    assert "'seq_999'" in line and "seq_00" in line
    assert "--port" in one_error_line(["--run", str(tiny["skel"]), "--port", "70000"], capsys)


def test_a_port_in_use_is_a_one_line_error(tiny, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = one_error_line(["--run", str(tiny["skel"]), "--port", str(port)], capsys)
    assert f"--port {port} is in use" in line


def test_without_viser_the_command_names_the_extra(tiny, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now raises ImportError
    assert ".[view]" in one_error_line(["--run", str(tiny["skel"])], capsys)


def test_record_writes_a_playback_file_of_every_frame(tiny, tmp_path):
    import msgspec
    import zstandard

    path = tmp_path / "run.viser"
    argv = ["view", "--run", str(tiny["skel"]), "--port", "0", "--record", str(path)]
    assert nmjax_main(argv) == 0
    raw = path.read_bytes()
    size = int.from_bytes(raw[:8], "little")  # viser's format: size, then one zstd frame
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=size)
    header = int.from_bytes(inner[:8], "little")
    recording = msgspec.msgpack.decode(inner[8 : 8 + header])
    trajectories = run_folder.load_trajectories(tiny["skel"], "test")
    frames = len(trajectories[sorted(trajectories)[0]])  # the sequence opened by default
    assert recording["durationSeconds"] == pytest.approx(frames / 10)
    named = {m[1].get("name") for m in recording["messages"] if isinstance(m[1], dict)}
    assert {"/keypoints", "/skeleton/bones", "/body/points"} <= named

    with opened(tiny["skel"]) as viewer:
        page = viewer.record(tmp_path / "run.html", progress=False).read_text()
    assert "__VISER_EMBED_DATA__" in page and page.lstrip().lower().startswith("<!doctype html")


# --- a real browser -----------------------------------------------------------------------------

# A screenshot's middle (left of the control panel, below the browser's notices) must vary more
# than this (pixel standard deviation, 0-255) to hold a drawn scene; a blank canvas has ~0.
VARIANCE_FLOOR = 3.0


def scene_spread(image: np.ndarray) -> float:
    h, w = image.shape[:2]
    return float(image[int(0.3 * h) : int(0.85 * h), int(0.08 * w) : int(0.6 * w)].std())


def test_a_browser_connects_and_draws_the_scene(tiny, tmp_path):
    executable = require_browser()  # skips without Chromium, except under CI=true
    with opened(tiny["skel"]) as viewer:
        connected = threading.Event()
        viewer.server.on_client_connect(lambda _: connected.set())
        with Chromium(executable) as browser:
            browser.open(viewer.url())
            assert connected.wait(60), "no client connected"
            drawn = browser.screenshot_until(lambda im: scene_spread(im) > VARIANCE_FLOOR)
            assert scene_spread(drawn) > VARIANCE_FLOOR
            for box in viewer.toggles.values():  # every layer off: the canvas goes blank
                box.value = False
            blank = browser.screenshot_until(lambda im: scene_spread(im) < VARIANCE_FLOOR)
            assert scene_spread(blank) < VARIANCE_FLOOR
