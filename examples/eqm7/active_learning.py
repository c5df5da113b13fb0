"""Active learning for mini-eQM7 (issue 51, item 4): DP-GEN's concurrent learning, aimed at
the MD failures of the models.

Stages (``active_learning.yaml``; ``key=value`` arguments override it, dots for nesting)::

    explore   MD of training molecules (a seeded sample of the card's train split, never a
              validation or test molecule, an IR molecule or QM7 rows 0-9, by molecular
              graph) at each temperature, a random field per trajectory as in the data
              (<= 0.01 au, uniform in the ball): emlpack.dynamics.md.run_md (NVT, its
              watchdog) driven by one member of the ensemble from the campaign's prepared
              geometry; every recorded frame is then judged by all members (each relaxing its
              own pairs, warm-started from frame to frame): the spread of the core forces and
              of the pair positions (EMLPCalculator's forces_std and electron_pairs_std,
              emlpack.calculators.calibration.result_spread) and the bonding against the start
              (emlpack.bonding.bonding_changes) -> WORKDIR/round-RR/MOLECULE/TT-K/{trajectory.xyz,
              spread.json}; resumable per trajectory (run_md's checkpoint; spread.json last)
    select    the configurations to label -> DATA/active-learning/round-RR.xyz (native extxyz,
              never rewritten: a new round for a new selection) and round-RR.json (thresholds,
              counts); per frame, DP-GEN's trust levels: a candidate when a spread lies
              between its lower and upper threshold (forces: by default the median and the
              95 % quantile of the ensemble's calibrated spreads on the validation molecules)
              or a member could not relax the pairs where the driver could, and the frames
              just before a watchdog stop or event or before the first bonding change
              (whatever their spread); frames at or after a bonding change or a stop are not
              used. At most max_per_trajectory per trajectory, min_spacing_fs apart (failures
              first, then the largest spread), then round-robin over the trajectories up to the
              budget. Each configuration keeps its provenance: key, molecule, temperature,
              field, time, spreads, reason
    label     the selections' configurations at the data set's level (campaign.yaml: the
              paper's PBE0/aug-cc-pVTZ + DF, Foster-Boys centres; PySCFLabeler) into the
              data set's active-learning part shards/al-NNNN.h5 (emlpack.qm.campaign.label_part:
              new shards every label.shard_minutes, the card rewritten, the campaign's shards
              untouched), training molecules only; resumable: keys in any shard are skipped,
              on any machine; --commit commits each shard with the card and the selections
    status    what is done: trajectories, the measured cost (s per MD step, s per judged
              frame), frames by class, candidates by reason, labels done and to do

Usage (from the project root)::

    OMP_NUM_THREADS=1 python examples/eqm7/active_learning.py explore explore.molecules=2
    python examples/eqm7/active_learning.py select
    python examples/eqm7/active_learning.py label --commit     # safe in the background
    python examples/eqm7/active_learning.py status
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import write_json_atomic
from emlpack.data.shards import (
    ACTIVE_LEARNING_DIR,
    ACTIVE_LEARNING_PART,
    finished_keys,
    read_molecule_table,
)
from emlpack.errors import EmlpackError, InputError

if TYPE_CHECKING:
    from collections.abc import Callable

    from emlpack.calculators.ensemble import ModelEnsemble
    from emlpack.qm.recipe import Configuration
    from emlpack.structure import Structure

    Log = Callable[[str], None]

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]  # the project
STAGES = ("explore", "select", "label", "status")
#: a trajectory's judged frames and its MD outcome (written last: the trajectory is done)
SPREAD_FILE = "spread.json"
#: the reasons a frame is selected for, in order of priority: the frames just before an MD
#: failure, a member that could not relax the pairs where the driving member could, a spread
#: between the trust levels
REASONS = ("watchdog stop", "bonding change", "watchdog event", "member failure", "spread")
#: frame classes by spread (DP-GEN's): below both lower levels, between, above an upper one
CLASSES = ("accurate", "candidate", "failed")
#: keywords of the force thresholds: from the ensemble's spread calibration
CALIBRATED = ("calibrated", "calibrated-median")


# ---------------------------------------------------------------------- config
def resolve(path: str | Path) -> Path:
    """A config path: absolute, or relative to the project root."""
    p = Path(path)
    return p if p.is_absolute() else ROOT / p


def load_config(path: str | Path, overrides: list[str] = ()) -> dict:
    """The YAML config with ``key=value`` overrides, checked (:class:`InputError`, one line)."""
    from emlpack.overrides import apply_overrides, load_yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such config file")
    cfg = load_yaml(path.read_text()) or {}
    apply_overrides(cfg, list(overrides))
    check_config(cfg, path.name)
    return cfg


def _number(value: object, where: str, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or value < 0 or (positive and value == 0):
        raise InputError(f"{where} must be a {'positive' if positive else 'non-negative'}"
                         f" number, got {value!r}")
    return float(value)


def _count(value: object, where: str, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise InputError(f"{where} must be an integer >= {minimum}, got {value!r}")
    return value


def check_config(cfg: dict, where: str) -> None:
    """Refuse a config that cannot run, naming the entry."""
    for key in ("data", "smiles", "model", "workdir", "explore", "select", "label"):
        if key not in cfg:
            raise InputError(f"{where}: missing entry {key!r}")
    _count(cfg.get("driver"), f"{where}: driver", 0)
    _count(cfg.get("round"), f"{where}: round", 0)
    e, s, lab = cfg["explore"], cfg["select"], cfg["label"]
    temperatures = e.get("temperatures")
    if not isinstance(temperatures, list) or not temperatures:
        raise InputError(f"{where}: explore.temperatures must be a list of temperatures (K)")
    for t in temperatures:
        _number(t, f"{where}: explore.temperatures entry")
    if e.get("molecules") is not None:
        _count(e["molecules"], f"{where}: explore.molecules")
    if e.get("molecule_list") is not None and not (
            isinstance(e["molecule_list"], list) and e["molecule_list"]):
        raise InputError(f"{where}: explore.molecule_list must be null or a list of names")
    _count(e.get("trajectories"), f"{where}: explore.trajectories")
    _count(e.get("evaluate_every"), f"{where}: explore.evaluate_every")
    dt_fs = _number(e.get("dt_fs"), f"{where}: explore.dt_fs")
    if _number(e.get("time_fs"), f"{where}: explore.time_fs") < dt_fs:
        raise InputError(f"{where}: explore.time_fs must be at least one step (dt_fs)")
    if not 0 <= _number(e.get("field_max_au"), f"{where}: explore.field_max_au", False) <= 0.05:
        raise InputError(f"{where}: explore.field_max_au must lie in [0, 0.05] au")
    _count(e.get("seed"), f"{where}: explore.seed", 0)
    for name, unit in (("forces", "eV/Å"), ("pairs", "Å")):
        levels = s.get(name)
        if not isinstance(levels, dict) or set(levels) != {"lower", "upper"}:
            raise InputError(f"{where}: select.{name} needs a lower and an upper threshold")
        for key, value in levels.items():
            if name == "forces" and value in CALIBRATED:
                continue
            _number(value, f"{where}: select.{name}.{key} ({unit}"
                    + (", or calibrated / calibrated-median)" if name == "forces" else ")"),
                    positive=key == "upper")
        lo, hi = levels["lower"], levels["upper"]
        if not isinstance(lo, str) and not isinstance(hi, str) and lo >= hi:
            raise InputError(f"{where}: select.{name}: lower ({lo}) must be below upper ({hi})")
    _count(s.get("max_per_trajectory"), f"{where}: select.max_per_trajectory")
    _count(s.get("failure_frames"), f"{where}: select.failure_frames", 0)
    _count(s.get("budget"), f"{where}: select.budget")
    _number(s.get("min_spacing_fs"), f"{where}: select.min_spacing_fs", False)
    _count(lab.get("workers"), f"{where}: label.workers", 0)
    _number(lab.get("shard_minutes"), f"{where}: label.shard_minutes")
    if lab.get("hours") is not None:
        _number(lab["hours"], f"{where}: label.hours", False)


def round_name(cfg: dict) -> str:
    """``round-RR`` of the config's round."""
    return f"round-{int(cfg['round']):02d}"


