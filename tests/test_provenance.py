"""nmjax.provenance: the commit and dirtiness of a git checkout made here, the answer outside one,
and the stamp in JSON, markdown and PNG files."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from nmjax import provenance

METRICS = {"sc": "Eq. 21 as published", "cd": "tracking Chamfer x1e4"}


def git(folder, *args: str) -> str:
    done = subprocess.run(
        ["git", "-C", str(folder), "-c", "user.name=t", "-c", "user.email=t@example.org", *args],
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.strip()


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """tmp_path with git's search for a checkout stopping at it, and no $NMJAX_COMMIT."""
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    monkeypatch.delenv(provenance.COMMIT_ENV, raising=False)
    return tmp_path


@pytest.fixture
def repo(isolated):
    """A git checkout with one commit of code/model.py and an ignored venv/."""
    root = isolated / "repo"
    (root / "code").mkdir(parents=True)
    (root / "code" / "model.py").write_text("x = 1\n")
    (root / ".gitignore").write_text("venv/\n")
    git(root, "init", "-q")
    git(root, "add", ".")
    git(root, "commit", "-q", "-m", "first")
    return root


def test_clean_checkout_names_its_commit(repo):
    stamp = provenance.stamp(METRICS, source=repo / "code" / "model.py")
    assert stamp["commit"] == git(repo, "rev-parse", "HEAD")
    assert (stamp["dirty"], stamp["changed"], stamp["changed_paths"]) == (False, 0, [])
    assert "commit_note" not in stamp and stamp["metrics"] == METRICS
    assert provenance.describe_commit(stamp) == f"{stamp['commit'][:10]} (clean)"


def test_changed_and_untracked_files_make_it_dirty(repo):
    (repo / "code" / "model.py").write_text("x = 2\n")
    stamp = provenance.stamp(source=repo / "code")
    assert stamp["dirty"] is True and stamp["changed_paths"] == ["code/model.py"]
    (repo / "code" / "new.py").write_text("")
    stamp = provenance.stamp(source=repo / "code")
    assert stamp["changed"] == 2 and "code/new.py" in stamp["changed_paths"]
    assert provenance.describe_commit(stamp).endswith("+ 2 changed paths")
    git(repo, "add", ".")
    git(repo, "commit", "-q", "-m", "second")
    again = provenance.stamp(source=repo / "code")
    assert again["dirty"] is False and again["commit"] != stamp["commit"]


def test_outside_a_checkout_it_says_so(isolated, monkeypatch):
    stamp = provenance.stamp(METRICS, source=isolated)
    assert stamp["commit"] is None and stamp["dirty"] is None and stamp["changed"] is None
    assert "not in a git checkout" in stamp["commit_note"]
    assert provenance.describe_commit(stamp).startswith("unknown (")
    monkeypatch.setenv(provenance.COMMIT_ENV, "abc123")
    stamp = provenance.stamp(source=isolated)
    assert stamp["commit"] == "abc123" and stamp["dirty"] is None
    assert provenance.COMMIT_ENV in stamp["commit_note"]
    assert provenance.describe_commit(stamp) == "abc123 (working tree unknown)"


def test_code_the_checkout_ignores_is_not_its_code(repo):
    """An installed copy inside a project's ignored virtual environment is not that project's
    commit."""
    (repo / "venv" / "nmjax").mkdir(parents=True)
    stamp = provenance.stamp(source=repo / "venv" / "nmjax")
    assert stamp["commit"] is None and "ignored" in stamp["commit_note"]


def test_without_git_installed(repo, monkeypatch):
    monkeypatch.setenv("PATH", "")
    stamp = provenance.stamp(source=repo)
    assert stamp["commit"] is None and stamp["commit_note"] == "git is not installed"
    assert stamp["gpu"] is None  # no nvidia-smi either


def test_machine_and_versions_are_recorded(repo):
    stamp = provenance.stamp(source=repo)
    assert stamp["cpu"] and stamp["cpu_count"] >= 1
    assert stamp["versions"]["jax"] and stamp["date"].endswith("Z")
    assert json.loads(json.dumps(stamp)) == stamp  # plain JSON


def test_json_and_markdown_carry_the_stamp(repo, tmp_path):
    (repo / "code" / "model.py").write_text("x = 3\n")
    stamp = provenance.stamp(METRICS, source=repo)
    provenance.write_json(tmp_path / "r.json", {"rows": [1, 2]}, stamp)
    written = json.loads((tmp_path / "r.json").read_text())
    assert list(written) == ["provenance", "rows"] and written["provenance"] == stamp
    provenance.write_markdown(tmp_path / "r.md", "# Table\n\n| a |\n", stamp)
    text = (tmp_path / "r.md").read_text()
    assert text.startswith("# Table\n\n| a |\n\n## Provenance\n")
    assert f"- commit: {stamp['commit'][:10]} + 1 changed path\n" in text
    assert "- changed: `code/model.py`" in text
    assert "  - `sc`: Eq. 21 as published" in text and stamp["cpu"] in text


def test_png_carries_the_stamp_and_keeps_its_pixels(repo, tmp_path):
    from PIL import Image

    path = tmp_path / "figure.png"
    pixels = np.random.default_rng(0).integers(0, 255, (6, 5, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)
    assert provenance.read_png(path) is None
    stamp = provenance.stamp(METRICS, source=repo)
    provenance.stamp_png(path, stamp)
    provenance.stamp_png(path, {**stamp, "date": "later"})  # replaces, never adds a second
    assert provenance.read_png(path) == {**stamp, "date": "later"}
    with Image.open(path) as image:
        assert np.array_equal(np.asarray(image), pixels)
        assert list(image.text) == [provenance.PNG_KEYWORD]
    (tmp_path / "not.png").write_bytes(b"GIF89a")
    with pytest.raises(ValueError, match="not a PNG"):
        provenance.stamp_png(tmp_path / "not.png", stamp)
