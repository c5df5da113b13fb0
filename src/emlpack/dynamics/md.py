"""Born-Oppenheimer molecular dynamics of the cores with relaxed electron pairs (float64).

:func:`run_md` integrates the cores with ASE (``NoseHooverChainNVT``, chain length 3, time
constant 100 fs as yaff's defaults, or ``VelocityVerlet`` for NVE) on an
:class:`~emlpack.calculators.ase.EMLPCalculator` whose pair solver
(:mod:`emlpack.pairs.solvers`) relaxes the electron pairs at every new core geometry:

* ``relax="corrected"`` (default, :class:`~emlpack.pairs.solvers.WarmStartSolver`): the pairs
  and cores of the last four relaxed steps are extrapolated (cubic) and the pairs get the linear
  response to the cores' extrapolation error, ``dp = -H^-1 C^T dc``; then a quasi-Newton
  method whose models of the pair Hessian ``H`` and of the core-pair block ``C`` are carried
  over from step to step (rotated with the molecule, refined by damped BFGS / Broyden updates
  from every evaluation, exact at a fresh start and when the measured model error exceeds
  0.5). The loop stops when (largest relative model error measured in this and the last step)
  x (largest pair-force component) < ``fmax`` (1e-5 eV/Å), i.e. when one more model Newton
  step ``s = -H^-1 g`` would converge the pairs; that step is applied without an evaluation:
  pairs + s, energy + g.s + s.H.s/2, core gradient g_c + C s. Measured (hexane, trained
  benchmark model, dt 0.5 fs): about 2.3 energy+gradient evaluations per step, per-step core
  forces as accurate as ``"warm"`` at the same ``fmax`` (benchmarks/md.py; docs/md.md).
* ``relax="warm"``: the pairs' offsets from their nearest cores extrapolated (cubic) and the
  same carried-Hessian quasi-Newton without the coupling model and the final correction,
  stopped at largest pair-force component < ``fmax`` (about 3.4 evaluations per step).
* ``relax="paper"`` (:class:`~emlpack.pairs.solvers.BoxedLBFGSB`): the reference code's
  scheme, SciPy L-BFGS-B from the previous pairs with every pair coordinate boxed to ±3x the
  largest core displacement since the last step
  (0.1 Å on the first call), ``gtol`` 1e-5 eV/Å.

A :class:`Watchdog` checks every step (relaxation converged, no two pairs closer than
``min_pair_distance``, no pair farther than ``max_core_distance`` from every core, and every
``curvature_every`` steps a positive smallest eigenvalue of the exact pair Hessian: Davidson
iterations on finite-difference Hessian-vector products, preconditioned by the carried model;
:func:`emlpack.pairs.checks.check_pairs` with the watchdog's thresholds; and that the potential
energy changed by the work of the forces along the step, within ``max_energy_mismatch`` per
core, so that pairs which jumped to another minimum or stopped short of theirs are caught even
when the solver reports convergence). A failed step is
rolled back (positions, momenta, thermostat, calculator and solver state) and retried from the
pairs of the last good step moved rigidly with their nearest cores, then from
:func:`emlpack.pairs.guess.guess_pairs`. When every start fails the energy check alone, the
model's surface itself jumps there (the pairs' minimum has gone): the result of the smallest
mismatch is kept and the event says so (``"fallback": "kept"``), and the conserved-quantity
analysis sees the jump. Otherwise, if both fallbacks fail, the run stops with
:class:`MDWatchdogError` after writing everything so far.

Outputs in the directory ``output``: ``trajectory.xyz`` (native extxyz, one frame per recorded
step, pairs as ``Es`` rows; see :func:`frame_structure` for the ``info`` keys), ``checkpoint.npz``
(full integrator, thermostat and pair state, written atomically with the byte length of the
trajectory it belongs to) and ``summary.json`` (``stopped.json`` instead when the watchdog stopped
the run: :func:`emlpack.dynamics.analysis.analyze_trajectory` then calls it unstable); progress
lines and watchdog events go to the module's logger (``emlp md`` writes them to ``md.log``),
and with ``progress=True`` a bar over the steps (:func:`emlpack.progress.progress`) shows the
rate and the time left. Re-running the same call resumes from the checkpoint (a partial
trailing frame is cut off) and continues the same trajectory.

Energies (the frames' ``energy``, ``potential_energy`` and ``conserved_energy``, the log's
``Epot``/``Econs``) are on the DFT scale when the model is a
:class:`~emlpack.calculators.ensemble.ModelMember` (or a checkpoint path) that carries its DFT
hydride references and the molecule is neutral, as every property command reports them
(``E = U + c . (E_DFT - U_hyd)``, a constant of the composition: the dynamics are the same);
else the model's own. :attr:`MDResult.energy_scale` says which (``"dft"`` or ``"model"``).
"""