def kind_of(cfg: dict, temperature_K: float) -> str:
    """The record kind of a selected configuration: ``alRR-mdTK`` (e.g. ``al00-md300K``)."""
    return f"al{int(cfg['round']):02d}-md{temperature_K:g}K"


def selection_path(cfg: dict) -> Path:
    """``DATA/active-learning/round-RR.xyz``."""
    return resolve(cfg["data"]) / ACTIVE_LEARNING_DIR / f"{round_name(cfg)}.xyz"


# ---------------------------------------------------------------------- the data rules
def composition(smiles: str) -> list[int]:
    """The sorted atomic numbers of a SMILES with its hydrogens (RDKit)."""
    from rdkit import Chem

    return sorted(a.GetAtomicNum() for a in Chem.AddHs(Chem.MolFromSmiles(smiles)).GetAtoms())


def allowed_molecules(cfg: dict) -> tuple[dict[str, dict], dict[str, str]]:
    """The molecules active learning may use (rows of ``molecules.csv`` by name: the train
    split, no graph of :func:`emlpack.qm.campaign.excluded_graphs`) and the excluded graphs
    with the reason (validation, test and IR molecules, QM7 rows 0-9)."""
    from emlpack.qm.campaign import excluded_graphs, graph_key

    data, smiles = resolve(cfg["data"]), resolve(cfg["smiles"])
    if not smiles.is_file():
        raise InputError(f"{smiles}: no such file (the QM7 SMILES whose rows 0-9 are never"
                         " labeled; config entry smiles)")
    banned = excluded_graphs(data, smiles)
    rows = read_molecule_table(data)
    allowed = {m["name"]: m for m in rows
               if m["split"] == "train" and graph_key(m["smiles"]) not in banned}
    return allowed, banned


def check_molecule(name: str, numbers: np.ndarray, allowed: dict[str, dict],
                   banned: dict[str, str], rows: dict[str, dict], where: str) -> None:
    """Refuse a configuration of a molecule that is not a training molecule (by split and by
    graph), or whose atoms are not the molecule's."""
    from emlpack.qm.campaign import graph_key

    if name not in allowed:
        row = rows.get(name)
        why = ("not in molecules.csv" if row is None else
               banned.get(graph_key(row["smiles"]), f"a {row['split']} molecule"))
        raise InputError(f"{where}: {name} is excluded ({why}): active learning uses"
                         " training molecules only")
    if sorted(np.asarray(numbers).tolist()) != composition(allowed[name]["smiles"]):
        raise InputError(f"{where}: its atoms are not those of {name}"
                         f" ({allowed[name]['smiles']})")


