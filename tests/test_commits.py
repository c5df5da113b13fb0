"""git_commit: only the given paths are committed, new files and removals alike."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from emlpack.commits import git_commit


def _committed(repo: Path) -> list[str]:
    return _git(repo, "ls-tree", "-r", "--name-only", "HEAD").split()


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True,
                          text=True).stdout


@pytest.fixture
def repo(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "config", "user.email", "t@example.org")
    _git(tmp_path, "config", "user.name", "t")
    (tmp_path / "other.txt").write_text("staged elsewhere\n")
    _git(tmp_path, "add", "other.txt")
    return tmp_path


def test_new_files_and_removals_are_committed_and_nothing_else(repo):
    snaps = repo / "snaps"
    (snaps / "step-1").mkdir(parents=True)
    (snaps / "step-1" / "a.pt").write_text("1")
    assert git_commit([snaps], "first")
    assert _committed(repo) == ["snaps/step-1/a.pt"]  # not other.txt
    assert "other.txt" in _git(repo, "diff", "--cached", "--name-only")
    shutil.rmtree(snaps / "step-1")
    (snaps / "step-2").mkdir()
    (snaps / "step-2" / "a.pt").write_text("2")
    assert git_commit([snaps], "second")
    assert _committed(repo) == ["snaps/step-2/a.pt"]
    assert _git(repo, "log", "--format=%s").split() == ["second", "first"]
    # a removed path that git tracks is committed too; an unknown one is no error
    shutil.rmtree(snaps)
    assert git_commit([snaps, repo / "never"], "third")
    assert _committed(repo) == []


def test_outside_a_repository_it_warns_and_returns_false(tmp_path, caplog):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    (tmp_path / "x").write_text("x")
    assert not git_commit([tmp_path / "x"], "m", tries=1)
    assert "not in a git repository" in caplog.text


def test_paths_another_job_committed_already_are_no_failure(repo, caplog):
    """Two jobs list the same finished files; the second finds them committed: success at
    once, no retries, no warning (it used to retry and warn "could not commit")."""
    (repo / "a.npz").write_text("a")
    assert git_commit([repo / "a.npz", repo / "other.txt"], "first")
    (repo / "other.txt").write_text("edited, not staged\n")  # a session's work in progress
    assert git_commit([repo / "a.npz"], "again", tries=1)
    assert _git(repo, "log", "--format=%s").split() == ["first"]
    assert "could not commit" not in caplog.text