from __future__ import annotations

import copy
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import ase.units
import numpy as np
import torch
from ase import Atoms
from ase.calculators.calculator import CalculationFailed
from ase.md.nose_hoover_chain import NoseHooverChainNVT
from ase.md.velocitydistribution import (
    Stationary,
    ZeroRotation,
    thermalize_momenta,
)
from ase.md.verlet import VelocityVerlet

from emlpack._files import atomic_write, write_npz_atomic
from emlpack.calculators.ase import EMLPCalculator
from emlpack.calculators.ensemble import ModelMember, load_member
from emlpack.errors import EmlpackError
from emlpack.io.extxyz import write_structures
from emlpack.nn.potential import EMLP
from emlpack.pairs.checks import MAX_CORE_DISTANCE, MD_MIN_PAIR_DISTANCE, check_pairs
from emlpack.pairs.guess import guess_matched
from emlpack.pairs.solvers import WarmStartSolver, md_solver
from emlpack.progress import progress as progress_bar
from emlpack.structure import Structure

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = [
    "MDResult",
    "MDWatchdogError",
    "Watchdog",
    "run_md",
    "TRAJECTORY",
    "CHECKPOINT",
    "STOPPED",
]

TRAJECTORY = "trajectory.xyz"
CHECKPOINT = "checkpoint.npz"
#: the log file ``emlp md`` writes in the output folder (the library itself only logs to
#: ``logging.getLogger(__name__)``; the CLI installs the handlers)
LOG = "md.log"
SUMMARY = "summary.json"
#: written when the watchdog stops a run (``{"step", "last_good_step", "reason"}``), so that an
#: analysis of the partial trajectory knows it is not a finished run; removed by a run that
#: finishes (a resumed one) or starts over
STOPPED = "stopped.json"

_log = logging.getLogger(__name__)


class MDWatchdogError(EmlpackError, RuntimeError):
    """The pairs could not be relaxed at some MD step, even from the fallback guesses."""


