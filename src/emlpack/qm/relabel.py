"""Recompute energy, forces and Foster-Boys centres for every frame of an extxyz file.

Each frame is labeled under its own field (``efield``). The output keeps the input's
convention: core centres are written when the input had them (or had no centres at all), and
when the input's centres can be matched one-to-one they keep the input's order.
Failed frames are left out of the output and listed in ``OUT.failed.yaml``; the run goes on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from emlpack._files import write_text_atomic
from emlpack.io.extxyz import (
    CORE_CENTRE_ROWS_KEY,
    CORE_CENTRES_KEY,
    ReferenceFrame,
    read_reference_frames,
    write_structures,
)
from emlpack.qm.levels import parse_level
from emlpack.qm.pyscf_labeler import LabelResult, PySCFLabeler
from emlpack.structure import Structure, n_core_pairs

if TYPE_CHECKING:
    from collections.abc import Iterable


@dataclass
class FrameComparison:
    """Differences between a relabeled frame and the input's labels (when it had them)."""

    source: str
    d_energy: float  # eV
    d_forces: float  # max |ΔF| (eV/Å)
    d_centres: float  # max distance (Å) after one-to-one matching
    wall_time: float  # s


@dataclass
class RelabelReport:
    """Outcome of :func:`relabel`: frames relabeled and failed, the failures (source, reason),
    the comparisons with the input's labels and notes (Foster-Boys starts that disagreed)."""

    n_frames: int = 0
    n_failed: int = 0
    failures: list[dict] = field(default_factory=list)
    comparisons: list[FrameComparison] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """The report ``emlp relabel`` prints: frames relabeled, largest differences from the
        input's labels, mean time per frame, failures and notes."""
        lines = [f"{self.n_frames - self.n_failed}/{self.n_frames} frames relabeled"]
        cmp_ = [c for c in self.comparisons if np.isfinite(c.d_energy)]
        if cmp_:
            d_e = max(abs(c.d_energy) for c in cmp_)
            d_f = max(c.d_forces for c in cmp_)
            d_c = max(c.d_centres for c in cmp_)
            t = float(np.mean([c.wall_time for c in cmp_]))
            lines.append(
                f"max |dE| = {d_e:.2e} eV, max |dF| = {d_f:.2e} eV/Å, max centre shift ="
                f" {d_c:.2e} Å vs the input; {t:.1f} s per frame"
            )
        for f in self.failures:
            lines.append(f"FAILED {f['source']}: {f['reason']}")
        lines.extend(self.notes)
        return "\n".join(lines)


def match_centres(reference: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, float]:
    """One-to-one matching of ``centres`` to ``reference`` (Å): (order, max distance)."""
    from scipy.optimize import linear_sum_assignment

    d = np.linalg.norm(reference[:, None, :] - centres[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(d)
    order = np.empty(len(reference), dtype=np.int64)
    order[rows] = cols
    return order, float(d[rows, cols].max()) if len(rows) else 0.0


def relabeled_frame(frame: ReferenceFrame, res: LabelResult, level_name: str) -> Structure:
    """The output frame of ``res`` in the convention of the input ``frame``: a
    :class:`Structure` whose recorded core centres (``info``) put the centres in their output
    order when written with ``core_centres="recorded"``."""
    n_core = int(n_core_pairs(frame.numbers).sum())
    n_all = len(res.centres)
    is_core = np.asarray(res.core_mask, dtype=bool)
    with_cores = len(frame.centres) != n_all - n_core or n_core == 0
    centres, is_core = (res.centres, is_core) if with_cores else (res.pairs, is_core[~is_core])
    if len(frame.centres) == len(centres) and len(centres):
        order, _ = match_centres(frame.centres, centres)
        centres, is_core = centres[order], is_core[order]
    info = {k: v for k, v in frame.info.items() if k not in (CORE_CENTRES_KEY,
                                                              CORE_CENTRE_ROWS_KEY)}
    info["level"] = level_name
    if is_core.any():
        info[CORE_CENTRES_KEY] = centres[is_core]
        info[CORE_CENTRE_ROWS_KEY] = np.flatnonzero(is_core)
    return Structure(
        numbers=frame.numbers, positions=frame.positions, pairs=centres[~is_core],
        field=frame.field, energy=res.energy, forces=res.forces, info=info, source=frame.source,
    )


def compare(frame: ReferenceFrame, res: LabelResult) -> FrameComparison:
    """Differences of ``res`` to the labels stored in ``frame`` (NaN where absent)."""
    d_e = res.energy - frame.energy if frame.energy is not None else float("nan")
    d_f = (
        float(np.abs(res.forces - frame.forces).max())
        if frame.forces is not None and res.forces is not None
        else float("nan")
    )
    d_c = float("nan")
    if len(frame.centres):
        mine = res.centres if len(frame.centres) == len(res.centres) else res.pairs
        if len(mine) == len(frame.centres):
            d_c = match_centres(frame.centres, mine)[1]
    return FrameComparison(frame.source, d_e, d_f, d_c, res.wall_time)


def relabel(
    in_path: str | Path,
    out_path: str | Path,
    level: str | None = None,
    index: str = ":",
    boys_starts: int = 3,
    progress: bool = True,
    labeler: PySCFLabeler | None = None,
    workers: int = 0,
    scheduler: str | None = None,
) -> RelabelReport:
    """Relabel ``in_path`` frame by frame and write ``out_path`` (temp file + rename).

    ``workers > 0`` runs the frames on a Dask ``LocalCluster``; ``scheduler`` on an existing
    Dask cluster; otherwise in this process.
    """
    from emlpack.progress import progress as progress_bar

    frames = read_reference_frames(in_path, index=index)
    lab = labeler or PySCFLabeler(parse_level(level), boys_starts=boys_starts)
    report = RelabelReport(n_frames=len(frames))
    out_frames: list[Structure] = []
    results = _results_in_order(frames, lab, workers, scheduler)
    for frame, res in progress_bar(zip(frames, results, strict=False), total=len(frames),
                                   desc="relabel", unit="frame", enabled=progress):
        if not res.ok:
            report.n_failed += 1
            report.failures.append({"source": frame.source, "reason": res.error})
            continue
        if res.boys_note:
            report.notes.append(f"{frame.source}: {res.boys_note}")
        report.comparisons.append(compare(frame, res))
        out_frames.append(relabeled_frame(frame, res, lab.level.name))
    write_structures(out_path, out_frames, convention="reference", core_centres="recorded")
    failed_path = Path(str(out_path) + ".failed.yaml")
    if report.failures:
        write_text_atomic(failed_path,
                          yaml.safe_dump(report.failures, sort_keys=False, width=1000))
    elif failed_path.exists():
        failed_path.unlink()
    return report


def _label_frame(lab: PySCFLabeler, frame: ReferenceFrame) -> LabelResult:
    return lab(frame.numbers, frame.positions, frame.field)


def _results_in_order(frames: Iterable[ReferenceFrame], lab: PySCFLabeler, workers: int,
                      scheduler: str | None):
    """Label results in frame order, computed here or on Dask (yielded as they are needed)."""
    from functools import partial

    from emlpack.qm.executor import Executor

    with Executor(workers or 0, scheduler) as executor:
        if executor.uses_dask and not scheduler:
            lab.threads = executor.threads_per_task
        yield from executor.map_ordered(partial(_label_frame, lab), frames)
