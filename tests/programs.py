"""Tests that need a program `make install` does not install (a browser, for one).

`make install && make test` must pass on a fresh machine, so such a test skips there, saying what
it needs and how to install it. CI installs every such program (`.ci/run`), and a test that
skipped there would hide a broken install, so with CI=true (what CI services set) a missing
program fails the test instead.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence

import pytest


def in_ci() -> bool:
    """Whether the suite runs in CI: the environment variable CI is "true" (any case)."""
    return os.environ.get("CI", "").strip().lower() == "true"


def require_program(names: Sequence[str], needed_for: str, install: str) -> str:
    """The path of the first of `names` found on PATH, for a test that needs that program.

    Args:
      names: executables that serve equally (e.g. "chromium", "google-chrome").
      needed_for: what the program is for, e.g. "the viewer's browser test drives Chromium".
      install: the command that installs it, e.g. "apt-get install chromium".

    Outside CI a missing program skips the calling test with `needed_for` and `install`; in CI
    (`in_ci`) it fails it with the same words.
    """
    found = next((path for name in names if (path := shutil.which(name))), None)
    if found is not None:
        return found
    reason = f"{needed_for}, and none of {', '.join(names)} is on PATH; install it: {install}"
    if in_ci():
        pytest.fail(f"CI=true requires it: {reason}", pytrace=False)
    pytest.skip(reason)