# ------------------------------------------------------------------------------ watchdog
@dataclass
class Watchdog:
    """MD's policy on the pairs after every step (Å): :func:`~emlpack.pairs.checks.check_pairs`
    with these thresholds (docs/md.md; stricter on merged pairs than a single relaxation's
    0.1 Å), and the exact pair curvature every ``curvature_every`` steps."""

    min_pair_distance: float = MD_MIN_PAIR_DISTANCE
    max_core_distance: float = MAX_CORE_DISTANCE
    #: exact pair Hessian (positive curvature) every this many steps (0: never)
    curvature_every: int = 50
    #: largest |dU + (F0 + F1)/2 . dR| of one step per core (eV): the potential energy must
    #: change by the work of the forces (trapezoid rule, error ~dt^3: below 1e-4 eV per core
    #: in the study's stable runs); more means the pairs left their minimum (jumped to another
    #: one, or stopped short of it); 0: never checked
    max_energy_mismatch: float = 1e-3

    def check(self, cores: np.ndarray, pairs: np.ndarray, diagnostics: dict) -> str:
        """Empty string when fine, else the reasons (the solver's ``diagnostics["reason"]``
        first, then :func:`check_pairs` at the watchdog's thresholds)."""
        reasons = [diagnostics["reason"]] if diagnostics.get("reason") else []
        found = check_pairs(pairs, cores, min_pair_distance=self.min_pair_distance,
                            max_core_distance=self.max_core_distance,
                            min_curvature=diagnostics.get("min_curvature", float("nan")))
        return "; ".join(reasons + ([found] if found else []))

    @staticmethod
    def _energy_and_work(before: tuple[float, np.ndarray, np.ndarray],
                         after: tuple[float, np.ndarray, np.ndarray]) -> tuple[float, float, int]:
        """(dU, (F0 + F1)/2 . dR, cores) of a step, eV."""
        (e0, f0, r0), (e1, f1, r1) = before, after
        return e1 - e0, float(0.5 * np.sum((f0 + f1) * (r1 - r0))), max(len(r0), 1)

    @staticmethod
    def energy_mismatch(before: tuple[float, np.ndarray, np.ndarray],
                        after: tuple[float, np.ndarray, np.ndarray]) -> float:
        """|dU + (F0 + F1)/2 . dR| per core (eV) of a step from ``before`` to ``after``, each
        (energy eV, forces eV/Å, core positions Å)."""
        change, work, n = Watchdog._energy_and_work(before, after)
        return abs(change + work) / n

    def check_step(self, before: tuple[float, np.ndarray, np.ndarray],
                   after: tuple[float, np.ndarray, np.ndarray]) -> str:
        """Empty string when the potential energy of a step changed by the work of the forces
        along it (:meth:`energy_mismatch` at most ``max_energy_mismatch``), else the reason."""
        if not self.max_energy_mismatch:
            return ""
        change, work, n = self._energy_and_work(before, after)
        mismatch = abs(change + work) / n
        if mismatch <= self.max_energy_mismatch:
            return ""
        return (f"the potential energy changed by {change:+.4g} eV where the forces did"
                f" {work:+.4g} eV of work ({mismatch:.3g} eV per core; threshold"
                f" {self.max_energy_mismatch:g}): the pairs left their minimum")


# ------------------------------------------------------------------------------ driver
@dataclass
class MDResult:
    """Summary of a run (counts, eV, K, s); per-step figures cover steps 1..``steps`` of the
    whole run (resumed parts included, the initial relaxation of step 0 excluded)."""

    output: str
    steps: int
    frames: int
    watchdog_events: int
    evaluations_per_step: float
    hessians_per_step: float
    seconds_per_step: float
    final_temperature: float
    final_conserved_energy: float
    relax: str
    ensemble: str
    resumed_from: int = 0
    events: list = field(default_factory=list)
    #: the energies' scale: "dft" (the model's DFT hydride references) or "model"
    energy_scale: str = "model"


