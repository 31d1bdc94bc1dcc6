"""Every `nmjax` subcommand answers a bad input with one line naming it, and exit status 2."""

from __future__ import annotations

import pytest

from nmjax.cli import COMMANDS
from nmjax.cli import main as nmjax_main

MISSING = "/nonexistent/nmjax-run"

# command -> [(argv after the command, text the one line must hold)]
BAD_INPUTS = {
    "rig": [
        (["--from", MISSING, "--out", "rig.glb"], MISSING),
        (["--from", MISSING, "--out", "rig.gltf"], ".glb"),
        (["--from", MISSING], "--out"),
        (["--from", MISSING, "--out", "rig.glb", "--steps", "0"], "--steps"),
        (["--from", MISSING, "--out", "rig.glb", "--minutes", "0"], "--minutes"),
        (["--from", MISSING, "--out", "rig.glb", "--steps", "5", "--minutes", "1"], "--steps"),
    ],
    "prepare-data": [(["--data", "nope"], "'nope'"), (["--data", "dfaust"], "--from")],
    "synthesize": [(["nope"], "nope")],
    "train-skel": [
        (["--data", "nope"], "'nope'"),
        (["--resume", "--run", MISSING], MISSING),
        (["--resume"], "--run"),
        (["--steps", "0"], "--steps"),
        (["--fit-minutes", "0"], "--fit-minutes"),
        (["--batch-size", "0"], "--batch-size"),
    ],
    "extract-skeleton": [(["--run", MISSING], MISSING), ([], "--run")],
    "export-keypoints": [(["--run", MISSING], MISSING), (["--split", "val"], "val")],
    "refine": [
        (["--run", MISSING], MISSING),
        ([], "--run"),
        (["--run", MISSING, "--iters", "0"], "--iters"),
        (["--run", MISSING, "--split", "val"], "val"),
    ],
    "train-dyn": [
        (["--data", "nope"], "'nope'"),
        (["--skel-run", MISSING], MISSING),
        (["--resume", "--run", MISSING], MISSING),
        (["--batch-size", "0"], "--batch-size"),
    ],
    "import-release": [
        ([MISSING + ".pth", "--options", MISSING + ".pickle", "--run", "out"], MISSING),
        ([MISSING + ".pth", "--run", "out"], "--options"),
    ],
    "generate": [
        (["--run", MISSING], MISSING),
        (["--run", MISSING, "--gen", "0"], "--gen"),
        (["--run", MISSING, "--source-file", "x.npy", "--source-rate", "0"], "--source-rate"),
    ],
    "interpolate": [(["--run", MISSING], MISSING), (["--run", MISSING, "--gap", "0"], "--gap")],
    "retarget": [
        (["--run", MISSING, "--target", MISSING + ".obj"], MISSING),
        (["--run", MISSING], "--target"),
        (
            ["--run", MISSING, "--target", "t.obj", "--source", "a", "--source-file", "a.npy"],
            "not both",
        ),
    ],
    "evaluate": [(["--run", MISSING], MISSING), (["--run", MISSING, "--rates", "x"], "--rates")],
    "bench": [(["--preset", "nope"], "nope"), (["--steps", "0"], "--steps")],
    "view": [(["--run", MISSING], MISSING), (["--run", MISSING, "--port", "-1"], "--port")],
    "export": [
        (["--run", MISSING, "--out", "rig.glb"], MISSING),
        (["--run", MISSING, "--out", "rig.fbx"], "'.fbx'"),
        (["--run", MISSING], "--out"),
        (["--run", MISSING, "--out", "rig.bvh", "--fps", "0"], "--fps"),
    ],
}


def test_every_command_has_bad_input_cases():
    assert set(BAD_INPUTS) == set(COMMANDS)


@pytest.mark.parametrize(
    ("command", "argv", "named"),
    [(c, argv, named) for c, cases in BAD_INPUTS.items() for argv, named in cases],
)
def test_bad_input_is_one_line_and_exit_2(command, argv, named, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a command that got past its checks would write here only
    assert nmjax_main([command, *argv]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert named in lines[0] and command in lines[0]
    assert not any(tmp_path.iterdir())


def test_unknown_command_lists_the_commands(capsys):
    assert nmjax_main(["trian-skel"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "'trian-skel'" in line and "train-skel" in line
