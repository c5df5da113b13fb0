"""Stability of MD runs from the conserved quantity (the paper's section on MD augmentation).

For one run with ``n_atoms`` nuclei (electron pairs are not atoms) and the conserved quantity
``E_tot(t_i)`` (eV; kinetic + potential + thermostat energy, as recorded by ``emlp md``):

* the initialisation phase is discarded: every frame whose step is less than
  ``first step + discard_steps`` (paper: the first 10 steps; a trajectory starting at step 0
  keeps steps 10, 11, ...);
* ``E_cons(t) = E_tot(t) / n_atoms`` (eV per atom);
* ``s_cons``: slope of the least-squares line ``E_cons(t) ~ a + s_cons t`` (eV/fs per atom);
* ``max |dE_cons|``: the largest ``|E_cons(t_{i+1}) - E_cons(t_i)|`` between consecutive
  recorded frames (eV per atom; the paper's jump between two time steps when every step is
  recorded, otherwise between frames ``stride`` steps apart, reported as ``stride_steps``);
* classification by the jump alone, as the paper defines the regions: ``stable`` when
  ``max |dE_cons| < 5e-4 eV``, ``transition`` when ``5e-4 <= max |dE_cons| <= 0.01 eV`` and
  ``unstable`` when ``> 0.01 eV`` (the paper's thresholds are per atom, since ``E_cons`` is;
  the exact boundaries 5e-4 and 0.01 belong to the transition region: "5e-4 to at most
  0.01 eV").

:func:`plot_conserved` draws the paper's Fig. (a): one point per run at
``(|s_cons|, max |dE_cons|)`` on log-log axes with the two thresholds.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import write_figure_atomic, write_json_atomic
from emlpack.dynamics.ir_acf import trajectory_file
from emlpack.errors import EmlpackError

if TYPE_CHECKING:
    from emlpack.dynamics.ir_acf import DipoleIRSpectrum

logger = logging.getLogger(__name__)

#: jump (eV per atom) below which a run is stable (paper)
STABLE_MAX_JUMP = 5e-4
#: jump (eV per atom) above which a run is unstable (paper)
UNSTABLE_MAX_JUMP = 1e-2
#: initial steps discarded (paper)
DISCARD_STEPS = 10
#: smallest number of frames left after the discard for a fit and a jump
MIN_FRAMES = 3
#: trajectory keys (Structure.info) read here, written by ``emlp md``
TIME_KEY, STEP_KEY, CONSERVED_KEY = "time", "step", "conserved_energy"

__all__ = [
    "ConservedAnalysis",
    "TrajectoryAnalysisError",
    "analyze_conserved",
    "analyze_trajectory",
    "classify",
    "plot_conserved",
    "plot_conserved_series",
    "read_conserved",
    "run_analysis",
    "run_md_ir",
    "trajectory_file",
]


class TrajectoryAnalysisError(EmlpackError, ValueError):
    """Unusable input for the analysis; the message names the file and frame."""


@dataclass
class ConservedAnalysis:
    """Conserved-quantity statistics of one MD run (eV, fs, per atom where stated).

    Attributes:
        source: file (or label) of the run.
        n_atoms: nuclei used for the per-atom normalisation.
        n_frames: frames used (after the discard).
        n_discarded: frames discarded at the start.
        first_step, last_step: MD steps of the first and last frame used.
        stride_steps: steps between consecutive frames used (1 = every step recorded).
        duration: time spanned by the frames used (fs).
        slope: s_cons, slope of the linear fit of E_cons(t) (eV/fs per atom).
        intercept: value of the fit at the first frame used (eV per atom).
        max_jump: max |E_cons(t_{i+1}) - E_cons(t_i)| (eV per atom).
        max_jump_step: step at the end of the largest jump.
        residual_std: standard deviation of E_cons about the fit (eV per atom).
        drift: slope x duration (eV per atom).
        classification: "stable", "transition" or "unstable" (from max_jump; "unstable"
            for a run the MD watchdog stopped).
        stopped: why the MD watchdog stopped the run (its ``stopped.json``), else "".
    """

    source: str
    n_atoms: int
    n_frames: int
    n_discarded: int
    first_step: int
    last_step: int
    stride_steps: int
    duration: float
    slope: float
    intercept: float
    max_jump: float
    max_jump_step: int
    residual_std: float
    drift: float
    classification: str
    stopped: str = ""

    def as_dict(self) -> dict:
        """Plain dict; keys with units: ``slope_eV_per_fs_per_atom`` etc."""
        d = asdict(self)
        return {
            "source": d["source"],
            "n_atoms": d["n_atoms"],
            "n_frames": d["n_frames"],
            "n_discarded": d["n_discarded"],
            "first_step": d["first_step"],
            "last_step": d["last_step"],
            "stride_steps": d["stride_steps"],
            "duration_fs": d["duration"],
            "slope_eV_per_fs_per_atom": d["slope"],
            "intercept_eV_per_atom": d["intercept"],
            "max_jump_eV_per_atom": d["max_jump"],
            "max_jump_step": d["max_jump_step"],
            "residual_std_eV_per_atom": d["residual_std"],
            "drift_eV_per_atom": d["drift"],
            "classification": d["classification"],
            "stopped": d["stopped"],
            "thresholds_eV_per_atom": {"stable_below": STABLE_MAX_JUMP,
                                       "unstable_above": UNSTABLE_MAX_JUMP},
        }

    def text(self) -> str:
        """One line: classification, slope (eV/fs/atom), largest jump (eV/atom), frames used."""
        return (
            f"{self.source}: {self.classification}; slope {self.slope:.3e} eV/fs/atom,"
            f" max jump {self.max_jump:.3e} eV/atom (step {self.max_jump_step}),"
            f" {self.n_frames} frames over {self.duration:.1f} fs"
            f" ({self.n_discarded} discarded, stride {self.stride_steps})"
            + (f"; stopped by the MD watchdog: {self.stopped}" if self.stopped else "")
        )


def classify(max_jump: float) -> str:
    """``stable`` (< 5e-4 eV), ``transition`` (5e-4 .. 0.01 eV inclusive) or ``unstable``."""
    if not math.isfinite(max_jump):
        return "unstable"
    if max_jump < STABLE_MAX_JUMP:
        return "stable"
    if max_jump <= UNSTABLE_MAX_JUMP:
        return "transition"
    return "unstable"


def analyze_conserved(
    times: Sequence[float] | np.ndarray,
    conserved: Sequence[float] | np.ndarray,
    n_atoms: int,
    steps: Sequence[int] | np.ndarray | None = None,
    discard_steps: int = DISCARD_STEPS,
    source: str = "<arrays>",
) -> ConservedAnalysis:
    """Analyse the conserved quantity of one run.

    Args:
        times: [n_frames] (fs), strictly increasing.
        conserved: [n_frames] total conserved quantity (eV, not per atom).
        n_atoms: number of nuclei (> 0).
        steps: [n_frames] MD step of each frame (default 0, 1, 2, ...).
        discard_steps: frames with ``step < steps[0] + discard_steps`` are dropped.
        source: name used in error messages and the result.

    Raises:
        TrajectoryAnalysisError: naming ``source`` and the frame, for non-finite values,
            non-increasing times or steps, or fewer than 3 frames after the discard.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    e = np.asarray(conserved, dtype=np.float64).reshape(-1)
    st = np.arange(len(t)) if steps is None else np.asarray(steps).reshape(-1)
    if not (len(t) == len(e) == len(st)):
        raise TrajectoryAnalysisError(
            f"{source}: {len(t)} times, {len(e)} energies and {len(st)} steps differ in length")
    if isinstance(n_atoms, bool) or int(n_atoms) != n_atoms or n_atoms <= 0:
        raise TrajectoryAnalysisError(f"{source}: n_atoms must be a positive integer, got"
                                      f" {n_atoms!r}")
    if discard_steps < 0:
        raise TrajectoryAnalysisError(f"{source}: discard_steps must be >= 0, got"
                                      f" {discard_steps}")
    for name, arr in (("time", t), ("conserved energy", e)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if len(bad):
            raise TrajectoryAnalysisError(
                f"{source}, frame {int(bad[0])}: {name} is not finite ({arr[bad[0]]})")
    for name, arr in (("time", t), ("step", st)):
        bad = np.flatnonzero(np.diff(arr) <= 0)
        if len(bad):
            k = int(bad[0]) + 1
            raise TrajectoryAnalysisError(
                f"{source}, frame {k}: {name} {arr[k]} does not increase (previous {arr[k - 1]})")
    if len(st) == 0:
        raise TrajectoryAnalysisError(f"{source}: no frames")
    keep = st >= st[0] + discard_steps
    n_discarded = int((~keep).sum())
    t, e, st = t[keep], e[keep] / n_atoms, st[keep]
    if len(t) < MIN_FRAMES:
        raise TrajectoryAnalysisError(
            f"{source}: {len(t)} frames left after discarding the first {discard_steps} steps"
            f" ({n_discarded} frames); at least {MIN_FRAMES} are needed")
    # least squares in centred time (well conditioned for long runs)
    tc = t - t.mean()
    slope = float(np.dot(tc, e - e.mean()) / np.dot(tc, tc))
    fit = e.mean() + slope * tc
    jumps = np.abs(np.diff(e))
    k = int(np.argmax(jumps))
    strides = np.diff(st)
    max_jump = float(jumps[k])
    return ConservedAnalysis(
        source=source,
        n_atoms=int(n_atoms),
        n_frames=len(t),
        n_discarded=n_discarded,
        first_step=int(st[0]),
        last_step=int(st[-1]),
        stride_steps=int(strides.max()),
        duration=float(t[-1] - t[0]),
        slope=slope,
        intercept=float(fit[0]),
        max_jump=max_jump,
        max_jump_step=int(st[k + 1]),
        residual_std=float(np.std(e - fit)),
        drift=slope * float(t[-1] - t[0]),
        classification=classify(max_jump),
    )


def read_conserved(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(times fs, conserved energy eV, steps, n_atoms) from an ``emlp md`` extxyz trajectory
    (or its output directory).

    Raises:
        TrajectoryAnalysisError: naming the file and frame of a missing or bad key, or a
            frame whose number of nuclei differs from the first frame's.
    """
    from emlpack.io import iread_structures

    path = trajectory_file(path)
    times, energies, steps = [], [], []
    n_atoms = None
    for i, s in enumerate(iread_structures(path)):
        where = f"{path}, frame {i}"
        for key in (TIME_KEY, STEP_KEY, CONSERVED_KEY):
            if key not in s.info:
                raise TrajectoryAnalysisError(
                    f"{where}: no '{key}' in the frame (not an 'emlp md' trajectory?)")
        try:
            times.append(float(s.info[TIME_KEY]))
            energies.append(float(s.info[CONSERVED_KEY]))
            steps.append(int(s.info[STEP_KEY]))
        except (TypeError, ValueError) as exc:
            raise TrajectoryAnalysisError(f"{where}: unreadable time/step/energy: {exc}") from None
        if n_atoms is None:
            n_atoms = s.n_cores
        elif s.n_cores != n_atoms:
            raise TrajectoryAnalysisError(
                f"{where}: {s.n_cores} nuclei, but frame 0 has {n_atoms}")
    if n_atoms is None:
        raise TrajectoryAnalysisError(f"{path}: no frames")
    return np.array(times), np.array(energies), np.array(steps), n_atoms


def analyze_trajectory(
    path: str | os.PathLike, discard_steps: int = DISCARD_STEPS
) -> ConservedAnalysis:
    """:func:`analyze_conserved` of the trajectory file ``path`` (frames' ``time``, ``step``
    and ``conserved_energy``; nuclei count from the frames). A run the MD watchdog stopped
    (``stopped.json`` beside the trajectory) is "unstable", whatever its frames show."""
    times, energies, steps, n_atoms = read_conserved(path)
    traj = trajectory_file(path)
    return _with_stop(analyze_conserved(times, energies, n_atoms, steps, discard_steps,
                                        source=str(traj)), traj)


def _with_stop(result: ConservedAnalysis, traj: Path) -> ConservedAnalysis:
    """``result`` of the trajectory ``traj``, "unstable" with the reason when the MD watchdog
    stopped its run (``stopped.json`` beside it)."""
    from emlpack.dynamics.md import STOPPED

    marker = traj.parent / STOPPED
    if not marker.exists():
        return result
    try:
        reason = str(json.loads(marker.read_text())["reason"])
    except (ValueError, KeyError, TypeError):
        reason = f"{marker} (unreadable)"
    return replace(result, classification="unstable", stopped=reason)


# ------------------------------------------------------------------------------------ plot
def plot_conserved(
    runs: Sequence[ConservedAnalysis | str | os.PathLike],
    png_path: str | os.PathLike,
    labels: Sequence[str] | None = None,
    groups: Sequence[str] | None = None,
    title: str = "",
    stopped: Sequence[bool] | None = None,
) -> list[ConservedAnalysis]:
    """Scatter plot (PNG, written atomically) of ``(|s_cons|, max |dE_cons|)``, one point per
    run, log-log, with the stable/unstable thresholds; ``runs`` are results or trajectory
    paths (analysed with the default discard). ``groups`` colour the points (e.g.
    "augmented"); ``labels`` annotate them (default: file stem); ``stopped`` marks the runs the
    MD watchdog stopped (crosses: unstable, whatever the part of the trajectory before the stop
    shows; default: each result's ``stopped``). Returns the analyses."""
    results = [r if isinstance(r, ConservedAnalysis) else analyze_trajectory(r) for r in runs]
    if not results:
        raise ValueError("plot_conserved: no runs")
    if labels is None:  # file stems, or directory names when the stems repeat
        labels = [Path(r.source).stem for r in results]
        if len(set(labels)) < len(labels):
            labels = [Path(r.source).parent.name or Path(r.source).stem for r in results]
    if groups is None:
        groups = [""] * len(results)
    if stopped is None:
        stopped = [bool(r.stopped) for r in results]
    if len(labels) != len(results) or len(groups) != len(results) \
            or len(stopped) != len(results):
        raise ValueError(f"plot_conserved: {len(results)} runs, {len(labels)} labels,"
                         f" {len(groups)} groups, {len(stopped)} stopped flags")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.array([abs(r.slope) for r in results])
    y = np.array([r.max_jump for r in results])
    # zeros cannot be drawn on log axes: put them at the bottom edge
    floor_x = min(x[x > 0].min(initial=1e-7) / 10, 1e-9)
    floor_y = min(y[y > 0].min(initial=1e-4) / 10, 1e-6)
    x = np.where(x > 0, x, floor_x)
    y = np.where(y > 0, y, floor_y)
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    colours = {"stable": "C2", "transition": "C1", "unstable": "C3"}
    for k, g in enumerate(dict.fromkeys(groups)):
        for cut, marker in ((False, "o"), (True, "X")):
            sel = [i for i, gi in enumerate(groups) if gi == g and bool(stopped[i]) == cut]
            if not sel:
                continue
            point_colours = [f"C{k}" if g else colours[results[i].classification] for i in sel]
            label = ((g or "runs") + ", stopped by the watchdog") if cut else (g or None)
            ax.scatter(x[sel], y[sel], s=36, zorder=3, c=point_colours, label=label,
                       marker=marker, edgecolors="k", linewidths=0.5)
    for xi, yi, text in zip(x, y, labels, strict=True):
        ax.annotate(text, (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    lo_y = min(y.min() / 3, STABLE_MAX_JUMP / 10)
    hi_y = max(y.max() * 3, UNSTABLE_MAX_JUMP * 10)
    ax.set_ylim(lo_y, hi_y)
    ax.set_xlim(min(x.min() / 3, 1e-8), max(x.max() * 3, 1e-4))
    ax.axhline(STABLE_MAX_JUMP, color="C2", ls="--", lw=1)
    ax.axhline(UNSTABLE_MAX_JUMP, color="C3", ls="--", lw=1)
    ax.axhspan(lo_y, STABLE_MAX_JUMP, color="C2", alpha=0.08)
    ax.axhspan(STABLE_MAX_JUMP, UNSTABLE_MAX_JUMP, color="C1", alpha=0.08)
    ax.axhspan(UNSTABLE_MAX_JUMP, hi_y, color="C3", alpha=0.08)
    ax.text(0.02, STABLE_MAX_JUMP * 0.8, "stable", transform=ax.get_yaxis_transform(),
            va="top", fontsize=8, color="C2")
    ax.text(0.02, UNSTABLE_MAX_JUMP * 0.8, "transition", transform=ax.get_yaxis_transform(),
            va="top", fontsize=8, color="C1")
    ax.text(0.02, UNSTABLE_MAX_JUMP * 1.25, "unstable", transform=ax.get_yaxis_transform(),
            va="bottom", fontsize=8, color="C3")
    ax.set_xlabel(r"$|s_\mathrm{cons}|$ (eV/fs per atom)")
    ax.set_ylabel(r"$\max|\Delta E_\mathrm{cons}|$ (eV per atom)")
    ax.set_title(title or "MD stability: conserved quantity per atom")
    if any(groups) or any(stopped):
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    write_figure_atomic(png_path, fig, dpi=120)
    plt.close(fig)
    return results


def plot_conserved_series(
    paths: Sequence[str | os.PathLike],
    png_path: str | os.PathLike,
    labels: Sequence[str] | None = None,
    discard_steps: int = DISCARD_STEPS,
    classes: Sequence[str] | None = None,
) -> None:
    """The paper's panels (b)/(c): ``E_cons(t) - E_cons(t_first)`` (eV per atom) of each
    trajectory after the discard, with its fitted line; PNG written atomically. The legend
    gives each run's class: ``classes[k]`` when given (a study with its own record of the
    runs the MD watchdog stopped), else the trajectory's (as :func:`analyze_trajectory`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for k, path in enumerate(paths):
        times, energies, steps, n_atoms = read_conserved(path)
        traj = trajectory_file(path)
        r = _with_stop(analyze_conserved(times, energies, n_atoms, steps, discard_steps,
                                         source=str(traj)), traj)
        keep = steps >= steps[0] + discard_steps
        t, e = times[keep], energies[keep] / n_atoms
        label = labels[k] if labels else Path(r.source).parent.name or Path(r.source).stem
        cls = classes[k] if classes else (
            r.classification + (" (stopped by the watchdog)" if r.stopped else ""))
        ax.plot(t, e - e[0], color=f"C{k}", lw=1,
                label=f"{label}: {cls},"
                      f" max jump {r.max_jump:.1e}")
        ax.plot(t, r.intercept - e[0] + r.slope * (t - t[0]), color=f"C{k}", ls=":", lw=1)
    ax.set_xlabel("time (fs)")
    ax.set_ylabel(r"$E_\mathrm{cons}(t) - E_\mathrm{cons}(t_0)$ (eV per atom)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_figure_atomic(png_path, fig, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------- commands
def run_analysis(
    paths: Sequence[str | os.PathLike],
    plot: str | os.PathLike | None = None,
    json_path: str | os.PathLike | None = None,
    discard_steps: int = DISCARD_STEPS,
    groups: Sequence[str] | None = None,
    series: str | os.PathLike | None = None,
    log: Callable[[str], None] | None = None,
) -> list[ConservedAnalysis]:
    """``emlp md-analysis``: analyse ``paths``, report one line each to ``log`` (default: this
    module's logger; the CLI prints), write the scatter PNG, the E_cons(t) plot (``series``)
    and a JSON ``{"runs": [as_dict(), ...]}`` (all atomically) when asked."""
    log = log or logger.info
    results = [analyze_trajectory(p, discard_steps) for p in paths]
    for r in results:
        log(r.text())
    if plot:
        plot_conserved(results, plot, groups=groups)
        log(f"wrote {plot}")
    if series:
        plot_conserved_series(paths, series, discard_steps=discard_steps)
        log(f"wrote {series}")
    if json_path:
        write_json_atomic(json_path, {"discard_steps": discard_steps,
                                      "runs": [r.as_dict() for r in results]})
        log(f"wrote {json_path}")
    return results


def run_md_ir(
    path: str | os.PathLike,
    json_path: str | os.PathLike,
    png_path: str | os.PathLike | None = None,
    harmonic_json: str | os.PathLike | None = None,
    temperature: float | None = None,
    discard_steps: int = 0,
    log: Callable[[str], None] | None = None,
    **options,
) -> DipoleIRSpectrum:
    """``emlp md-ir``: IR spectrum from the dipole ACF of an ``emlp md`` trajectory (see
    :func:`emlpack.dynamics.ir_acf.ir_from_trajectory`), optionally overlaid with the harmonic
    spectrum of an ``emlp ir`` JSON (``frequencies_cm-1``, ``intensities_km_per_mol``); the summary
    goes to ``log`` (default: this module's logger; the CLI prints)."""
    log = log or logger.info
    from emlpack.dynamics.ir_acf import ir_from_trajectory, write_dipole_ir

    spec = ir_from_trajectory(path, temperature, discard_steps, **options)
    log(spec.text())
    harmonic = None
    if harmonic_json:
        data = json.loads(Path(harmonic_json).read_text())
        try:
            harmonic = (np.asarray(data["frequencies_cm-1"], float),
                        np.asarray(data["intensities_km_per_mol"], float))
        except KeyError as exc:
            raise ValueError(f"{harmonic_json}: no {exc} (not an 'emlp ir' JSON?)") from None
    write_dipole_ir(spec, json_path, png_path, harmonic=harmonic, title=str(path))
    log(f"wrote {json_path}" + (f" and {png_path}" if png_path else ""))
    return spec