def run_md(
    model: EMLP | ModelMember | str | Path,
    structure: Structure,
    steps: int,
    output: str | Path,
    dt_fs: float = 0.5,
    temperature_K: float | None = 300.0,
    ensemble: str = "nvt",
    field: np.ndarray | Sequence[float] | None = None,
    seed: int = 0,
    tdamp_fs: float = 100.0,
    tchain: int = 3,
    relax: str = "corrected",
    fmax: float = 1e-5,
    record_every: int = 1,
    checkpoint_every: int = 10,
    log_every: int = 10,
    resume: bool = True,
    watchdog: Watchdog | None = None,
    extrapolation: int = 3,
    guess_method: str = "auto",
    callback: Callable[[int, Atoms, EMLPCalculator], None] | None = None,
    progress: bool = False,
) -> MDResult:
    """Run (or resume) Born-Oppenheimer MD of ``structure`` for ``steps`` steps in total.

    Args:
        model: the eMLP, a :class:`~emlpack.calculators.ensemble.ModelMember` or a checkpoint
            path (evaluated in float64; a member or checkpoint with DFT hydride references
            gives energies on the DFT scale, see the module docstring).
        structure: start (cores; pairs may be empty: guessed and relaxed). Velocities (Å/fs)
            in ``structure.info["velocities"]`` (flat or (N, 3)) are used when present.
        steps: total number of MD steps (a resumed run continues up to it).
        output: output directory (trajectory, checkpoint, summary).
        dt_fs: time step (fs).
        temperature_K: NVT target and initial Maxwell-Boltzmann temperature (K); ``None``
            starts at rest (NVE only).
        ensemble: ``"nvt"`` (Nosé-Hoover chain, ``tchain``, ``tdamp_fs``) or ``"nve"``.
        field: homogeneous field (V/Å); default ``structure.field``.
        seed: seed of the initial velocities.
        relax: ``"corrected"``, ``"warm"`` or ``"paper"`` (see the module docstring).
        fmax: pair-relaxation tolerance (eV/Å).
        record_every: a trajectory frame every this many steps (step 0 included).
        checkpoint_every: frames are appended and the checkpoint written every this many steps.
        resume: continue from ``output/checkpoint.npz`` when it exists.
        watchdog: the checks (:class:`Watchdog`).
        callback: called after every accepted step as ``callback(step, atoms, calc)``
            (``calc.pair_solver`` is the :class:`~emlpack.pairs.solvers.WarmStartSolver`).
        progress: a progress bar over the steps on stderr (:func:`emlpack.progress.progress`).
    """
    if ensemble not in ("nvt", "nve"):
        raise ValueError(f"ensemble must be 'nvt' or 'nve', not {ensemble!r}")
    if ensemble == "nvt" and temperature_K is None:
        raise ValueError("NVT needs temperature_K")
    if structure.pbc:
        raise ValueError(f"{structure.source}: run_md supports molecules only (no cell)")
    watchdog = watchdog or Watchdog()
    out_dir = Path(output)
    out_dir.mkdir(parents=True, exist_ok=True)
    log = _log
    if isinstance(model, (str, Path)):
        model = load_member(model, torch.float64)
    member = model if isinstance(model, ModelMember) else ModelMember(model)
    model = member.model.double().eval()
    member = replace(member, model=model)
    dft = member.hydride_delta() is not None and structure.charge == 0
    flags = [(p, p.requires_grad) for p in model.parameters()]
    for p, _ in flags:
        p.requires_grad_(False)
    field_v = structure.field if field is None else np.asarray(field, float).reshape(3)
    signature = {
        "numbers": structure.numbers.tolist(), "dt_fs": dt_fs, "temperature_K": temperature_K,
        "ensemble": ensemble, "field": field_v.tolist(), "seed": seed, "tdamp_fs": tdamp_fs,
        "tchain": tchain, "relax": relax, "fmax": fmax, "record_every": record_every,
        "extrapolation": extrapolation,
    }
    if dft:  # a run on the model's scale (before there was a DFT scale) resumes as it was
        signature["energy_scale"] = "dft"
    try:
        return _Run(member, structure, field_v, out_dir, log, signature, watchdog,
                    guess_method, callback, progress).run(steps, resume, checkpoint_every,
                                                          log_every)
    finally:
        for p, flag in flags:
            p.requires_grad_(flag)


