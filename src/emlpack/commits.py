"""Committing the finished outputs of long jobs to git (campaign shards, training snapshots).

A long job on a machine that may vanish (a session that ends without warning) keeps its
finished work by committing it as it goes: :func:`git_commit` stages the given paths (new,
changed and removed files under them) and commits only those, whatever else the index holds.
"""

from __future__ import annotations

import logging
import subprocess
import time
from pathlib import Path

log = logging.getLogger(__name__)


def git_commit(paths: list[Path], message: str, tries: int = 5) -> bool:
    """Commit ``paths`` (files or folders; removals under a folder included) and nothing else
    to the git repository that holds them. Retries while another git command holds the index
    lock; returns False (with a warning) when the commit could not be made."""
    paths = [Path(p).resolve() for p in paths]
    cwd = _existing_parent(paths[0])
    top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=cwd, capture_output=True,
                         text=True)
    if top.returncode != 0:
        log.warning("could not commit %s: not in a git repository", [str(p) for p in paths])
        return False
    root = Path(top.stdout.strip()).resolve()
    rel = [str(p.relative_to(root)) for p in paths if p.exists() or _tracked(root, p)]
    if not rel:
        return True
    error = ""
    for attempt in range(tries):
        add = subprocess.run(["git", "add", "-A", "--", *rel], cwd=root, capture_output=True,
                             text=True)
        if add.returncode == 0:
            same = subprocess.run(["git", "diff", "--cached", "--quiet", "--", *rel], cwd=root,
                                  capture_output=True)
            if same.returncode == 0:  # nothing to commit (e.g. another job committed them)
                return True
            com = subprocess.run(["git", "commit", "-q", "-m", message, "--", *rel], cwd=root,
                                 capture_output=True, text=True)
            if com.returncode == 0 or "nothing" in com.stdout + com.stderr:
                return True
            error = (com.stderr or com.stdout).strip()
        else:
            error = add.stderr.strip()
        time.sleep(2.0 * (attempt + 1))  # e.g. another git command holds index.lock
    log.warning("could not commit %s: %s", rel, error)
    return False


def _existing_parent(path: Path) -> Path:
    while not path.is_dir():
        path = path.parent
    return path


def _tracked(root: Path, path: Path) -> bool:
    """Whether git tracks ``path`` (or files under it): a removed folder still to commit."""
    out = subprocess.run(["git", "ls-files", "--", str(path.relative_to(root))], cwd=root,
                         capture_output=True, text=True)
    return bool(out.stdout.strip())
