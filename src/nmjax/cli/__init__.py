"""The `nmjax` command: a dispatcher over one module per command group.

Each command is a `main(argv) -> int` function; the dispatcher turns the errors a command
expects (ValueError, OSError: a bad name, a missing folder, a damaged file) into one line on
stderr naming the input and the fix, exit status 2. A training that stops on a NaN loss exits 1.
Command modules are imported lazily so that `nmjax --help` and the data commands start without
loading JAX.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

# name -> (module under nmjax.cli, function, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "rig": (
        "rig",
        "rig",
        "your capture to a skinned, animated rig (.glb, .bvh) in one command",
    ),
    "prepare-data": ("data", "prepare_data", "write a dataset in the nmjax layout"),
    "synthesize": ("data", "synthesize", "generate one synthetic set and time it"),
    "train-skel": ("train", "train_skel", "phase 1: train the keypoint detector and affinity"),
    "extract-skeleton": (
        "runs",
        "extract_skeleton",
        "turn a phase-1 run's affinity into skeleton.json",
    ),
    "export-keypoints": (
        "runs",
        "export_keypoints",
        "write a phase-1 run's keypoints_{train,test}.npz (phase 2 reads them)",
    ),
    "refine": (
        "runs",
        "refine",
        "fit an articulated model to a phase-1 run's sequences (a refined skeleton)",
    ),
    "train-dyn": ("train", "train_dyn", "phase 2: train the VRNN dynamics on a phase-1 run"),
    "import-release": (
        "release",
        "import_release",
        "the authors' trained model as a phase-1 and a phase-2 run (no PyTorch)",
    ),
    "generate": ("tasks", "generate", "sample future motion from a phase-2 run"),
    "interpolate": ("tasks", "interpolate", "interpolate between two keyframes, with baselines"),
    "retarget": ("tasks", "retarget", "retarget a test motion onto a mesh (Eqs. 24-25, LBS)"),
    "evaluate": (
        "evaluate",
        "evaluate",
        "SC-score, 4D-tracking Chamfer, interpolation M-CD; --generation: generation measures",
    ),
    "bench": (
        "bench",
        "bench",
        "steps/s, load vs compute, compile time, memory of the train steps",
    ),
    "export": (
        "export",
        "export",
        "the rig and its motion as glTF 2.0 (.glb, .gltf) or BVH, for Blender and co.",
    ),
    "view": ("view", "view", "look at a run in 3D in the browser (viser), frame by frame"),
}


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (and exit status 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def parser(command: str, description: str) -> Parser:
    return Parser(prog=f"nmjax {command}", description=description)


def positive(parser: argparse.ArgumentParser, args: argparse.Namespace, *names: str) -> None:
    """Refuses (a usage error) any of the integer options `names` below 1."""
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {value}")


def one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: nmjax <command> [options]   (nmjax <command> --help for its options)", ""]
    lines += [f"  {name:<{width}}  {help_}" for name, (_, _, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(
            f"nmjax: unknown command {name!r}; valid commands: {', '.join(COMMANDS)}",
            file=sys.stderr,
        )
        return 2
    module, function, _ = COMMANDS[name]
    command = getattr(importlib.import_module(f"nmjax.cli.{module}"), function)
    try:
        return int(command(rest) or 0)
    except SystemExit as done:  # argparse: --help (0) or a usage error (2, already printed)
        return done.code if isinstance(done.code, int) else int(done.code is not None)
    except (ValueError, OSError) as err:
        print(f"nmjax {name}: {one_line(err)}", file=sys.stderr)
        return 2
    except RuntimeError as err:
        from nmjax.train.loop import NonFiniteLossError  # only the trainers load JAX

        if not isinstance(err, NonFiniteLossError):
            raise
        print(f"nmjax {name}: {one_line(err)}", file=sys.stderr)
        return 1
