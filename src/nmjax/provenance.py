"""What made a results file: the commit and whether the working tree differed from it, the date,
the command, the machine (CPU model, GPU when present), the versions, and the definitions of the
metrics the file reports.

Every writer of results (`nmjax bench`, `nmjax evaluate`, the scripts of experiments/) takes one
`stamp` when it starts and puts it into each file it writes: JSON under the key "provenance"
(`write_json`), markdown as a closing "Provenance" section (`write_markdown`), PNG as a text chunk
(`stamp_png`, read back by `read_png`). A stamp never fails: outside a git checkout (an installed
wheel, a copy without .git) it says so in `commit_note` and leaves `commit` and `dirty` None.

The stamp is taken when the work starts, so the files the work itself writes into a checkout do
not count as changes to it.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import shlex
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from nmjax import atomic

# A copy of the repository without .git (the GPU machines' working trees) names its commit here.
COMMIT_ENV = "NMJAX_COMMIT"
# The changed paths listed in a stamp; the count is always complete.
MAX_LISTED_CHANGES = 20
VERSIONED = ("jax", "jaxlib", "flax", "numpy")
PNG_KEYWORD = "nmjax provenance"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_GIT_TIMEOUT_S = 20


def stamp(metrics: Mapping[str, str] | None = None, *, source: str | os.PathLike | None = None):
    """The provenance of results made now by the code at `source`.

    Args:
      metrics: {name: one-line definition} of every metric the results report, as the caller
        computes it (recorded verbatim, so a reader of the file knows what the numbers mean even
        after a definition changes).
      source: a file or folder of the code that runs; default this package's own folder, so the
        commit is the one of the checkout nmjax was imported from.

    Returns:
      {"commit": full hash or None, "dirty": bool or None (the working tree, untracked files
       included, differs from the commit), "changed": number of changed paths, "changed_paths":
       the first `MAX_LISTED_CHANGES` of them, "commit_note" (only when commit or dirty is
       unknown: why), "date": UTC ISO 8601, "command", "cpu", "cpu_count", "gpu": [names] or
       None, "python", "platform", "versions": {package: version or None}, "metrics"}.
    """
    source = Path(__file__).resolve().parent if source is None else Path(source).resolve()
    return {
        **git_state(source),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": shlex.join([Path(sys.executable).name, *sys.argv]),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "gpu": gpu_names(),
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
        "versions": {name: _version(name) for name in VERSIONED},
        "metrics": dict(metrics or {}),
    }


def _git(folder: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=_GIT_TIMEOUT_S
    )


def git_state(source: Path) -> dict[str, Any]:
    """{"commit", "dirty", "changed", "changed_paths"} of the git checkout holding `source`, and
    "commit_note" where they cannot be known (no git, no checkout, or `source` ignored by the
    checkout around it, as a virtual environment inside a project is: its files are not that
    project's code). `$NMJAX_COMMIT` then supplies the commit, its dirtiness unknown."""
    folder = source if source.is_dir() else source.parent
    try:
        top = _git(folder, "rev-parse", "--show-toplevel")
        if top.returncode != 0:
            said = top.stderr.strip().splitlines()
            return _without_git(
                f"{source} is not in a git checkout" + (f" (git: {said[0]})" if said else "")
            )
        if _git(folder, "check-ignore", "-q", str(source)).returncode == 0:
            return _without_git(f"{source} is ignored by the git checkout {top.stdout.strip()}")
        commit = _git(folder, "rev-parse", "HEAD")
        status = _git(folder, "status", "--porcelain=v1", "--untracked-files=all")
    except FileNotFoundError:
        return _without_git("git is not installed")
    except subprocess.TimeoutExpired:
        return _without_git(f"git did not answer within {_GIT_TIMEOUT_S} s")
    if commit.returncode != 0:
        return _without_git(f"the checkout {top.stdout.strip()} has no commit yet")
    changed = [line[3:] for line in status.stdout.splitlines() if line.strip()]
    return {
        "commit": commit.stdout.strip(),
        "dirty": bool(changed),
        "changed": len(changed),
        "changed_paths": changed[:MAX_LISTED_CHANGES],
    }


def _without_git(why: str) -> dict[str, Any]:
    commit = os.environ.get(COMMIT_ENV) or None
    if commit:
        why += f"; commit from ${COMMIT_ENV}, working tree unknown"
    return {
        "commit": commit,
        "dirty": None,
        "changed": None,
        "changed_paths": [],
        "commit_note": why,
    }


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, sysctl on macOS), else the architecture."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model", "cpu model") and value.strip():
                    return value.strip()
    except OSError:
        pass
    if sys.platform == "darwin":
        try:
            out = subprocess.run(
                ["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True
            )
            if out.returncode == 0 and out.stdout.strip():
                return out.stdout.strip()
        except OSError:
            pass
    return platform.processor() or platform.machine() or "unknown"


def gpu_names() -> list[str] | None:
    """The names of the NVIDIA GPUs `nvidia-smi` lists, or None without one. Asked of the
    driver, not of JAX: creating JAX's GPU client here would take device memory in a process
    that may not mean to use the device (`nmjax bench` measures each row in a child)."""
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=_GIT_TIMEOUT_S,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    names = [line.strip() for line in out.stdout.splitlines() if line.strip()]
    return names if out.returncode == 0 and names else None


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def describe_commit(stamp: Mapping[str, Any]) -> str:
    """The commit in one phrase: '1a2b3c4d5e (clean)', '1a2b3c4d5e + 3 changed paths',
    'unknown (why)'."""
    commit = stamp.get("commit")
    if not commit:
        return f"unknown ({stamp.get('commit_note', 'not recorded')})"
    short = commit[:10]
    if stamp.get("dirty") is None:
        return f"{short} (working tree unknown)"
    if not stamp["dirty"]:
        return f"{short} (clean)"
    return f"{short} + {stamp['changed']} changed path" + ("s" if stamp["changed"] > 1 else "")


def markdown(stamp: Mapping[str, Any]) -> str:
    """The stamp as a markdown section (heading "## Provenance")."""
    versions = ", ".join(f"{k} {v}" for k, v in stamp["versions"].items() if v is not None)
    gpu = ", ".join(stamp["gpu"]) if stamp.get("gpu") else "none"
    lines = [
        "## Provenance",
        "",
        f"- commit: {describe_commit(stamp)}",
        f"- date: {stamp['date']}",
        f"- command: `{stamp['command']}`",
        f"- CPU: {stamp['cpu']} ({stamp['cpu_count']} cores); GPU: {gpu}",
        f"- Python {stamp['python']}, {versions}; {stamp['platform']}",
    ]
    if stamp.get("dirty") and stamp.get("changed_paths"):
        more = stamp["changed"] - len(stamp["changed_paths"])
        listed = ", ".join(f"`{p}`" for p in stamp["changed_paths"])
        lines.append(f"- changed: {listed}" + (f" and {more} more" if more > 0 else ""))
    if stamp.get("metrics"):
        lines.append("- metrics:")
        lines += [f"  - `{name}`: {text}" for name, text in stamp["metrics"].items()]
    return "\n".join(lines) + "\n"


def write_json(path: str | os.PathLike, obj: Mapping[str, Any], stamp: Mapping[str, Any]) -> None:
    """`obj` as JSON at `path` (atomically), the stamp first under "provenance"."""
    atomic.write_json(path, {"provenance": dict(stamp), **obj})


def write_markdown(path: str | os.PathLike, text: str, stamp: Mapping[str, Any]) -> None:
    """`text` at `path` (atomically) with the stamp's section after it."""
    atomic.write_text(path, text.rstrip("\n") + "\n\n" + markdown(stamp))


def _png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """[(type, payload)] of a PNG file's chunks (ValueError if it is not one)."""
    if not data.startswith(_PNG_SIGNATURE):
        raise ValueError("not a PNG file (bad signature)")
    chunks, pos = [], len(_PNG_SIGNATURE)
    while pos < len(data):
        if pos + 8 > len(data):
            raise ValueError("truncated PNG chunk header")
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise ValueError(f"truncated PNG chunk {kind!r}")
        chunks.append((kind, data[pos + 8 : pos + 8 + length]))
        pos = end
    return chunks


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def stamp_png(path: str | os.PathLike, stamp: Mapping[str, Any]) -> None:
    """Adds the stamp to the PNG at `path` as a tEXt chunk (keyword `PNG_KEYWORD`, the stamp as
    ASCII JSON) after its header, replacing an earlier stamp; the image data is untouched.
    Image viewers show it among the file's properties; `read_png` returns it."""
    path = Path(path)
    chunks = _png_chunks(path.read_bytes())
    key = PNG_KEYWORD.encode("latin-1") + b"\0"
    kept = [(k, p) for k, p in chunks if not (k == b"tEXt" and p.startswith(key))]
    text = (b"tEXt", key + json.dumps(dict(stamp), ensure_ascii=True).encode("ascii"))
    with atomic.writer(path, "wb") as f:
        f.write(_PNG_SIGNATURE)
        for i, (kind, payload) in enumerate(kept):
            f.write(_png_chunk(kind, payload))
            if i == 0:  # IHDR must come first
                f.write(_png_chunk(*text))


def read_png(path: str | os.PathLike) -> dict[str, Any] | None:
    """The stamp `stamp_png` put into the PNG at `path`, or None when it has none."""
    key = PNG_KEYWORD.encode("latin-1") + b"\0"
    for kind, payload in _png_chunks(Path(path).read_bytes()):
        if kind == b"tEXt" and payload.startswith(key):
            return json.loads(payload[len(key) :].decode("ascii"))
    return None
