"""The rule for tests that need an outside program (tests/programs.py): skip with the install
command on a user's machine, fail under CI=true, with the lookup and the environment patched."""

from __future__ import annotations

import shutil

import browser
import programs
import pytest


def test_a_missing_program_skips_outside_ci_naming_the_install_command(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    for value in (None, "false", ""):
        if value is None:
            monkeypatch.delenv("CI", raising=False)
        else:
            monkeypatch.setenv("CI", value)
        with pytest.raises(pytest.skip.Exception) as skipped:
            browser.require_browser()
        reason = str(skipped.value)
        assert "chromium" in reason and "apt-get install chromium" in reason, reason


def test_a_missing_program_fails_under_ci(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    for value in ("true", "TRUE"):
        monkeypatch.setenv("CI", value)
        with pytest.raises(pytest.fail.Exception) as failed:
            browser.require_browser()
        assert "CI=true" in str(failed.value) and "apt-get install chromium" in str(failed.value)


def test_the_first_program_found_is_returned(monkeypatch):
    found = {"google-chrome": "/opt/chrome/google-chrome"}
    monkeypatch.setattr(shutil, "which", found.get)
    monkeypatch.setenv("CI", "true")
    assert browser.require_browser() == "/opt/chrome/google-chrome"
    path = programs.require_program(("nope", "google-chrome"), "a test", "install it")
    assert path == "/opt/chrome/google-chrome"
