"""The model stages' small outputs of a study work directory, kept in the repository so that a
long evaluation (long_jobs.sh phases 2b and 4: hours of MD, the IR stage) goes on from them on a
fresh machine instead of starting again.

    python examples/eqm7/study_outputs.py save WORKDIR ARCHIVE [--commit]
    python examples/eqm7/study_outputs.py restore ARCHIVE WORKDIR

``save`` copies every finished output of the evaluate, polarizability, ir and md stages
(``OUTPUTS``: per-model JSON files and each MD run's ``analysis.json``, a few kB each) that the
archive lacks or holds in another version, each through a temporary file and a rename; with
``--commit`` it commits them. A file being written (not complete JSON) is left for the next
call. ``restore`` copies the archive's files into WORKDIR where they are missing, so the stages
skip that work. MD trajectories and checkpoints stay in WORKDIR (hundreds of MB): a run cut off
on another machine starts again, and Figure 3's panels b and c show runs whose trajectory is
on this machine.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

#: the outputs kept, as globs under the work directory
OUTPUTS = ("eval/*/*.json", "polarizability/*.json", "polarizability/*/*.json", "ir/*.json",
           "md/*/*/analysis.json")


def finished_outputs(workdir: Path) -> list[Path]:
    """The outputs under ``workdir`` (relative paths) that are complete JSON."""
    out = []
    for pattern in OUTPUTS:
        for path in sorted(workdir.glob(pattern)):
            try:
                json.loads(path.read_text())
            except (ValueError, OSError):
                continue  # being written, or gone
            out.append(path.relative_to(workdir))
    return out


def copy_outputs(source: Path, target: Path, replace: bool) -> list[Path]:
    """Copy the finished outputs of ``source`` into ``target`` where they are missing, and with
    ``replace`` also where they differ; returns the paths written under ``target``."""
    from emlpack._files import write_bytes_atomic

    written = []
    for rel in finished_outputs(source):
        data, dest = (source / rel).read_bytes(), target / rel
        if dest.exists() and (not replace or dest.read_bytes() == data):
            continue
        dest.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(dest, data)
        written.append(dest)
    return written


def save(workdir: Path, archive: Path) -> list[Path]:
    """Copy the new or changed finished outputs into ``archive``; returns their archive paths."""
    return copy_outputs(workdir, archive, replace=True)


def restore(archive: Path, workdir: Path) -> list[Path]:
    """Copy the archive's outputs into ``workdir`` where they are missing; returns them."""
    return copy_outputs(archive, workdir, replace=False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("save", help="work directory -> archive")
    s.add_argument("workdir", type=Path)
    s.add_argument("archive", type=Path)
    s.add_argument("--commit", action="store_true", help="commit what was saved")
    r = sub.add_parser("restore", help="archive -> work directory (missing files only)")
    r.add_argument("archive", type=Path)
    r.add_argument("workdir", type=Path)
    args = ap.parse_args(argv)
    if args.command == "restore":
        done = restore(args.archive, args.workdir)
        print(f"restored {len(done)} outputs from {args.archive} into {args.workdir}")
        return 0
    done = save(args.workdir, args.archive)
    if done and args.commit:
        from emlpack.commits import git_commit

        if git_commit(done, f"eqm7 study outputs: {len(done)} files ({args.archive})"):
            print(f"committed {len(done)} outputs to {args.archive}", flush=True)
    elif done:
        print(f"saved {len(done)} outputs to {args.archive}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
