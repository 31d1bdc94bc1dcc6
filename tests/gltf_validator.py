"""The Khronos glTF Validator (npm package `gltf-validator`) run under Node, for the export tests.

`.ci/run` installs it globally (`INSTALL` below); the package is looked up in Node's global
modules folder (`npm root -g`) and in NODE_PATH. Outside CI a missing Node or package skips
the tests that need it, naming the install command; in CI (CI=true) it fails them.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

VERSION = "2.0.0-dev.3.10"
INSTALL = f"npm install -g gltf-validator@{VERSION}"

# Reads the file named by argv[1], validates it and prints the report as JSON.
_SCRIPT = """
const fs = require('fs');
const validator = require('gltf-validator');
const bytes = new Uint8Array(fs.readFileSync(process.argv[1]));
validator.validateBytes(bytes, {maxIssues: 100})
  .then((report) => { console.log(JSON.stringify(report)); })
  .catch((error) => { console.error(String(error)); process.exit(3); });
"""


@functools.cache
def _node_path() -> str | None:
    """NODE_PATH under which `require('gltf-validator')` resolves, or None when it does not."""
    node = shutil.which("node")
    if node is None:
        return None
    folders = [p for p in os.environ.get("NODE_PATH", "").split(os.pathsep) if p]
    npm = shutil.which("npm")
    if npm is not None:
        root = subprocess.run([npm, "root", "-g"], capture_output=True, text=True, timeout=60)
        if root.returncode == 0 and root.stdout.strip():
            folders.append(root.stdout.strip())
    path = os.pathsep.join(folders)
    found = subprocess.run(
        [node, "-e", "require.resolve('gltf-validator')"],
        env={**os.environ, "NODE_PATH": path},
        capture_output=True,
        timeout=60,
    )
    return path if found.returncode == 0 else None


def require_validator() -> None:
    """Skips the calling test (fails it in CI) when Node or the validator is missing."""
    if _node_path() is not None:
        return
    missing = "Node.js" if shutil.which("node") is None else "the npm package gltf-validator"
    message = f"needs {missing}: install with `{INSTALL}` (and Node.js from your system's packages)"
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must have the glTF validator; {message}")
    pytest.skip(message)


def validate(path: str | Path) -> dict[str, Any]:
    """The validator's report on `path` (`issues.numErrors`, `issues.messages`, ...)."""
    require_validator()
    done = subprocess.run(
        [shutil.which("node"), "-e", _SCRIPT, str(path)],
        env={**os.environ, "NODE_PATH": _node_path()},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, f"the validator failed on {path}: {done.stderr.strip()}"
    return json.loads(done.stdout)