# ---------------------------------------------------------------------- explore
@dataclass(frozen=True)
class Trajectory:
    """One exploration run: molecule, temperature (K), index, MD seed, field (V/Å), folder."""

    molecule: str
    smiles: str
    temperature_K: float
    index: int
    seed: int
    field: tuple[float, float, float]
    path: Path


def plan(cfg: dict, allowed: dict[str, dict], banned: dict[str, str]) -> list[Trajectory]:
    """The exploration's trajectories: ``explore.molecule_list``, else a seeded sample of
    ``explore.molecules`` training molecules with a prepared geometry; per molecule,
    temperature and index a field and an MD seed from the random stream
    :func:`emlpack.qm.recipe.sample_rng` (independent of the order and the other runs)."""
    from emlpack.qm.recipe import sample_rng
    from emlpack.qm.sampling import random_field

    e = cfg["explore"]
    prepared = resolve(cfg["data"]) / "prepared"
    if e.get("molecule_list"):
        rows = {m["name"]: m for m in read_molecule_table(resolve(cfg["data"]))}
        names = [str(n) for n in e["molecule_list"]]
        for name in names:
            if name not in allowed:
                check_molecule(name, np.zeros(0), allowed, banned, rows, "explore.molecule_list")
            if not (prepared / f"{name}.npz").is_file():
                raise InputError(f"explore.molecule_list: {name} has no prepared geometry"
                                 f" ({prepared / name}.npz)")
    else:
        pool = [n for n in allowed if (prepared / f"{n}.npz").is_file()]
        rng = np.random.default_rng(int(e["seed"]))
        names = [pool[k] for k in rng.permutation(len(pool))]
        names = names[: e["molecules"]] if e.get("molecules") else names
    out = []
    base = resolve(cfg["workdir"]) / round_name(cfg)
    for name in names:
        for t in e["temperatures"]:
            for k in range(int(e["trajectories"])):
                rng = sample_rng(int(e["seed"]), name, f"md{float(t):g}K", k)
                field = random_field(rng, float(e["field_max_au"]),
                                     str(e.get("field_distribution", "ball")))
                out.append(Trajectory(name, allowed[name]["smiles"], float(t), k,
                                      int(rng.integers(2**31)), tuple(map(float, field)),
                                      base / name / f"T{float(t):g}-{k}"))
    return out


def start_structure(data: Path, name: str) -> Structure:
    """The campaign's prepared geometry of ``name`` (``DATA/prepared/NAME.npz``, the
    cheap-level optimum) with guessed electron pairs (run_md relaxes them at step 0)."""
    from ase import Atoms

    from emlpack.pairs.guess import guess_pairs
    from emlpack.structure import Structure

    with np.load(data / "prepared" / f"{name}.npz") as d:
        numbers, positions = d["numbers"].astype(int), d["positions"].astype(float)
    pairs = guess_pairs(Atoms(numbers=numbers, positions=positions))
    return Structure(numbers=numbers, positions=positions, pairs=pairs, source=name)


def judge_frames(ensemble: ModelEnsemble, frames: list[Structure], relax: str) -> list[dict]:
    """Every member on every frame (:class:`EMLPCalculator` over the ensemble, each member's
    pairs relaxed by MD's warm-start solver, carried from the previous frame; from the frame's
    pairs at the first frame and after a frame where a member failed). Per frame: ``step``,
    ``time_fs``, the spreads of the members whose relaxation succeeded
    (:func:`~emlpack.calculators.calibration.result_spread`: ``energy_spread`` eV/atom,
    ``force_spread`` eV/Å, ``pair_spread`` Å; None with fewer than
    :data:`~emlpack.calculators.ensemble.MIN_SOUND_MEMBERS` of them), ``n_failed`` and
    ``failed`` (the members whose pair relaxation failed, with the reasons) and ``bonding``
    (the bonds broken or formed since the first frame, :func:`emlpack.bonding.bonding_changes`).
    """
    from ase.calculators.calculator import CalculationFailed

    from emlpack.bonding import bonding_changes
    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.calculators.calibration import result_spread
    from emlpack.calculators.ensemble import MIN_SOUND_MEMBERS
    from emlpack.io.ase_convert import PAIRS_KEY, structure_to_atoms
    from emlpack.pairs.solvers import md_solver

    calc = EMLPCalculator(ensemble, check_bonding=False, pair_solver=md_solver(relax),
                          failed_members="drop")
    none = {"energy_spread": None, "force_spread": None, "pair_spread": None}
    rows, fresh = [], True
    calculator_log = logging.getLogger("emlpack.calculators.ase")
    level = calculator_log.level
    calculator_log.setLevel(logging.ERROR)  # spread warnings are this loop's measurements
    try:
        for f in frames:
            if calc.dropped:  # every member is judged at every frame: start them afresh
                calc.reset()
                fresh = True
            atoms = structure_to_atoms(f)
            if not fresh:
                atoms.info.pop(PAIRS_KEY)  # each member from its own pairs of the last frame
            atoms.calc = calc
            row: dict = {"step": int(f.info["step"]), "time_fs": float(f.info["time"])}
            try:
                atoms.get_potential_energy()
                failed = {k: str(reason) for k, reason in calc.dropped.items()}
                sound = len(ensemble) - len(failed) >= MIN_SOUND_MEMBERS
                row.update(result_spread(calc.results, len(atoms)) if sound else none)
                fresh = False
            except CalculationFailed as exc:  # every member failed
                failed = {k: str(exc) for k in range(len(ensemble))}
                row.update(none)
                calc.reset()
                fresh = True
            row["n_failed"] = len(failed)
            row["failed"] = "; ".join(f"member {k}: {why}" for k, why in failed.items())[:300]
            row["bonding"] = bonding_changes(f.numbers, frames[0].positions, f.positions)
            rows.append(row)
    finally:
        calculator_log.setLevel(level)
    return rows