class _Run:
    def __init__(self, member: ModelMember, structure: Structure, field_v: np.ndarray,
                 out_dir: Path, log: logging.Logger, sig: dict, watchdog: Watchdog,
                 guess_method: str, callback: Callable[[int, Atoms, EMLPCalculator], None] | None,
                 progress: bool = False):
        self.model, self.s0, self.field = member.model, structure, field_v
        self.progress = progress
        self.energy_scale = sig.get("energy_scale", "model")
        self.dir, self.log, self.sig = out_dir, log, sig
        self.watchdog, self.guess_method, self.callback = watchdog, guess_method, callback
        self.traj = out_dir / TRAJECTORY
        self.ckpt = out_dir / CHECKPOINT
        self.atoms = Atoms(structure.numbers, structure.positions)
        self.atoms.info["charge"] = float(structure.charge)
        self.solver: WarmStartSolver = md_solver(sig["relax"], fmax=sig["fmax"],
                                                 extrapolation=sig["extrapolation"])
        self.calc = EMLPCalculator(member, field=field_v, pairs=structure.pairs,
                                   pair_solver=self.solver, check_bonding=False)
        self.atoms.calc = self.calc
        dt = sig["dt_fs"] * ase.units.fs
        if sig["ensemble"] == "nvt":
            self.dyn = NoseHooverChainNVT(self.atoms, dt, sig["temperature_K"],
                                          sig["tdamp_fs"] * ase.units.fs, tchain=sig["tchain"])
        else:
            self.dyn = VelocityVerlet(self.atoms, dt)
        self.step = 0
        self.events: list[dict] = []
        self.buffer: list[Structure] = []
        self.frames = 0
        self.step_evals = 0
        self.step_hess = 0
        self.wall = 0.0
        #: evaluations, Hessians and seconds spent before step 1 (the initial relaxation)
        self.base = [0, 0, 0.0]

    # -------------------------------------------------------------- state
    def snapshot(self) -> dict:
        calc = self.calc
        snap = {
            "positions": self.atoms.positions.copy(),
            "momenta": self.atoms.get_momenta().copy(),
            "solver": self.solver.state(),
            "results": copy.deepcopy(calc.results),
            "atoms_positions": None if calc.atoms is None else calc.atoms.positions.copy(),
        }
        if isinstance(self.dyn, NoseHooverChainNVT):
            snap["eta"] = self.dyn._thermostat._eta.copy()
            snap["p_eta"] = self.dyn._thermostat._p_eta.copy()
        return snap

    def restore(self, snap: dict) -> None:
        self.atoms.calc = None
        self.atoms.positions[:] = snap["positions"]
        self.atoms.set_momenta(snap["momenta"])
        self.calc.reset()  # results, the calculator's warm start and the solver's state
        self.solver.set_state(snap["solver"])
        if snap["atoms_positions"] is not None:  # the results belong to these positions
            done = self.atoms.copy()
            done.positions[:] = snap["atoms_positions"]
            self.calc.set_results(done, snap["results"])
        self.atoms.calc = self.calc
        if isinstance(self.dyn, NoseHooverChainNVT):
            self.dyn._thermostat._eta[:] = snap["eta"]
            self.dyn._thermostat._p_eta[:] = snap["p_eta"]
            self.dyn._q = self.atoms.get_positions()
            self.dyn._p = self.atoms.get_momenta()

    def thermostat_energy(self) -> float:
        if isinstance(self.dyn, NoseHooverChainNVT):
            return float(self.dyn._thermostat.get_thermostat_energy())
        return 0.0

    # -------------------------------------------------------------- checkpoint
    def write_checkpoint(self) -> None:
        snap = self.snapshot()
        c = snap.pop("solver")
        hist = c.pop("history")
        results = snap["results"]
        arrays = {
            "positions": snap["positions"], "momenta": snap["momenta"],
            "eta": snap.get("eta", np.zeros(0)), "p_eta": snap.get("p_eta", np.zeros(0)),
            "start_pairs": self.calc.initial_pairs,
            "hessian": np.zeros((0, 0)) if c["hessian"] is None else c["hessian"],
            "coupling": np.zeros((0, 0)) if c["coupling"] is None else c["coupling"],
            "history_cores": np.array([h[0] for h in hist]),
            "history_pairs": np.array([h[1] for h in hist]),
            "forces": results["forces"],
            "dipole": results["dipole"],
        }
        meta = {
            "signature": self.sig, "step": self.step, "frames": self.frames,
            "trajectory_bytes": self.traj.stat().st_size if self.traj.exists() else 0,
            "energy": results["energy"], "diagnostics": _jsonable(c["diagnostics"]),
            "n_evaluations": c["n_evaluations"], "n_hessians": c["n_hessians"],
            "events": self.events, "wall": self.wall,
            "has_hessian": c["hessian"] is not None, "base": self.base,
            "has_coupling": c["coupling"] is not None, "model_error": c["model_error"],
        }
        arrays["meta"] = np.array(json.dumps(meta))
        write_npz_atomic(self.ckpt, **arrays)

    def load_checkpoint(self) -> bool:
        if not self.ckpt.exists():
            return False
        with np.load(self.ckpt) as data:
            a = {k: data[k] for k in data.files}
        meta = json.loads(str(a["meta"]))
        if meta["signature"] != _jsonable(self.sig):
            diff = sorted(k for k in self.sig if meta["signature"].get(k) != _jsonable(self.sig[k]))
            raise ValueError(
                f"{self.ckpt}: the checkpoint belongs to a different run (differs in {diff});"
                " use another output directory or start over (resume=False, emlp md --no-resume)")
        results = {"energy": meta["energy"], "free_energy": meta["energy"],
                   "forces": a["forces"], "dipole": a["dipole"]}
        solver_state = {
            "history": list(zip(a["history_cores"], a["history_pairs"], strict=True)),
            "hessian": a["hessian"] if meta["has_hessian"] else None,
            "coupling": a["coupling"] if meta.get("has_coupling") else None,
            "model_error": meta.get("model_error", 1.0),
            "diagnostics": meta["diagnostics"], "n_evaluations": meta["n_evaluations"],
            "n_hessians": meta["n_hessians"],
        }
        snap = {"positions": a["positions"], "momenta": a["momenta"], "solver": solver_state,
                "results": results, "atoms_positions": a["positions"],
                "eta": a["eta"], "p_eta": a["p_eta"]}
        self.calc.initial_pairs = a["start_pairs"].reshape(-1, 3)
        self.restore(snap)
        self.step, self.frames = meta["step"], meta["frames"]
        self.events, self.wall = meta["events"], meta["wall"]
        self.base = meta["base"]
        # cut the trajectory back to what the checkpoint covers (drops a partial frame)
        size = meta["trajectory_bytes"]
        if not self.traj.exists() or self.traj.stat().st_size < size:
            raise ValueError(f"{self.traj}: shorter than the checkpoint says ({size} bytes);"
                             " the trajectory was modified, start a new run")
        with open(self.traj, "r+b") as fh:
            fh.truncate(size)
        return True

    # -------------------------------------------------------------- frames
    def frame(self) -> Structure:
        atoms, calc = self.atoms, self.calc
        d = self.solver.diagnostics
        kin = float(atoms.get_kinetic_energy())
        pot = float(calc.results["energy"])
        thermo = self.thermostat_energy()
        info = {
            "step": int(self.step),
            "time": float(self.step * self.sig["dt_fs"]),
            "potential_energy": pot,
            "kinetic_energy": kin,
            "thermostat_energy": thermo,
            "conserved_energy": kin + pot + thermo,
            "temperature": float(atoms.get_temperature()),
            "dipole": np.asarray(calc.results["dipole"], float).copy(),
            "relax_evaluations": int(self.step_evals),
            "relax_hessians": int(self.step_hess),
            "relax_max_force": float(d.get("max_force", 0.0)),
            "watchdog_events": len(self.events),
            "velocities": (atoms.get_velocities() * ase.units.fs).reshape(-1),
        }
        return Structure(atoms.numbers, atoms.positions.copy(), self.solver.pairs.copy(),
                         field=self.field, charge=self.s0.charge, energy=pot,
                         forces=np.asarray(calc.results["forces"]).copy(), info=info)

    def flush(self) -> None:
        """Append the buffered frames (fsync), then write the checkpoint atomically."""
        if self.buffer:
            tmp = self.dir / f".{TRAJECTORY}.chunk"
            write_structures(tmp, self.buffer)
            data = tmp.read_bytes()
            tmp.unlink()
            with open(self.traj, "ab") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            self.frames += len(self.buffer)
            self.buffer = []
        self.write_checkpoint()

    # -------------------------------------------------------------- stepping
    def attempt(self, advance: Callable[[], None], snap: dict) -> tuple[str, float | None]:
        """Run ``advance``; the watchdog's reasons to reject the result (empty: accepted) and,
        when the energy check is the only one that failed, the step's energy mismatch.
        ``snap``: the state before, whose energy and forces the step's must join smoothly."""
        self.solver.diagnostics = {}
        try:
            advance()
            failed = ""
        except CalculationFailed as exc:  # the solver's check_pairs failed, or worse
            failed = str(exc)
        d = self.solver.diagnostics
        self.step_evals += d.get("n_evaluations", 0)
        self.step_hess += d.get("n_hessians", 0)
        if failed:
            return failed, None
        reason = self.watchdog.check(self.atoms.positions, self.solver.pairs, d)
        before = snap["results"]
        if reason or snap["atoms_positions"] is None or "forces" not in before:
            return reason, None  # at the start there is no step to join
        r = self.calc.results
        ends = ((before["energy"], before["forces"], snap["atoms_positions"]),
                (r["energy"], r["forces"], self.atoms.positions))
        reason = self.watchdog.check_step(*ends)
        return reason, (self.watchdog.energy_mismatch(*ends) if reason else None)

    def guarded(self, advance: Callable[[], None], what: str) -> None:
        """Run ``advance`` with the watchdog: roll back and retry from fallback pairs. When
        every start fails the energy check alone, the surface itself is discontinuous there
        (the pairs' minimum has gone): the result of the smallest mismatch is kept, and the
        event says so (the conserved-quantity analysis then sees the jump)."""
        snap = self.snapshot()
        self.step_evals = self.step_hess = 0
        every = self.watchdog.curvature_every
        if every and self.step % every == 0:
            self.solver.want_curvature = True
        reason, mismatch = self.attempt(advance, snap)
        if not reason:
            return
        kept = (mismatch, self.snapshot()) if mismatch is not None else None
        tried = [f"{self.solver.diagnostics.get('start', 'start')}: {reason}"]
        # rigid follow needs a last good step; at the start only the fresh guess is left
        fallbacks = ["rigid", "guess"] if snap["solver"]["history"] else ["guess"]
        for fb in fallbacks:
            event = {"step": self.step, "reason": reason, "fallback": fb}
            self.events.append(event)
            self.log.warning("watchdog: %s %d: %s -> roll back, retry from %s pairs",
                             what, self.step, reason, fb)
            evals, hess = self.step_evals, self.step_hess
            self.restore(snap)
            self.step_evals, self.step_hess = evals, hess
            self.solver.restart = fb
            self.solver.want_curvature = True
            reason, mismatch = self.attempt(advance, snap)
            event["ok"] = not reason
            if not reason:
                self.log.warning("watchdog: %s %d recovered from %s pairs", what, self.step, fb)
                return
            if mismatch is not None and (kept is None or mismatch < kept[0]):
                kept = (mismatch, self.snapshot())
            tried.append(f"{fb}: {reason}")
        if kept is not None:
            evals, hess = self.step_evals, self.step_hess
            self.restore(kept[1])
            self.step_evals, self.step_hess = evals, hess
            self.events.append({"step": self.step, "reason": reason, "fallback": "kept",
                                "ok": True, "energy_mismatch_eV_per_core": kept[0]})
            self.log.warning("watchdog: %s %d: every start relaxes to pairs whose energy jumps"
                             " (%.3g eV per core): kept, the model's surface is discontinuous"
                             " here", what, self.step, kept[0])
            return
        failed = self.step
        self.restore(snap)
        if what == "step":  # keep everything up to the last good step
            self.step -= 1
            self.flush()
            kept_text = f"the trajectory and checkpoint up to step {self.step} are in {self.dir}"
        else:
            kept_text = "nothing written"
        message = (f"MD {what} {failed}: the electron pairs could not be relaxed ("
                   + " | ".join(tried) + f"); stopped, {kept_text}")
        stop = {"step": failed, "last_good_step": self.step if what == "step" else None,
                "reason": message}
        atomic_write(self.dir / STOPPED, lambda fh: json.dump(stop, fh, indent=1))
        raise MDWatchdogError(message)

    def initial(self) -> None:
        """Velocities and the relaxed pairs of step 0."""
        sig = self.sig
        vel = self.s0.info.get("velocities")
        if vel is not None:
            self.atoms.set_velocities(np.asarray(vel, float).reshape(-1, 3) / ase.units.fs)
        elif sig["temperature_K"]:
            rng = np.random.default_rng(sig["seed"])
            thermalize_momenta(self.atoms, sig["temperature_K"], rng=rng)
            Stationary(self.atoms)
            if len(self.atoms) > 1:
                ZeroRotation(self.atoms)
        if isinstance(self.dyn, NoseHooverChainNVT):
            self.dyn._q = self.atoms.get_positions()
            self.dyn._p = self.atoms.get_momenta()
        if self.s0.n_pairs == 0:
            self.log.info("no electron pairs in the start structure: guess_pairs + relaxation")
            self.calc.initial_pairs = guess_matched(self.s0.numbers, self.s0.positions,
                                                    np.zeros((0, 3)), self.s0.charge,
                                                    self.guess_method)
        self.guarded(lambda: self.atoms.get_forces(), "start")

    def run(self, steps: int, resume: bool, checkpoint_every: int, log_every: int) -> MDResult:
        resumed = 0
        if resume and self.load_checkpoint():
            resumed = self.step
            self.log.info("resuming from step %d (%d frames) in %s", self.step, self.frames,
                          self.dir)
        else:
            for path in (self.traj, self.ckpt, self.dir / STOPPED):
                if path.exists():
                    path.unlink()
            self.log.info("MD %s: %d steps, dt %g fs, T %s K, field %s V/Å, relax %s, %d cores,"
                          " %d pairs, energies on the %s scale -> %s",
                          self.sig["ensemble"].upper(), steps, self.sig["dt_fs"],
                          self.sig["temperature_K"], self.sig["field"], self.sig["relax"],
                          len(self.atoms), len(self.calc.initial_pairs),
                          self.energy_scale.upper() if self.energy_scale == "dft" else "model's",
                          self.dir)
            t0 = time.perf_counter()
            self.initial()
            self.wall += time.perf_counter() - t0
            self.base = [self.solver.n_evaluations, self.solver.n_hessians, self.wall]
            self.buffer.append(self.frame())
            self.flush()
        if self.step >= steps:
            self.log.info("the run is complete (%d steps); nothing to do", self.step)
        evals0, hess0, wall0 = self.base
        step0 = 0
        record = self.sig["record_every"]
        bar = progress_bar(total=steps, initial=min(self.step, steps), desc="md", unit="step",
                           enabled=self.progress)
        try:
            while self.step < steps:
                t0 = time.perf_counter()
                self.step += 1
                self.guarded(self.dyn.step, "step")
                self.wall += time.perf_counter() - t0
                bar.update(1)
                if self.step % record == 0:
                    self.buffer.append(self.frame())
                if self.callback is not None:
                    self.callback(self.step, self.atoms, self.calc)
                if self.step % checkpoint_every == 0 or self.step == steps:
                    self.flush()
                if self.step % log_every == 0 or self.step == steps:
                    f = self.frame()
                    done = max(self.step - step0, 1)
                    self.log.info(
                        "step %d t %.1f fs T %.1f K Epot %.6f eV Econs %.6f eV evals/step %.2f"
                        " s/step %.4f events %d", self.step, f.info["time"],
                        f.info["temperature"], f.info["potential_energy"],
                        f.info["conserved_energy"],
                        (self.solver.n_evaluations - evals0) / done, (self.wall - wall0) / done,
                        len(self.events))
                    bar.set_postfix_str(f"T {f.info['temperature']:.0f} K, Econs"
                                        f" {f.info['conserved_energy']:.4f} eV", refresh=False)
        except MDWatchdogError:
            raise
        except BaseException:
            # interrupted: keep the frames and checkpoint of the last complete flush only
            self.buffer = []
            raise
        finally:
            bar.close()
        done = max(self.step - step0, 1)
        f = self.frame()
        result = MDResult(
            output=str(self.dir), steps=self.step, frames=self.frames,
            watchdog_events=len(self.events),
            evaluations_per_step=(self.solver.n_evaluations - evals0) / done,
            hessians_per_step=(self.solver.n_hessians - hess0) / done,
            seconds_per_step=(self.wall - wall0) / done,
            final_temperature=f.info["temperature"],
            final_conserved_energy=f.info["conserved_energy"],
            relax=self.sig["relax"], ensemble=self.sig["ensemble"], resumed_from=resumed,
            events=self.events, energy_scale=self.energy_scale,
        )
        atomic_write(self.dir / SUMMARY, lambda fh: json.dump(asdict(result), fh, indent=1))
        (self.dir / STOPPED).unlink(missing_ok=True)  # a stopped run resumed to its end
        self.log.info("done: %d steps, %d frames, %d watchdog events, %.2f evaluations/step,"
                      " %.3f Hessians/step, %.4f s/step", result.steps, result.frames,
                      result.watchdog_events, result.evaluations_per_step,
                      result.hessians_per_step, result.seconds_per_step)
        return result


def _jsonable(obj: object):
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist")
                                 else float(o)))

