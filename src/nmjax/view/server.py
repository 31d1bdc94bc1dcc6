"""Starting a view: what a folder holds (`folder_kind`), the sequence asked for, a viser server on
exactly the port asked for, and the viewer of that kind (`open_view`). viser is imported here
only, when a viewer starts (`import_viser`)."""

from __future__ import annotations

import dataclasses
import socket
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from nmjax.view.exported import GltfViewer
from nmjax.view.phase1 import Phase1Viewer, read_phase1
from nmjax.view.phase2 import Phase2Viewer, RetargetViewer, read_phase2
from nmjax.view.viewer import Viewer

EXTRA = "view"  # the optional dependency group that installs viser
UP_AXES = ("x", "y", "z")


def import_viser():
    """The viser module, or an ImportError whose message names the extra that installs it."""
    try:
        import viser
    except ImportError as err:
        raise ImportError(
            f"nmjax view needs viser; install it with `pip install -e '.[{EXTRA}]'`"
        ) from err
    return viser


GLTF_SUFFIXES = (".glb", ".gltf")


def folder_kind(folder: str | Path) -> str:
    """What `folder` holds: "skel" (a phase-1 run), "dyn" (phase 2) or "retarget"
    (`tasks.folder_kind`); "gltf" for a .glb / .gltf file.

    Raises:
      FileNotFoundError: no such folder, or one that is neither a run nor a retarget output.
      ValueError: a file that is not .glb / .gltf (a .bvh, say).
    """
    from nmjax import run_folder, tasks

    folder = Path(folder)
    if folder.is_file() and folder.suffix.lower() in GLTF_SUFFIXES:
        return "gltf"
    if folder.is_file():
        raise ValueError(
            f"--run {folder} is a {folder.suffix or 'plain'} file; nmjax view shows the .glb / "
            ".gltf files of `nmjax export` (write one with `nmjax export --run RUN --out "
            "RIG.glb`), run folders and `nmjax retarget` outputs"
        )
    if not folder.is_dir():
        raise FileNotFoundError(
            f"--run {folder} does not exist; give a run folder of `nmjax train-skel` or "
            "`nmjax train-dyn`, an output folder of `nmjax retarget`, or a .glb / .gltf file "
            "of `nmjax export`"
        )
    found = tasks.folder_kind(folder)
    if found in ("skel", "dyn", "retarget"):
        return found
    if found is not None:  # a generate or interpolate output
        raise FileNotFoundError(
            f"--run {folder} is an `nmjax {found}` output, which `nmjax view` does not show; "
            "view the phase-2 run it came from (it generates and interpolates live), or turn "
            "it into a file with `nmjax export`"
        )
    raise FileNotFoundError(
        f"--run {folder} holds neither {run_folder.CONFIG_FILE} (a run folder) nor "
        f"{tasks.RETARGET_FILE} (an `nmjax retarget` output); is it an unfinished run?"
    )


def pick_sequence(names: Iterable[str], seq: str | None, where: str) -> str:
    """`seq`, or the first name in sorted order when it is None.

    Raises:
      ValueError: `seq` is not among `names` (the message lists some that are).
    """
    names = sorted(names)
    if seq is None:
        return names[0]
    if seq not in names:
        shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
        raise ValueError(f"--seq {seq!r} is not a sequence of {where}; available: {shown}")
    return seq


def check_port(host: str, port: int) -> None:
    """Refuses a `host`:`port` that cannot be listened on (taken, or not this machine's).

    viser itself would move on to the next free port; a view must be where the user (and an
    SSH port forward) expects it.

    Raises:
      OSError: one line naming the port or host and the fix.
    """
    import errno

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            # As the server binds: a port left in TIME_WAIT is free, one with a listener is not.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
    except OSError as err:
        if err.errno == errno.EADDRINUSE:
            raise OSError(
                f"--port {port} is in use on {host}; pick another with --port N"
            ) from None
        raise OSError(
            f"cannot listen on --host {host} --port {port} ({err.strerror or err}); give an "
            "address of this machine (127.0.0.1, or 0.0.0.0 for every interface)"
        ) from None


def start_server(host: str, port: int) -> Any:
    """A viser server on exactly `host`:`port` (0: any free port)."""
    viser = import_viser()
    check_port(host, port)
    server = viser.ViserServer(host=host, port=port, label="nmjax", verbose=False)
    if port and server.get_port() != port:  # taken between the check and the bind
        server.stop()
        raise OSError(f"--port {port} is in use on {host}; pick another with --port N")
    return server


def open_view(
    folder: str | Path,
    *,
    split: str = "test",
    seq: str | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    up: str | None = None,
    cond: int = 5,
    gen: int = 25,
    samples: int = 3,
    gap: int = 10,
    trajectories: int = 16,
    seed: int = 0,
) -> Viewer:
    """Reads `folder` and starts a viewer of it on `host`:`port`; `stop()` ends it.

    Everything is read and checked before the port is taken. `up` ("x", "y" or "z") overrides
    the up axis of the run's data (z for a retarget output, y for a glTF file); the phase-2
    options are those of
    `nmjax generate` and `nmjax interpolate`.

    Raises:
      ImportError: viser is not installed (the message names the extra).
      FileNotFoundError, ValueError, OSError: a missing or unfinished folder, an unknown
        sequence, a port in use; one line each.
    """
    from nmjax import run_folder, tasks

    import_viser()
    folder = Path(folder)
    kind = folder_kind(folder)
    up_axis = None if up is None else UP_AXES.index(up)
    if kind == "gltf":
        from nmjax.export import gltf

        if seq is not None:
            raise ValueError(f"--seq does not apply to {folder}: a glTF file is one motion")
        data = gltf.read(folder)
        server = start_server(host, port)
        try:  # glTF is +Y up
            return GltfViewer(server, folder, data, 1 if up_axis is None else up_axis)
        except BaseException:
            server.stop()
            raise
    if kind == "retarget":
        if seq is not None:
            raise ValueError(f"--seq does not apply to {folder}: a retarget output is one motion")
        data = tasks.read_retarget(folder)
    else:
        data = read_phase1(folder, split) if kind == "skel" else read_phase2(folder, split)
        if up_axis is not None:
            data = dataclasses.replace(data, up_axis=up_axis)
        source = data.run if kind == "skel" else data.skel_run
        seq = pick_sequence(data.keypoints, seq, str(run_folder.keypoints_file(source, split)))
    server = start_server(host, port)
    try:
        if kind == "skel":
            return Phase1Viewer(server, data, seq)
        if kind == "dyn":
            return Phase2Viewer(
                server,
                data,
                seq,
                cond=cond,
                gen=gen,
                samples=samples,
                gap=gap,
                trajectories=trajectories,
                seed=seed,
            )
        return RetargetViewer(server, folder, data, 2 if up_axis is None else up_axis)
    except BaseException:
        server.stop()
        raise
