"""The `nmjax` command: one subcommand per stage, each implemented by a `main(argv)` function.

Subcommands are imported lazily so that `nmjax --help` and the data commands start without
loading JAX.
"""

from __future__ import annotations

import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "prepare-data": ("nmjax.data.prepare", "write a dataset in the nmjax layout"),
    "train-skel": ("nmjax.train.skel", "phase 1: train the keypoint detector and affinity"),
    "extract-skeleton": ("nmjax.skeleton_cli", "turn a phase-1 run's affinity into skeleton.json"),
    "train-dyn": ("nmjax.train.dyn", "phase 2: train the VRNN dynamics on a phase-1 run"),
    "generate": ("nmjax.commands.generate", "sample future motion from a phase-2 run"),
    "interpolate": (
        "nmjax.commands.interpolate",
        "interpolate between two keyframes, with baselines",
    ),
    "retarget": ("nmjax.commands.retarget", "retarget a test motion onto a mesh (Eqs. 24-25, LBS)"),
    "evaluate": (
        "nmjax.evaluate",
        "SC-score, 4D-tracking Chamfer, interpolation M-CD; --generation: generation measures",
    ),
    "bench": ("nmjax.bench", "steps/s, load vs compute, compile time, memory of the train steps"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: nmjax <command> [options]   (nmjax <command> --help for its options)", ""]
    lines += [f"  {name:<{width}}  {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"nmjax: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    return int(module.main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