def explore_one(cfg: dict, ensemble: ModelEnsemble, traj: Trajectory, log: Log = print,
                starts: dict[str, Structure] | None = None) -> dict:
    """One trajectory (or its record, when ``spread.json`` exists): the MD run (resumed from
    its checkpoint), its outcome (a watchdog stop, the watchdog's events), the judged frames
    and the measured cost; written to ``spread.json``. ``starts``: the start structures by
    molecule, filled as they are made (one pair guess per molecule)."""
    from ase.calculators.calculator import CalculationFailed

    from emlpack.dynamics.md import LOG, STOPPED, TRAJECTORY, MDWatchdogError, run_md
    from emlpack.io.extxyz import read_structures
    from emlpack.units import FIELD_AU_IN_V_PER_A

    target = traj.path / SPREAD_FILE
    if target.exists():
        return json.loads(target.read_text())
    e = cfg["explore"]
    steps = int(round(float(e["time_fs"]) / float(e["dt_fs"])))
    every = int(e["evaluate_every"])
    starts = {} if starts is None else starts
    if traj.molecule not in starts:
        starts[traj.molecule] = start_structure(resolve(cfg["data"]), traj.molecule)
    start = starts[traj.molecule]
    stopped, events, md_s_per_step = None, [], None
    traj.path.mkdir(parents=True, exist_ok=True)
    md_log = logging.getLogger("emlpack.dynamics.md")  # its lines and warnings: to md.log
    handler = logging.FileHandler(traj.path / LOG)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    md_log.addHandler(handler)
    md_level = md_log.level
    md_log.setLevel(logging.INFO)
    resumed = 0  # a resumed run: the steps before are not this call's
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        result = run_md(ensemble.members[int(cfg["driver"])], start, steps, traj.path,
                        dt_fs=float(e["dt_fs"]), temperature_K=traj.temperature_K,
                        ensemble="nvt", field=np.array(traj.field), seed=traj.seed,
                        relax=str(e["relax"]), record_every=every,
                        checkpoint_every=every * max(1, 100 // every), log_every=10 * every)
        md_s_per_step, resumed = result.seconds_per_step, result.resumed_from
        events = [{"step": int(v["step"]), "reason": str(v.get("reason", ""))[:300],
                   "fallback": v.get("fallback"), "ok": bool(v.get("ok", False))}
                  for v in result.events]
    except (MDWatchdogError, CalculationFailed) as exc:
        stop_file = traj.path / STOPPED
        stop = json.loads(stop_file.read_text()) if stop_file.exists() else {"step": 0}
        stopped = {"step": int(stop["step"]), "reason": str(exc)[:300]}
    finally:
        md_log.removeHandler(handler)
        md_log.setLevel(md_level)
        handler.close()
    md_wall, md_cpu = time.perf_counter() - t0, time.process_time() - c0
    frames_file = traj.path / TRAJECTORY
    frames = read_structures(frames_file) if frames_file.exists() else []
    done_steps = int(frames[-1].info["step"]) if frames else 0
    if md_s_per_step is None:
        md_s_per_step = md_wall / max(done_steps, 1)
    md_cpu_per_step = md_cpu / (done_steps - resumed) if done_steps > resumed else None
    t0, c0 = time.perf_counter(), time.process_time()
    rows = judge_frames(ensemble, frames, str(e["relax"])) if frames else []
    judge_wall, judge_cpu = time.perf_counter() - t0, time.process_time() - c0
    record = {
        "molecule": traj.molecule, "smiles": traj.smiles, "temperature_K": traj.temperature_K,
        "index": traj.index, "seed": traj.seed, "field_V_per_A": list(traj.field),
        "field_au": float(np.linalg.norm(traj.field)) / FIELD_AU_IN_V_PER_A,
        "model": str(cfg["model"]), "driver": int(cfg["driver"]), "steps": steps,
        "dt_fs": float(e["dt_fs"]), "evaluate_every": every, "relax": str(e["relax"]),
        "stopped": stopped, "events": events, "md_seconds_per_step": md_s_per_step,
        # CPU seconds of this process per step it ran (None when it resumed a finished run),
        # which a machine shared with other jobs does not inflate as it does the wall time
        "md_cpu_seconds_per_step": md_cpu_per_step,
        "judge_seconds_per_frame": judge_wall / max(len(rows), 1),
        "judge_cpu_seconds_per_frame": judge_cpu / max(len(rows), 1),
        "path": str(traj.path.relative_to(resolve(cfg["workdir"]))), "frames": rows,
    }
    write_json_atomic(target, record)
    log(f"explore: {traj.molecule} {traj.temperature_K:g} K #{traj.index}:"
        f" {len(rows)} frames, "
        + (f"stopped at step {stopped['step']}" if stopped else f"{steps} steps")
        + (f", {md_cpu_per_step:.3f} CPU s per step" if md_cpu_per_step else "")
        + f", {record['judge_cpu_seconds_per_frame']:.2f} CPU s per judged frame")
    return record


def stage_explore(cfg: dict, log: Log = print, commit: bool = False) -> list[dict]:
    """Every planned trajectory (finished ones read back)."""
    from emlpack.calculators.ensemble import as_ensemble
    from emlpack.progress import progress

    trajectories = plan(cfg, *allowed_molecules(cfg))
    ensemble = as_ensemble(cfg["model"])
    if int(cfg["driver"]) >= len(ensemble):
        raise InputError(f"driver {cfg['driver']}: the ensemble has {len(ensemble)} members")
    log(f"explore: {len(trajectories)} trajectories of"
        f" {len({t.molecule for t in trajectories})} training molecules, member"
        f" {cfg['driver']} of {cfg['model']} driving -> {resolve(cfg['workdir'])}")
    starts: dict[str, Structure] = {}
    return [explore_one(cfg, ensemble, t, log, starts)
            for t in progress(trajectories, desc="explore", unit="trajectory",
                              enabled=bool(cfg.get("progress", True)))]


def explored(trajectories: list[Trajectory]) -> list[dict]:
    """The records of the ``trajectories`` that are done (``spread.json``)."""
    return [json.loads((t.path / SPREAD_FILE).read_text()) for t in trajectories
            if (t.path / SPREAD_FILE).exists()]


# ---------------------------------------------------------------------- select
def thresholds(select: dict, ensemble: ModelEnsemble | None) -> dict:
    """The trust levels ``{"forces": [lower, upper] (eV/Å), "pairs": [lower, upper] (Å),
    "basis": ...}``: numbers as given; ``calibrated`` the ensemble's calibrated force
    threshold (:attr:`ModelEnsemble.spread_thresholds`: a quantile of the spreads on held-out
    molecules), ``calibrated-median`` the median spread of that calibration, scaled the same
    way (:meth:`SpreadThresholds.calibrated`)."""
    from emlpack.calculators.ensemble import SpreadThresholds

    levels = {"forces": [], "pairs": []}
    basis = {}
    calibrated = ensemble.spread_thresholds if ensemble is not None else None
    for name in ("forces", "pairs"):
        for key in ("lower", "upper"):
            spec = select[name][key]
            if spec not in CALIBRATED:
                levels[name].append(float(spec))
                basis[f"{name}.{key}"] = "given"
                continue
            if calibrated is None or calibrated.basis == "heuristic":
                raise InputError(f"select.{name}.{key}: {spec!r} needs an ensemble whose"
                                 " members carry a spread calibration; give a number (eV/Å)")
            cal = ensemble.members[0].spread_calibration
            if spec == "calibrated":
                levels[name].append(calibrated.forces)
            else:
                median = dict(cal, forces_eV_per_A=cal["median"]["force_spread"],
                              energy_eV_per_atom=cal["median"]["energy_spread"])
                levels[name].append(SpreadThresholds.calibrated(median, len(ensemble)).forces)
            what = ("the median spread" if spec == "calibrated-median" else
                    "the warning threshold")
            basis[f"{name}.{key}"] = f"{spec}: {what} of the calibration ({calibrated.basis})"
        if levels[name][0] >= levels[name][1]:
            raise InputError(f"select.{name}: lower {levels[name][0]:.4g} must be below upper"
                             f" {levels[name][1]:.4g}")
    return {**levels, "basis": basis}


def ensemble_for(cfg: dict) -> ModelEnsemble | None:
    """The ensemble when a threshold is ``calibrated`` (its calibration), else None."""
    from emlpack.calculators.ensemble import as_ensemble

    uses = any(cfg["select"][n][k] in CALIBRATED for n in ("forces", "pairs")
               for k in ("lower", "upper"))
    return as_ensemble(cfg["model"]) if uses else None


def classify(frame: dict, th: dict) -> str:
    """One of :data:`CLASSES`: ``failed`` when a spread reaches its upper level (or too few
    members relaxed their pairs to have one), ``candidate`` when a spread reaches its lower
    level or a member failed to relax the pairs, else ``accurate``."""
    force, pair = frame["force_spread"], frame["pair_spread"]
    if force is None or force >= th["forces"][1] or pair >= th["pairs"][1]:
        return "failed"
    if frame["n_failed"] or force >= th["forces"][0] or pair >= th["pairs"][0]:
        return "candidate"
    return "accurate"


def failure_points(record: dict) -> list[tuple[int, str, str]]:
    """``(step, reason, detail)`` of a trajectory's failures: the watchdog's stop, the first
    frame whose bonding changed, each step with a watchdog event (once)."""
    out = []
    if record["stopped"]:
        out.append((int(record["stopped"]["step"]), "watchdog stop", record["stopped"]["reason"]))
    changed = next((f for f in record["frames"] if f["bonding"]), None)
    if changed is not None:
        out.append((int(changed["step"]), "bonding change", changed["bonding"][0]))
    seen = set()
    for ev in record["events"]:
        if ev["step"] not in seen:
            seen.add(ev["step"])
            out.append((int(ev["step"]), "watchdog event", ev["reason"]))
    return out


def trajectory_candidates(record: dict, th: dict, failure_frames: int = 1) -> list[dict]:
    """A trajectory's candidate frames, one entry per frame with its first reason of
    :data:`REASONS`: the ``failure_frames`` frames just before each failure
    (:func:`failure_points`) and the frames classified ``candidate``, all before the first
    stop or bonding change (a frame after a bonding change is another molecule, possibly a
    held-out one; a failure after it is its consequence). Each: ``frame`` (the judged row),
    ``reason``, ``detail`` and ``score`` (the larger of the spreads over their upper levels;
    0 when unknown)."""
    points = failure_points(record)
    ends = [step for step, reason, _ in points if reason != "watchdog event"]
    limit = min(ends) if ends else float("inf")
    usable = [f for f in record["frames"] if f["step"] < limit]
    found: dict[int, dict] = {}

    def add(frame: dict, reason: str, detail: str) -> None:
        step = int(frame["step"])
        if step in found and REASONS.index(found[step]["reason"]) <= REASONS.index(reason):
            return
        score = 0.0 if frame["force_spread"] is None else max(
            frame["force_spread"] / th["forces"][1], frame["pair_spread"] / th["pairs"][1])
        found[step] = {"frame": frame, "reason": reason, "detail": detail, "score": score}

    for step, reason, detail in points:
        if step > limit:
            continue
        before = [f for f in usable if f["step"] < step]
        for f in before[len(before) - failure_frames:] if failure_frames else []:
            add(f, reason, detail)
    for f in usable:
        if classify(f, th) == "candidate":
            spread = (f"force spread {f['force_spread']:.3f} eV/Å, pair spread"
                      f" {f['pair_spread']:.4f} Å")
            if f["n_failed"]:
                add(f, "member failure", f"{f['failed']} ({spread} of the others)")
            else:
                add(f, "spread", spread)
    return sorted(found.values(), key=lambda c: c["frame"]["step"])


def deduplicate(candidates: list[dict], max_per_trajectory: int,
                min_spacing_fs: float) -> list[dict]:
    """At most ``max_per_trajectory`` of one trajectory's candidates, pairwise at least
    ``min_spacing_fs`` apart in time: failures first (:data:`REASONS` order), then the
    largest score, then the earliest; returned in that order (their rank)."""
    order = sorted(candidates, key=lambda c: (REASONS.index(c["reason"]), -c["score"],
                                              c["frame"]["step"]))
    chosen: list[dict] = []
    for c in order:
        if len(chosen) >= max_per_trajectory:
            break
        t = c["frame"]["time_fs"]
        if all(abs(t - x["frame"]["time_fs"]) >= min_spacing_fs for x in chosen):
            chosen.append(c)
    return chosen


def apply_budget(ranked: list[list[dict]], budget: int) -> list[tuple[int, dict]]:
    """Round-robin over the trajectories' ranked candidates (every trajectory's first, then
    every second, ...; within a round failures first, then the largest score) until
    ``budget``: ``(trajectory index, candidate)`` pairs."""
    pool = [(rank, REASONS.index(c["reason"]), -c["score"], k, c)
            for k, cands in enumerate(ranked) for rank, c in enumerate(cands)]
    pool.sort(key=lambda item: item[:4])
    return [(k, c) for *_, k, c in pool[:budget]]


def select(records: list[dict], th: dict, sel: dict) -> tuple[list[tuple[int, dict]], dict]:
    """The selection of ``records`` (trajectory records of ``spread.json``) and its counts:
    frames by class, candidates and selected configurations by reason."""
    ranked, counts = [], {c: 0 for c in CLASSES}
    candidates = {r: 0 for r in REASONS}
    for rec in records:
        for f in rec["frames"]:
            counts[classify(f, th)] += 1
        cands = trajectory_candidates(rec, th, int(sel["failure_frames"]))
        for c in cands:
            candidates[c["reason"]] += 1
        ranked.append(deduplicate(cands, int(sel["max_per_trajectory"]),
                                  float(sel["min_spacing_fs"])))
    chosen = apply_budget(ranked, int(sel["budget"]))
    selected = {r: sum(1 for _, c in chosen if c["reason"] == r) for r in REASONS}
    return chosen, {"frames": counts, "candidates": candidates, "selected": selected,
                    "after_deduplication": sum(len(r) for r in ranked)}


def _text(value: str, limit: int = 200) -> str:
    """A one-line provenance text for an extxyz comment line."""
    return " ".join(str(value).replace('"', "'").split())[:limit]


def stage_select(cfg: dict, log: Log = print, commit: bool = False) -> Path:
    """Write the round's selection (refusing to replace one) and its JSON beside it."""
    from emlpack.dynamics.md import TRAJECTORY
    from emlpack.io.extxyz import read_structures, write_structures

    out = selection_path(cfg)
    if out.exists():
        raise InputError(f"{out} exists: a selection is never rewritten (set"
                         f" round={cfg['round'] + 1} for a new one)")
    allowed, banned = allowed_molecules(cfg)
    rows = {m["name"]: m for m in read_molecule_table(resolve(cfg["data"]))}
    records = explored(plan(cfg, allowed, banned))
    if not records:
        raise InputError(f"no explored trajectory under {resolve(cfg['workdir'])}/"
                         f"{round_name(cfg)} (run the explore stage first)")
    for rec in records:  # training molecules only, by split and by graph
        if rec["molecule"] not in allowed:
            check_molecule(rec["molecule"], np.zeros(0), allowed, banned, rows, rec["path"])
    th = thresholds(cfg["select"], ensemble_for(cfg))
    chosen, counts = select(records, th, cfg["select"])
    workdir = resolve(cfg["workdir"])
    frames_of: dict[int, dict[int, object]] = {}
    structures, index = [], {}
    for k, c in sorted(chosen, key=lambda kc: (kc[0], kc[1]["frame"]["step"])):
        rec = records[k]
        if k not in frames_of:
            frames_of[k] = {int(s.info["step"]): s
                            for s in read_structures(workdir / rec["path"] / TRAJECTORY)}
        if c["frame"]["bonding"]:  # trajectory_candidates never selects one: a guard
            raise InputError(f"{rec['path']} step {c['frame']['step']}: bonding changed")
        s = frames_of[k][int(c["frame"]["step"])]
        check_molecule(rec["molecule"], s.numbers, allowed, banned, rows,
                       f"{rec['path']} step {c['frame']['step']}")
        kind = kind_of(cfg, rec["temperature_K"])
        n = index[(rec["molecule"], kind)] = index.get((rec["molecule"], kind), -1) + 1
        f = c["frame"]
        info = {"key": f"{rec['molecule']}/{kind}/{n:04d}", "molecule_id": rec["molecule"],
                "kind": kind, "reason": c["reason"], "detail": _text(c["detail"]),
                "temperature_K": rec["temperature_K"], "time_fs": f["time_fs"],
                "step": f["step"], "trajectory": rec["path"], "md_seed": rec["seed"],
                "model": str(cfg["model"]), "driver": rec["driver"], "round": int(cfg["round"])}
        for key in ("force_spread", "pair_spread", "energy_spread"):
            info[key] = float("nan") if f[key] is None else float(f[key])
        structures.append(s.copy(energy=None, forces=None, pair_forces=None, info=info))
    summary = {
        "round": int(cfg["round"]),
        "written": f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC",
        "model": str(cfg["model"]), "driver": int(cfg["driver"]),
        "thresholds": th, "explore": cfg["explore"], "select": cfg["select"],
        "trajectories": len(records), "stopped": sum(1 for r in records if r["stopped"]),
        "bonding_changed": sum(1 for r in records if any(f["bonding"] for f in r["frames"])),
        **counts, "configurations": len(structures),
        "molecules": len({s.info["molecule_id"] for s in structures}),
    }
    write_json_atomic(out.with_suffix(".json"), summary)
    write_structures(out, structures)  # atomic; last: the selection exists once complete
    log(f"select: {len(structures)} configurations of {summary['molecules']} molecules from"
        f" {len(records)} trajectories -> {out} (by reason: "
        + ", ".join(f"{r} {n}" for r, n in counts["selected"].items()) + ")")
    if commit:
        from emlpack.commits import git_commit

        git_commit([out, out.with_suffix(".json")], f"active learning: selection {out.stem}")
    return out


# ---------------------------------------------------------------------- label
def selection_files(cfg: dict) -> list[Path]:
    """Every round's selection of the data set, in order."""
    return sorted((resolve(cfg["data"]) / ACTIVE_LEARNING_DIR).glob("round-[0-9][0-9].xyz"))


def selection_configurations(cfg: dict, files: list[Path]) -> list[Configuration]:
    """The configurations to label of the selection ``files``, each checked: a training
    molecule (split and graph), the molecule's atoms, a key ``MOLECULE/alRR-.../NNNN``."""
    from emlpack.io.extxyz import read_structures
    from emlpack.qm.recipe import Configuration

    allowed, banned = allowed_molecules(cfg)
    rows = {m["name"]: m for m in read_molecule_table(resolve(cfg["data"]))}
    out = []
    for path in files:
        for k, s in enumerate(read_structures(path)):
            where = f"{path}, frame {k}"
            key, name, kind = (str(s.info.get(x, "")) for x in ("key", "molecule_id", "kind"))
            if key.split("/")[:2] != [name, kind] or not kind.startswith("al"):
                raise InputError(f"{where}: key {key!r} must be MOLECULE/KIND/NNNN of its"
                                 f" molecule_id {name!r} and an active-learning kind {kind!r}")
            check_molecule(name, s.numbers, allowed, banned, rows, where)
            out.append(Configuration(key, name, kind, s.numbers, s.positions, s.field,
                                     s.charge))
    return out


def stage_label(cfg: dict, log: Log = print, commit: bool = False) -> dict:
    """Label every selection's configurations into the data set's active-learning part."""
    from emlpack.qm.campaign import label_part

    files = selection_files(cfg)
    if not files:
        raise InputError(f"no selection in {resolve(cfg['data']) / ACTIVE_LEARNING_DIR} (run"
                         " the select stage first)")
    configs = selection_configurations(cfg, files)
    lab = cfg["label"]
    log(f"label: {len(configs)} configurations of {len(files)} selections"
        f" ({', '.join(p.name for p in files)})")
    out = label_part(resolve(cfg["data"]), configs, ACTIVE_LEARNING_PART,
                     source=", ".join(f"{ACTIVE_LEARNING_DIR}/{p.name}" for p in files),
                     workers=int(lab["workers"]), threads=lab.get("threads"),
                     hours=lab.get("hours"), shard_minutes=float(lab["shard_minutes"]),
                     commit=commit, commit_paths=[resolve(cfg["data"]) / ACTIVE_LEARNING_DIR],
                     progress=bool(cfg.get("progress", True)))
    shards = ", ".join(Path(p).name for p in out["shards"]) or "none"
    log(f"label: {out['new_records']} new, {out['new_failures']} failed,"
        f" {out['skipped_done']} done before; new shards: {shards}")
    return out


# ---------------------------------------------------------------------- status
def stage_status(cfg: dict, log: Log = print, commit: bool = False) -> dict:
    """Print (and return) what is done and what is left, with the measured costs."""
    trajectories = plan(cfg, *allowed_molecules(cfg))
    records = explored(trajectories)
    started = sum(1 for t in trajectories if t.path.exists())
    e = cfg["explore"]
    steps = float(e["time_fs"]) / float(e["dt_fs"])
    info: dict = {"trajectories": len(trajectories), "done": len(records), "started": started}
    log(f"explore ({round_name(cfg)}): {len(records)} of {len(trajectories)} trajectories done"
        f" ({started - len(records)} started), "
        f"{sum(len(r['frames']) for r in records)} frames judged")
    if records:
        cost = {}
        for key in ("md_cpu_seconds_per_step", "md_seconds_per_step",
                    "judge_cpu_seconds_per_frame", "judge_seconds_per_frame"):
            values = [r[key] for r in records if r[key] is not None]
            cost[key] = float(np.median(values)) if values else None
        info.update(cost)

        def text(key: str, digits: int) -> str:
            return "n/a" if cost[key] is None else f"{cost[key]:.{digits}f}"

        per = ((cost["md_cpu_seconds_per_step"] or cost["md_seconds_per_step"]) * steps
               + (cost["judge_cpu_seconds_per_frame"] or 0.0) * steps
               / int(e["evaluate_every"]))
        log(f"  cost (median of {len(records)} trajectories): MD"
            f" {text('md_cpu_seconds_per_step', 3)} CPU s per step"
            f" ({text('md_seconds_per_step', 3)} s wall), judging"
            f" {text('judge_cpu_seconds_per_frame', 2)} CPU s per frame (every member;"
            f" {text('judge_seconds_per_frame', 2)} s wall): about"
            f" {per * (len(trajectories) - len(records)) / 3600:.1f} CPU hours left")
        log(f"  {sum(1 for r in records if r['stopped'])} stopped by the watchdog,"
            f" {sum(1 for r in records if any(f['bonding'] for f in r['frames']))} with"
            " bonding changed")
        try:
            th = thresholds(cfg["select"], ensemble_for(cfg))
            _, counts = select(records, th, cfg["select"])
            info["selection_preview"] = counts
            log(f"  thresholds: forces {th['forces'][0]:.3f}-{th['forces'][1]:.3f} eV/Å, pairs"
                f" {th['pairs'][0]:.3f}-{th['pairs'][1]:.3f} Å; frames "
                + ", ".join(f"{k} {v}" for k, v in counts["frames"].items())
                + "; candidates " + ", ".join(f"{k} {v}" for k, v in counts["candidates"].items())
                + f"; {counts['after_deduplication']} after deduplication, selected now"
                f" {sum(counts['selected'].values())} (budget {cfg['select']['budget']})")
        except InputError as exc:
            log(f"  selection preview: {exc}")
    files = selection_files(cfg)
    if files:
        configs = selection_configurations(cfg, files)
        data = resolve(cfg["data"])
        labeled = finished_keys(data, failures=False, part=ACTIVE_LEARNING_PART)
        done = finished_keys(data, failures=True, part=ACTIVE_LEARNING_PART)
        left = [c for c in configs if c.key not in done]
        info.update(selected=len(configs), labeled=sum(c.key in labeled for c in configs),
                    failed=sum(c.key in done and c.key not in labeled for c in configs),
                    left=len(left))
        log(f"label: {info['selected']} selected ({', '.join(p.name for p in files)}),"
            f" {info['labeled']} labeled, {info['failed']} failed, {info['left']} to do")
    else:
        log("label: no selection yet")
    return info


# ---------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("stage", choices=STAGES)
    p.add_argument("overrides", nargs="*", help="key=value overrides of the config (dots for"
                   " nesting, values parsed as YAML), e.g. explore.molecules=2")
    p.add_argument("--config", default=str(HERE / "active_learning.yaml"))
    p.add_argument("--commit", action="store_true",
                   help="select: commit the selection; label: commit every new shard with the"
                   " card and the selections")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    args = p.parse_args(argv)

    def log(message: str) -> None:
        print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {message}", flush=True)

    stage = {"explore": stage_explore, "select": stage_select, "label": stage_label,
             "status": stage_status}[args.stage]
    try:
        cfg = load_config(args.config, args.overrides + (["progress=false"] if args.quiet
                                                         else []))
        stage(cfg, log, args.commit)
    except EmlpackError as exc:
        print(f"active_learning.py {args.stage}: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
