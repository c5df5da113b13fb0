"""The beta-glycine study (issue 7): DFT data -> eMLP -> the paper's table, DFT vs eMLP.

Stages (each resumable; labels are committed one record at a time to an HDF5 store, so a
killed run loses at most the calculation in flight)::

    optimize   DFT optimisation of positions and cell (ASE BFGS, P2_1 kept), every step a
               stored stress-set record -> WORKDIR/optimized.xyz, the reference structure
               of the finite differences and of the samples (config `optimization`)
    label      DFT reference-tensor calculations first (19: unperturbed + 6 fields + 12
               strains), then the training configurations of every round whose samples can be
               generated (round 0: random displacements; round r>0 needs `sample`), in
               interleaved field/stress order, until --until HH:MM (UTC) or the end
    reference  finite-difference DFT tensors from the 19 calculations -> WORKDIR/dft.json
    train      the eMLP ensemble (Ewald, stress in the loss, constant reference) on the store:
               ``training.members`` models (seeds training.seed + k) of ``training.family``,
               from scratch or fine-tuned from ``training.init_from``, each in
               WORKDIR/model_r<round>/<name>/seed<seed>; a finished member is not retrained
    sample     next round's samples from member 0's BO cell Hessian (600 K)
    emlp       per member: tensors at the DFT geometry, BO cell optimisation (convergence
               recorded, a non-converged one warned about), lattice and clamped- and
               relaxed-ion tensors at its optimum (response.py) -> WORKDIR/emlp.json
    curve      learning curve: one model on the first N configurations (a fixed, seeded
               order) for each N of ``learning_curve``, its eMLP values
    table      results.json + results.md (DFT vs the ensemble's mean ± spread vs deviation,
               targets within issue 52's tolerances, the learning curve, the paper's numbers)
    all        optimize, label, reference, train, emlp, curve, table

Usage (from the project root)::

    python examples/beta_glycine/run_study.py label --until 05:55   # CP2K, in the background
    python examples/beta_glycine/run_study.py reference train emlp table
    python examples/beta_glycine/run_study.py all --config my.yaml workdir=/tmp/x

``key=value`` arguments override the YAML config (dots for nesting, values parsed as YAML).
The labeler is CP2K (:class:`emlpack.qm.cp2k.CP2KLabeler`, settings under ``cp2k:``);
:func:`run` accepts any labeler obeying the protocol (tests use an eMLP).
"""

from __future__ import annotations

import argparse
import copy
import datetime as dt
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from emlpack.data.store import DatasetStore
from emlpack.io.extxyz import read_structures
from emlpack.progress import progress
from emlpack.properties.fd_reference import (
    CrystalReferenceError,
    FDSettings,
    ReferenceTensors,
    reference_tasks,
    reference_tensors,
)
from emlpack.qm.crystal_sampling import LabelTask, crystal_tasks
from emlpack.structure import Structure
from emlpack.units import (
    A_PER_V_IN_PM_PER_V,
    E_PER_A2_IN_C_PER_M2,
    EV_PER_A3_IN_GPA,
    FIELD_AU_IN_V_PER_A,
)

HERE = Path(__file__).resolve().parent
STAGES = ("optimize", "label", "reference", "train", "sample", "emlp", "curve", "table")

#: the paper's numbers (emlp-paper.tex, tables tab:beta_glycine_lattice and
#: tab:beta_glycine_response_properties): PBE-D3(BJ), Quantum ESPRESSO, 3x3x3 k-points, and the
#: paper's eMLP; stiffness, e and d are the paper's (relaxed-ion) values
PAPER = {
    "pbe": {"a": 5.08, "b": 6.24, "c": 5.40, "beta": 112.6, "volume": 158.05,
            "eps11": 2.65, "eps22": 2.19, "eps33": 2.52,
            "C11": 62.4, "C22": 22.2, "C33": 77.6, "C44": 8.5, "C55": 17.5, "C66": 3.8,
            "e14": -0.11, "e16": 0.24, "e21": 0.04, "e22": -0.16, "e23": 0.12, "e25": -0.08,
            "e34": 0.01, "e36": -0.05,
            "d14": -25.0, "d16": 71.6, "d21": 1.0, "d22": -9.6, "d23": 1.9, "d25": -4.3,
            "d34": 3.2, "d36": -15.1},
    "emlp": {"a": 5.08, "b": 6.25, "c": 5.40, "beta": 112.4, "volume": 158.41,
             "eps11": 2.68, "eps22": 2.21, "eps33": 2.55,
             "C11": 65.0, "C22": 31.4, "C33": 84.1, "C44": 9.2, "C55": 18.9, "C66": 5.7,
             "e14": -0.11, "e16": 0.24, "e21": 0.04, "e22": -0.03, "e23": 0.10, "e25": -0.05,
             "e34": 0.02, "e36": -0.05,
             "d14": -19.8, "d16": 46.5, "d21": 0.3, "d22": -1.8, "d23": 1.2, "d25": -1.3,
             "d34": 3.9, "d36": -9.9},
}
#: nonzero components for point group 2 with the two-fold axis along y (b)
PIEZO_KEYS = ("14", "16", "21", "22", "23", "25", "34", "36")
STIFF_KEYS = ("11", "22", "33", "44", "55", "66", "12", "13", "23", "15", "25", "35", "46")


# ---------------------------------------------------------------------- config
def load_config(path: str | Path, overrides: list[str] = ()) -> dict:
    """config.yaml with ``key=value`` overrides."""
    from emlpack.overrides import OverrideError, apply_overrides, load_yaml

    cfg = load_yaml(Path(path).read_text()) or {}
    try:
        apply_overrides(cfg, overrides)
    except OverrideError as exc:
        raise SystemExit(str(exc)) from None
    cfg.setdefault("workdir", "runs/beta_glycine")
    cfg.setdefault("molecule_id", "beta-glycine")
    cfg.setdefault("seed", 0)
    return cfg


class Study:
    """Paths and shared state of one study run (``cfg`` resolved, see config.yaml)."""

    def __init__(self, cfg: dict, labeler: Callable | None = None, log=print) -> None:
        self.cfg = cfg
        self.workdir = Path(cfg["workdir"])
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.log = log
        self._labeler = labeler
        #: called with the open store after each stored optimisation step (optimize_job.py:
        #: the finished steps become immutable shards of datasets/beta-glycine)
        self.on_stored: Callable | None = None
        self.input = read_structures(cfg["input"])[0].copy(
            energy=None, forces=None, stress=None, info={})
        r = cfg.get("reference", {})
        self.fd = FDSettings(field_step=float(r.get("field_step_au", 0.005)) * FIELD_AU_IN_V_PER_A,
                             strain_step=float(r.get("strain_step", 0.01)),
                             points=int(r.get("points", 2)))
        (self.workdir / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))

    @property
    def optimizing(self) -> bool:
        return bool(self.cfg.get("optimization", {}).get("enabled", False))

    @property
    def optimized_path(self) -> Path:
        return self.workdir / "optimized.xyz"

    @property
    def reference(self) -> Structure:
        """The structure of the finite differences and the samples: the DFT optimum when
        ``optimization.enabled`` (the `optimize` stage must have run), else the input."""
        if not self.optimizing:
            return self.input
        if not self.optimized_path.exists():
            raise SystemExit(f"{self.optimized_path}: no DFT-optimised structure yet (run the"
                             " optimize stage, or set optimization.enabled=false)")
        return read_structures(self.optimized_path)[0].copy(
            energy=None, forces=None, stress=None, pair_forces=None, info={})

    @property
    def fd_prefix(self) -> str:
        return "ref-opt" if self.optimizing else "ref"

    @property
    def store_path(self) -> Path:
        return self.workdir / "labels.h5"

    def shard_store(self, shard: int) -> Path:
        """Store written by labeling shard ``shard`` (one writer per store)."""
        return self.store_path if shard == 0 else self.workdir / f"labels.{shard}.h5"

    @property
    def dataset(self) -> Path | None:
        """The committed data set (``dataset`` of config.yaml: immutable shards written by
        campaign_job.py), read by every stage beside the working stores; None: none."""
        d = self.cfg.get("dataset")
        return Path(d) if d else None

    def stores(self) -> list[Path]:
        """The committed shards (``dataset``), then every labeling store of the run (the main
        one and the shards')."""
        from emlpack.data.shards import shard_paths

        shards = shard_paths(self.dataset) if self.dataset is not None else []
        return [*shards, *sorted(p for p in self.workdir.glob("labels*.h5") if p.is_file())]

    def records(self) -> list[Structure]:
        """Every labeled record, each key once (a record in a shard and in a working store:
        the shard's)."""
        out, seen = [], set()
        for path in self.stores():
            with DatasetStore(path, "r") as store:
                for s in store:
                    if s.info.get("key") not in seen:
                        seen.add(s.info.get("key"))
                        out.append(s)
        return out

    def failures(self) -> list[dict]:
        out = []
        for path in self.stores():
            with DatasetStore(path, "r") as store:
                out += store.failures()
        return out

    def done_keys(self, exclude: Path | None = None) -> set[str]:
        done: set[str] = set()
        for path in self.stores():
            if path != exclude:
                with DatasetStore(path, "r") as store:
                    done |= store.done_keys()
        return done

    def labeler(self) -> Callable:
        if self._labeler is None:
            from emlpack.qm.cp2k import CP2KLabeler, CP2KSettings

            self._labeler = CP2KLabeler(CP2KSettings(**self.cfg.get("cp2k", {})),
                                        workdir=self.workdir / "scratch")
        return self._labeler

    def level(self) -> str:
        lab = self.labeler()
        settings = getattr(lab, "settings", None)
        return settings.level() if settings is not None else getattr(lab, "level", "custom")

    def fd_tasks(self):
        return reference_tasks(self.reference, self.fd, prefix=self.fd_prefix)

    def round_tasks(self) -> list[LabelTask]:
        """Tasks of every round whose samples can be generated now, interleaved by set."""
        out = []
        for rnd in self.cfg.get("rounds", []):
            index = int(rnd["round"])
            hessian = None
            if rnd.get("hessian") == "model":
                path = self.workdir / f"hessian_r{index}.npy"
                if not path.exists():
                    continue  # `sample` has not run yet
                hessian = np.load(path)
            around = self.input if rnd.get("around") == "input" else self.reference
            tasks = crystal_tasks(
                around, {"field": rnd.get("field", 0), "stress": rnd.get("stress", 0)},
                seed=self.cfg["seed"], round_index=index, hessian=hessian,
                temperature=float(rnd.get("temperature", 600.0)),
                sigma=float(rnd.get("sigma", 0.05)),
                max_strain=float(rnd.get("max_strain", 0.02)),
                max_field_au=float(rnd.get("max_field_au", 0.01)),
                min_eigenvalue=rnd.get("min_eigenvalue"), molecule_id=self.cfg["molecule_id"],
                prefix=str(rnd.get("prefix", "")))
            field = [t for t in tasks if not t.stress]
            stress = [t for t in tasks if t.stress]
            for k in range(max(len(field), len(stress))):
                out += [lst[k] for lst in (field, stress) if k < len(lst)]
        return out


# ---------------------------------------------------------------------- stages
def stage_optimize(study: Study) -> dict | None:
    """DFT optimisation of positions and cell from the input (resumable: the stored steps are
    replayed) -> WORKDIR/optimized.xyz and optimization.json."""
    from emlpack.io.extxyz import write_structures
    from emlpack.qm.crystal_optimize import optimize_crystal

    o = study.cfg.get("optimization", {})
    if not study.optimizing:
        study.log("optimize: disabled (optimization.enabled: false), the input is the reference")
        return None
    settings = dict(study.cfg.get("cp2k", {}), **o.get("cp2k", {}))
    labeler = study._labeler
    if labeler is None:
        from emlpack.qm.cp2k import CP2KLabeler, CP2KSettings

        labeler = CP2KLabeler(CP2KSettings(**settings), workdir=study.workdir / "scratch_opt")
    start = study.input.copy(info={"molecule_id": study.cfg["molecule_id"]})
    t0 = time.perf_counter()
    res = optimize_crystal(labeler, start, fmax=float(o.get("fmax", 0.01)),
                           max_steps=int(o.get("max_steps", 100)),
                           symprec=o.get("symprec", 0.01), maxstep=float(o.get("maxstep", 0.1)),
                           store_path=study.store_path, prefix="opt", level=study.level(),
                           log=study.log, on_stored=study.on_stored)
    out = {"converged": res.converged, "steps": res.steps, "calculations": res.calculations,
           "max_force": res.max_force, "max_stress_GPa": res.max_stress_gpa,
           "time_s": time.perf_counter() - t0, "lattice_input": lattice(study.input.cell),
           "lattice": lattice(res.structure.cell), "history": res.history}
    _write_json(study.workdir / "optimization.json", out)
    if not res.converged:
        study.log(f"optimize: NOT converged after {res.steps} steps (max force"
                  f" {res.max_force:.4f} eV/Å); raise optimization.max_steps and re-run (the"
                  " stored steps are replayed, not recomputed)")
        return out
    write_structures(study.optimized_path, [res.structure])  # atomic
    study.log(f"optimize: converged in {res.steps} steps, lattice {out['lattice']}")
    return out


def stage_label(study: Study, until: dt.datetime | None = None,
                shard: tuple[int, int] = (0, 1), reference_only: bool = False) -> dict:
    """Label the FD reference calculations, then (unless ``reference_only``) the round
    samples, skipping stored keys.

    ``shard = (i, n)``: this process takes every n-th task starting at i and writes its own
    store (several single-process CP2K workers side by side); keys finished by any shard are
    skipped, re-checked before every calculation."""
    todo = [LabelTask(t.key, t.structure.copy(info={"key": t.key, "kind": t.kind,
                                                     "molecule_id": study.cfg["molecule_id"]},
                                               source=t.key), t.stress)
            for t in study.fd_tasks()]
    if not reference_only:
        todo += study.round_tasks()
    n_new = n_fail = 0
    index, n_shards = shard
    path = study.shard_store(index)
    with DatasetStore(path, "a") as store:
        done = store.done_keys() | study.done_keys(exclude=path)
        pending = [t for k, t in enumerate(todo) if t.key not in done and k % n_shards == index]
        study.log(f"label: {len(todo)} tasks, {len(done)} done, {len(pending)} to go in shard"
                  f" {index}/{n_shards} ({study.level()})")
        # a bar on stderr: rate and time left on a terminal, a line every tenth otherwise
        bar = progress(pending, desc="label", unit="calc",
                       enabled=bool(study.cfg.get("progress", True)))
        for t in bar:
            if until is not None and dt.datetime.now(dt.timezone.utc) >= until:
                study.log(f"label: stopping at {until:%H:%M} UTC")
                break
            if t.key in study.done_keys(exclude=path):
                continue
            t0 = time.perf_counter()
            try:
                out = study.labeler()(t.structure, stress=t.stress)
            except Exception as exc:  # recorded, not fatal: the store keeps the reason
                store.add_failures([{"key": t.key, "molecule_id": study.cfg["molecule_id"],
                                     "kind": t.structure.info.get("kind", ""),
                                     "reason": f"{type(exc).__name__}: {exc}"[:1000]}])
                n_fail += 1
                study.log(f"label: {t.key} FAILED: {exc}")
                continue
            wall = time.perf_counter() - t0
            out.info = {"key": t.key, "molecule_id": study.cfg["molecule_id"],
                        "kind": t.structure.info.get("kind", ""), "level": study.level(),
                        "wall_time": float(out.info.get("wall_time", wall))}
            store.append(out)
            n_new += 1
            study.log(f"label: {t.key} done in {wall:.1f} s")
            if study.on_stored is not None:
                study.on_stored(store)
        bar.close()
        n_total = len(store)
    return {"new": n_new, "failed": n_fail, "stored": n_total}


def stage_reference(study: Study) -> dict | None:
    """FD DFT tensors from the stored calculations -> WORKDIR/dft.json (None if incomplete)."""
    tasks = study.fd_tasks()
    labeled = {s.info["key"]: s for s in study.records()}
    try:
        tensors = reference_tensors(tasks, labeled, study.fd)
    except CrystalReferenceError as exc:
        study.log(f"reference: not yet possible: {exc}")
        return None
    out = tensors.as_dict()
    out["lattice"] = lattice(labeled[f"{study.fd_prefix}/zero"].cell)
    out["wall_time_s"] = [float(labeled[t.key].info.get("wall_time", np.nan)) for t in tasks]
    _write_json(study.workdir / "dft.json", out)
    study.log(f"reference: eps diag {np.diag(tensors.dielectric).round(3).tolist()}")
    return out


def _train_records(study: Study) -> list[Structure]:
    """The training records (optionally without the FD calculations or the field-set core
    forces), in the store's order."""
    t = study.cfg.get("training", {})
    use_fd = bool(t.get("use_reference_calcs", True))
    field_forces = bool(t.get("field_set_forces", True))
    keep = [s for s in study.records() if use_fd or not _is_fd(s)]
    for k, s in enumerate(keep):
        s.info = {k: v for k, v in s.info.items() if isinstance(v, (str, float))}
        if not field_forces and np.any(s.field):
            # CP2K 2023.1 double-counts Berry-phase field forces in small cells: train
            # the field set on energies and electron pairs only
            keep[k] = s.copy(forces=None)
    study.log(f"train: {len(keep)} labeled configurations (FD calculations included: {use_fd};"
              f" field-set core forces used: {field_forces})")
    return keep


def subset_order(keys: list[str], seed: int) -> list[int]:
    """The learning curve's fixed order of the records: by a seeded hash of each key, so the
    first N are the same records whatever order the stores list them in."""
    import hashlib

    return sorted(range(len(keys)), key=lambda k: hashlib.sha256(
        f"{seed}/{keys[k]}".encode()).hexdigest())


def _write_store(path: Path, records: list[Structure]) -> Path:
    tmp = path.with_suffix(".tmp.h5")
    tmp.unlink(missing_ok=True)
    with DatasetStore(tmp, "a") as dst:
        dst.append(records)
    os.replace(tmp, path)
    return path


def _round_dir(study: Study) -> Path:
    rounds = [int(r["round"]) for r in study.cfg.get("rounds", [])
              if r.get("hessian") != "model" or (study.workdir / f"hessian_r{r['round']}.npy")
              .exists()]
    return study.workdir / f"model_r{max(rounds, default=0)}"


def _family(study: Study) -> str:
    """The short-range family of the study's models: ``training.family``, else the
    fine-tune start's, else train.yaml's."""
    t = study.cfg.get("training", {})
    if t.get("family"):
        return str(t["family"])
    if t.get("init_from"):
        from emlpack.nn.checkpoint import read_checkpoint

        return read_checkpoint(_init_files(study)[0])["config"].get("family", "schnet")
    from emlpack.train.config import load_config as load_train_config

    return load_train_config(_resolve(t.get("config", HERE / "train.yaml")))["model"]["family"]


def _ensemble_dir(study: Study) -> Path:
    """The folder of the configured ensemble: ``model_r<round>/<name>``, the name
    ``training.name`` or the family, ``-ft`` appended for a fine-tune (``init_from``)."""
    t = study.cfg.get("training", {})
    name = t.get("name") or (_family(study) + ("-ft" if t.get("init_from") else ""))
    return _round_dir(study) / str(name)


def _seeds(study: Study) -> list[int]:
    """Training seeds of the members: ``training.seed`` (default the study's ``seed``) and
    the next ``training.members - 1`` integers."""
    t = study.cfg.get("training", {})
    base = int(t.get("seed", study.cfg["seed"]))
    n = int(t.get("members", 1))
    if n < 1:
        raise SystemExit(f"training.members must be >= 1, got {n}")
    return [base + k for k in range(n)]


def member_dirs(study: Study) -> list[Path]:
    return [_ensemble_dir(study) / f"seed{s}" for s in _seeds(study)]


def _init_files(study: Study) -> list[Path]:
    """The checkpoints of ``training.init_from`` (a checkpoint, a folder of them or a
    pretrained name such as mini-eqm7); member k starts from the (k mod n)-th."""
    from emlpack.pretrained import PretrainedError, resolve_model

    name = str(study.cfg["training"]["init_from"])
    target = next((p for p in (Path(name), HERE / name) if p.exists()), name)
    try:
        return resolve_model(target)[0]
    except PretrainedError as exc:
        raise SystemExit(f"training.init_from: {exc}") from None


def _train_model(study: Study, data: Path, out_dir: Path, seed: int, start: Path | None,
                 n_configurations: int) -> Path:
    """One model in ``out_dir`` (resumable: a folder with ``done.json`` is not trained
    again; one with a ``last.pt`` goes on from it). ``start``: the fine-tune's checkpoint
    (``training.init_weights``; the model section is the checkpoint's)."""
    from emlpack.nn.checkpoint import read_checkpoint
    from emlpack.nn.potential import ModelConfig
    from emlpack.train.config import load_config as load_train_config
    from emlpack.train.trainer import train

    done = out_dir / "done.json"
    if done.exists() and (out_dir / "best.pt").exists():
        info = json.loads(done.read_text())
        note = ("" if info.get("n_configurations") == n_configurations else
                f"; the data now hold {n_configurations} configurations: remove {out_dir} to"
                " retrain on them")
        study.log(f"train: {out_dir} finished ({info.get('n_configurations')} configurations,"
                  f" seed {info.get('seed')}), not retrained{note}")
        return out_dir / "best.pt"
    t = study.cfg.get("training", {})
    overrides = [f"data.path={data}", f"output.dir={out_dir}", "data.reference=constant",
                 "data.split=configuration"]
    if t.get("family"):
        overrides.append(f"model.family={t['family']}")
    overrides += [*t.get("overrides", []), f"training.seed={seed}"]
    if start is not None:
        overrides.append(f"training.init_weights={start}")
    cfg = load_train_config(_resolve(t.get("config", HERE / "train.yaml")), overrides)
    if start is not None:  # the fine-tune's architecture is its start's
        saved = ModelConfig.from_dict(read_checkpoint(start)["config"])
        if t.get("family") and saved.family != t["family"]:
            raise SystemExit(f"training.init_from={t['init_from']}: family {saved.family},"
                             f" not training.family={t['family']}")
        cfg["model"] = saved.to_dict()
    t0 = time.perf_counter()
    best = train(cfg)
    _write_json(done, {"best": str(best), "seed": seed, "n_configurations": n_configurations,
                       "init_weights": str(start) if start else None,
                       "family": cfg["model"]["family"], "time_s": time.perf_counter() - t0})
    study.log(f"train: best model {best}")
    return best


def stage_train(study: Study) -> list[Path]:
    """The ensemble (``training.members``, seeds ``training.seed`` + k), each member in
    ``model_r<round>/<name>/seed<seed>``; a finished member is not retrained."""
    dirs = member_dirs(study)
    records = _train_records(study)
    data = _write_store(study.workdir / "train_data.h5", records)
    starts = _init_files(study) if study.cfg.get("training", {}).get("init_from") else None
    return [_train_model(study, data, d, seed, starts[k % len(starts)] if starts else None,
                         len(records))
            for k, (d, seed) in enumerate(zip(dirs, _seeds(study), strict=True))]


def _model_path(study: Study) -> Path:
    """Member 0's model (the `sample` stage's)."""
    path = member_dirs(study)[0] / "best.pt"
    if not path.exists():
        raise SystemExit(f"{path}: no trained model (run the train stage)")
    return path


def learning_curve_sizes(study: Study, n_total: int) -> list[int]:
    """``learning_curve`` sizes below the data's size (the full set is the ensemble's
    member 0)."""
    return sorted({int(n) for n in study.cfg.get("learning_curve") or [] if int(n) < n_total})


def stage_curve(study: Study) -> dict | None:
    """The learning curve: one model (member 0's seed and start) on the first N records of a
    fixed, seeded order (:func:`subset_order`) for each N of ``learning_curve``, each model's
    eMLP tensors (:func:`emlp_model`) -> WORKDIR/learning_curve.json; the full data set is
    member 0 of the ensemble (the `train` and `emlp` stages)."""
    if not study.cfg.get("learning_curve"):
        study.log("curve: no learning_curve sizes configured")
        return None
    records = _train_records(study)
    sizes = learning_curve_sizes(study, len(records))
    order = subset_order([s.info["key"] for s in records], int(study.cfg["seed"]))
    seed = _seeds(study)[0]
    starts = _init_files(study) if study.cfg.get("training", {}).get("init_from") else None
    points = []
    for n in sizes:
        out_dir = _ensemble_dir(study) / f"curve-n{n}"
        out_dir.mkdir(parents=True, exist_ok=True)
        data = _write_store(out_dir / "train_data.h5", [records[k] for k in order[:n]])
        best = _train_model(study, data, out_dir, seed, starts[0] if starts else None, n)
        points.append({"n_configurations": n, **emlp_model(study, best)})
    full = member_dirs(study)[0] / "best.pt"
    if full.exists():
        points.append({"n_configurations": len(records), "all": True, **emlp_model(study, full)})
    out = {"seed": seed, "order_seed": int(study.cfg["seed"]), "points": points}
    _write_json(study.workdir / "learning_curve.json", out)
    return out


def stage_sample(study: Study) -> None:
    """Save the BO cell Hessian of the latest model at the input structure for the next
    model-Hessian round (whose samples `label` then generates)."""
    from emlpack.calculators.labeler import bo_cell_hessian
    from emlpack.nn.checkpoint import load_model

    pending = [int(r["round"]) for r in study.cfg.get("rounds", [])
               if r.get("hessian") == "model"
               and not (study.workdir / f"hessian_r{r['round']}.npy").exists()]
    if not pending:
        study.log("sample: no model-Hessian round pending")
        return
    model = load_model(_model_path(study))
    h = bo_cell_hessian(model, study.reference)
    path = study.workdir / f"hessian_r{min(pending)}.npy"
    np.save(path.with_suffix(".tmp.npy"), h)
    os.replace(path.with_suffix(".tmp.npy"), path)
    w = np.linalg.eigvalsh(h)
    study.log(f"sample: model Hessian saved to {path} (eigenvalues {w[:8].round(3).tolist()} ...)")


def lattice(cell: np.ndarray) -> dict:
    from ase.geometry import cell_to_cellpar

    a, b, c, alpha, beta, gamma = cell_to_cellpar(cell)
    return {"a": float(a), "b": float(b), "c": float(c), "alpha": float(alpha),
            "beta": float(beta), "gamma": float(gamma), "volume": float(abs(np.linalg.det(cell)))}


def emlp_model(study: Study, path: Path) -> dict:
    """One model's eMLP values: pairs relaxed at the DFT geometry and the tensors there, then
    the BO cell optimisation (``emlp`` settings) and the tensors at the model's own optimum
    (clamped and relaxed ions); a non-converged optimisation gives a warning. Cached in the
    model's folder (``emlp.json``) for the same weights, settings and DFT geometry."""
    import hashlib

    from emlpack.nn.checkpoint import load_model
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.optimize import optimize
    from emlpack.properties.response import crystal_response

    e = study.cfg.get("emlp", {})
    s0 = study.reference
    digest = hashlib.sha256(Path(path).read_bytes())
    digest.update(json.dumps(e, sort_keys=True, default=str).encode())
    digest.update(np.ascontiguousarray(s0.positions, float).tobytes())
    digest.update(np.ascontiguousarray(s0.cell, float).tobytes())
    cache = Path(path).parent / "emlp.json"
    cached = _read_json(cache)
    if cached is not None and cached.get("key") == digest.hexdigest():
        study.log(f"emlp: {path}: done before (same weights, settings and geometry)")
        return cached["result"]
    model = load_model(path)
    r = relax_pairs(model, s0, fmax=1e-6)[0]
    out: dict = {"model": str(path), "warnings": []}
    if r.failed:
        out["input_geometry"] = {"error": f"pair relaxation failed: {r.reason}"}
    else:
        s_in = s0.copy(pairs=r.pairs)
        try:
            out["input_geometry"] = {"lattice": lattice(s_in.cell),
                                     **crystal_response(model, s_in).as_dict()}
        except (np.linalg.LinAlgError, ValueError) as exc:
            out["input_geometry"] = {"error": f"response failed: {exc}"}
        s0 = s_in
    if "error" in out["input_geometry"]:
        out["warnings"].append(f"{path}: at the DFT geometry: {out['input_geometry']['error']}")
    t0 = time.perf_counter()
    res = optimize(model, s0, cell=True, fmax=float(e.get("fmax", 1e-4)),
                   smax=float(e.get("smax", 1e-6)),
                   max_iterations=int(e.get("max_iterations", 60)),
                   hessian_every=int(e.get("hessian_every", 1)),
                   log=study.log if e.get("verbose") else None)
    opt = {"converged": res.converged, "iterations": res.iterations, "reason": res.reason,
           "max_force": res.max_force, "max_stress_GPa": res.max_stress * EV_PER_A3_IN_GPA,
           "min_curvature": res.min_curvature, "time_s": time.perf_counter() - t0,
           "lattice": lattice(res.structure.cell)}
    try:
        opt.update(crystal_response(model, res.structure).as_dict())
    except (np.linalg.LinAlgError, ValueError) as exc:
        opt["error"] = f"response failed: {exc}"
        out["warnings"].append(f"{path}: at its optimised cell: {opt['error']}")
    out["optimized"] = opt
    if not res.converged:
        out["warnings"].insert(0, (
            f"{path}: BO cell optimisation NOT converged after {res.iterations} iterations"
            f" ({res.reason or 'no reason given'}; max force {res.max_force:.3g} eV/Å, max"
            f" stress {res.max_stress * EV_PER_A3_IN_GPA:.3g} GPa): its optimised-cell values"
            " belong to a non-stationary structure"))
    for w in out["warnings"]:
        study.log(f"emlp: WARNING: {w}")
    study.log(f"emlp: {path}: optimisation converged={res.converged} ({res.reason or 'ok'}),"
              f" lattice {lattice(res.structure.cell)}")
    _write_json(cache, {"key": digest.hexdigest(), "result": out})
    return out


def stage_emlp(study: Study) -> dict:
    """Every member's eMLP values (:func:`emlp_model`) -> WORKDIR/emlp.json: ``members`` (one
    entry each, with its seed) and ``warnings`` (the non-converged optimisations among them)."""
    dirs = member_dirs(study)
    missing = [d for d in dirs if not (d / "best.pt").exists()]
    if missing:
        raise SystemExit(f"{missing[0] / 'best.pt'}: no trained model (run the train stage)")
    members = [{"member": k, "seed": seed, **emlp_model(study, d / "best.pt")}
               for k, (d, seed) in enumerate(zip(dirs, _seeds(study), strict=True))]
    out = {"ensemble": str(_ensemble_dir(study)), "family": _family(study),
           "init_from": study.cfg.get("training", {}).get("init_from"), "members": members,
           "warnings": [w for m in members for w in m.get("warnings", [])]}
    _write_json(study.workdir / "emlp.json", out)
    n_conv = sum(bool(m["optimized"]["converged"]) for m in members)
    study.log(f"emlp: {len(members)} members, {n_conv} BO cell optimisations converged")
    return out


# ---------------------------------------------------------------------- table
LATTICE_KEYS = ("a", "b", "c", "beta", "volume")
#: issue 52's targets, eMLP vs our DFT: (tolerance in % of the DFT value, absolute tolerance
#: or None); a value within either counts. 22 quantities: the lattice, the 3 diagonal eps_inf,
#: C11-C66 and the 8 allowed e components
TOLERANCES: dict[str, tuple[float, float | None]] = {
    **{k: (2.0, None) for k in LATTICE_KEYS},
    **{f"eps{i}{i}": (10.0, None) for i in (1, 2, 3)},
    **{f"C{i}{i}": (15.0, None) for i in range(1, 7)},
    **{f"e{k}": (25.0, 0.02) for k in PIEZO_KEYS},  # C/m^2
}
#: the eMLP columns of the table: clamped-ion tensors at the DFT geometry (pairs relaxed),
#: lattice and clamped-ion tensors at the model's own BO-optimised cell, relaxed-ion tensors
#: there
COLUMNS = ("emlp_clamped_at_dft_geometry", "emlp_clamped", "emlp_relaxed_ion")


def within_tolerance(name: str, ref: float | None, value: float | None) -> bool | None:
    """Whether ``value`` is within the :data:`TOLERANCES` of ``ref`` (None: no target for
    ``name`` or a value missing)."""
    tol = TOLERANCES.get(name)
    dev = _dev(ref, value)
    if tol is None or dev is None:
        return None
    pct, absolute = tol
    return abs(dev) <= pct or (absolute is not None and abs(value - ref) <= absolute)


def tolerance_count(ref: dict, values: dict, names=None) -> dict:
    """The targets (``names``, default all of :data:`TOLERANCES`) that ``values`` meet against
    ``ref``: ``within``, ``outside``, ``missing`` (no value to compare) and their number."""
    out: dict = {"within": [], "outside": [], "missing": []}
    for n in names or TOLERANCES:
        ok = within_tolerance(n, ref.get(n), values.get(n))
        out["missing" if ok is None else "within" if ok else "outside"].append(n)
    out["n_within"] = len(out["within"])
    out["n_targets"] = len(names or TOLERANCES)
    return out


def _flat(prefix: str, d: dict | None, kind: str) -> dict[str, float]:
    """Named components (eps11, C11, e14, d14, ...) of a tensor dict in report units."""
    if not d or "error" in d and len(d) == 1:
        return {}
    out: dict[str, float] = {}
    key = {"dft": ("dielectric", "stiffness_voigt_GPa", "piezo_e_voigt_C_per_m2",
                   "piezo_d_voigt_pm_per_V"),
           "clamped": ("dielectric_ion_clamped", "stiffness_clamped_ion_voigt_GPa",
                       "piezo_e_clamped_ion_voigt_C_per_m2", None),
           "relaxed": ("dielectric_ion_clamped", "stiffness_voigt_GPa",
                       "piezo_e_voigt_C_per_m2", "piezo_d_voigt_pm_per_V")}[kind]
    eps, c, e, dd = (np.array(d[k]) if k else None for k in key)
    if dd is None:  # d = e : C^-1 in report units (e/Å² over eV/Å³ is Å/V)
        dd = (e / E_PER_A2_IN_C_PER_M2) @ np.linalg.inv(c / EV_PER_A3_IN_GPA)
        dd = dd * A_PER_V_IN_PM_PER_V
    for i in range(3):
        out[f"eps{i + 1}{i + 1}"] = float(eps[i, i])
    for k in STIFF_KEYS:
        out[f"C{k}"] = float(c[int(k[0]) - 1, int(k[1]) - 1])
    for k in PIEZO_KEYS:
        out[f"e{k}"] = float(e[int(k[0]) - 1, int(k[1]) - 1])
        out[f"d{k}"] = float(dd[int(k[0]) - 1, int(k[1]) - 1])
    if "lattice" in d:
        lat = d["lattice"]
        out.update({k: float(lat[k]) for k in LATTICE_KEYS})
    return out


def emlp_columns(result: dict) -> dict[str, dict[str, float]]:
    """One model's values (:func:`emlp_model`'s result) by table column (:data:`COLUMNS`):
    the lattice only at the model's own optimum (at the DFT geometry it is DFT's)."""
    opt = result.get("optimized") or {}
    inp = result.get("input_geometry") or {}
    tensors = "stiffness_voigt_GPa"
    cols = {"emlp_clamped_at_dft_geometry": _flat("emlp", inp if tensors in inp else None,
                                                  "clamped"),
            "emlp_clamped": _flat("emlp", opt if tensors in opt else None, "clamped"),
            "emlp_relaxed_ion": _flat("emlp", opt if tensors in opt else None, "relaxed")}
    for k in LATTICE_KEYS:
        cols["emlp_clamped_at_dft_geometry"].pop(k, None)
        cols["emlp_relaxed_ion"].pop(k, None)
    if "lattice" in opt:  # also when the tensors there failed
        cols["emlp_clamped"].update({k: float(opt["lattice"][k]) for k in LATTICE_KEYS})
    return cols


def ensemble_columns(members: list[dict]) -> tuple[dict, dict, dict, list[str]]:
    """The ensemble's mean and spread (population std over members, as
    :func:`emlpack.calculators.ensemble.member_spread`) of every value of every column, the
    members that entered each column, and notes. The optimised-cell columns average the
    members whose BO cell optimisation converged (all members when none did, with a note)."""
    from emlpack.calculators.ensemble import member_spread

    converged = [k for k, m in enumerate(members) if (m.get("optimized") or {}).get("converged")]
    notes = []
    if len(converged) < len(members):
        use = converged or list(range(len(members)))
        notes.append(
            f"BO cell optimisation converged for {len(converged)} of {len(members)} members;"
            " the optimised-cell columns (eMLP opt., eMLP rel.) are "
            + (f"the mean of members {', '.join(map(str, use))}" if converged else
               "the mean of all members, every one a NON-STATIONARY structure"))
    else:
        use = converged
    per_member = [emlp_columns(m) for m in members]
    mean, std, used = {}, {}, {}
    for col in COLUMNS:
        take = range(len(members)) if col == "emlp_clamped_at_dft_geometry" else use
        mean[col], std[col], used[col] = {}, {}, list(take)
        names = {n for k in take for n in per_member[k][col]}
        for n in names:
            vals = [per_member[k][col][n] for k in take if n in per_member[k][col]]
            mean[col][n] = float(np.mean(vals))
            std[col][n] = float(member_spread([{"v": v} for v in vals])["v_std"])
    return mean, std, used, notes


def _dev(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not np.isfinite(a) or not np.isfinite(b) or a == 0:
        return None
    return 100.0 * (b - a) / abs(a)


#: the quantities of the table, in order
NAMES = (list(LATTICE_KEYS) + ["eps11", "eps22", "eps33"] + [f"C{k}" for k in STIFF_KEYS]
         + [f"e{k}" for k in PIEZO_KEYS] + [f"d{k}" for k in PIEZO_KEYS])
#: the targets that a column can meet: at the DFT geometry the lattice is DFT's own
TARGETS = {"emlp_clamped_at_dft_geometry": [n for n in TOLERANCES if n not in LATTICE_KEYS],
           "emlp_clamped": list(TOLERANCES)}


def stage_table(study: Study, out_dir: Path | None = None) -> dict:
    out_dir = Path(out_dir or study.cfg.get("results_dir", HERE))
    dft = _read_json(study.workdir / "dft.json")
    emlp = _read_json(study.workdir / "emlp.json")
    if emlp is not None and "members" not in emlp:  # one model, written before the ensembles
        emlp = {"members": [emlp], "warnings": []}
    members = (emlp or {}).get("members") or []
    recs = study.records()
    failures = study.failures()
    n_fd = sum(_is_fd(s) for s in recs)
    n_opt = sum(s.info["key"].startswith("opt/") for s in recs)
    walls = np.array([float(s.info.get("wall_time", np.nan)) for s in recs])
    n_field = sum(not _is_fd(s) and bool(np.any(s.field)) for s in recs)
    n_stress = sum(not _is_fd(s) and s.stress is not None for s in recs) - n_opt
    dft_v = _flat("dft", dft, "dft")
    if dft:
        dft_v.update({k: float(dft["lattice"][k]) for k in LATTICE_KEYS})
    mean, std, used, notes = ensemble_columns(members) if members else ({}, {}, {}, [])
    rows = []
    for n in NAMES:
        row = {"quantity": n, "dft": dft_v.get(n)}
        for col in COLUMNS:
            row[col] = mean.get(col, {}).get(n)
            row[f"{col}_std"] = std.get(col, {}).get(n)
        row.update({
            "deviation_pct": _dev(dft_v.get(n), row["emlp_clamped"]),
            "deviation_at_dft_geometry_pct": _dev(dft_v.get(n),
                                                  row["emlp_clamped_at_dft_geometry"]),
            "within_tolerance": within_tolerance(n, dft_v.get(n), row["emlp_clamped"]),
            "within_tolerance_at_dft_geometry": within_tolerance(
                n, dft_v.get(n), row["emlp_clamped_at_dft_geometry"]),
            "paper_pbe": PAPER["pbe"].get(n), "paper_emlp": PAPER["emlp"].get(n)})
        rows.append(row)
    warnings = [*(emlp or {}).get("warnings", []), *notes]
    summary = {
        "labeler_level": study.level(),
        "labeler_settings": getattr(getattr(study.labeler(), "settings", None), "to_dict",
                                    lambda: {})(),
        "n_configurations": len(recs), "n_fd_calculations": n_fd,
        "n_optimization_steps": n_opt,
        "dft_geometry": "optimized" if study.optimizing else "input",
        "dft_optimisation": {k: v for k, v in (_read_json(
            study.workdir / "optimization.json") or {}).items() if k != "history"},
        "n_field_set": n_field, "n_stress_set": n_stress, "n_failures": len(failures),
        "wall_time_per_point_s": float(np.nanmean(walls)) if len(walls) else None,
        "total_dft_time_h": float(np.nansum(walls) / 3600.0) if len(walls) else None,
        "fd_settings": {"field_step_au": study.fd.field_step / FIELD_AU_IN_V_PER_A,
                        "strain_step": study.fd.strain_step, "points": study.fd.points},
        "ensemble": {k: (emlp or {}).get(k) for k in ("ensemble", "family", "init_from")}
        | {"n_members": len(members), "members_in_columns": used},
        "emlp_optimisation": [
            {"member": m.get("member", k), "seed": m.get("seed"),
             **{key: (m.get("optimized") or {}).get(key) for key in (
                 "converged", "iterations", "reason", "max_force", "max_stress_GPa")}}
            for k, m in enumerate(members)],
        "warnings": warnings,
        "tolerance": {col: tolerance_count(dft_v, mean.get(col, {}), TARGETS[col])
                      for col in TARGETS},
        "training": _training_summary(study),
        "learning_curve": _learning_curve_rows(study, dft_v),
    }
    train_data = study.workdir / "train_data.h5"
    if train_data.exists():
        with DatasetStore(train_data, "r") as store:
            summary["n_training_configurations"] = len(store)
    for w in warnings:
        study.log(f"table: WARNING: {w}")
    result = {"summary": summary, "rows": rows, "dft": dft, "emlp": emlp,
              "tolerances": {k: {"percent": p, "absolute": a}
                             for k, (p, a) in TOLERANCES.items()},
              "units": {"lattice": "Å, degrees, Å^3", "C": "GPa", "e": "C/m^2", "d": "pm/V"}}
    out_dir.mkdir(parents=True, exist_ok=True)
    _write_json(out_dir / "results.json", result)
    _write_text(out_dir / "results.md", markdown(result, study.cfg.get("notes", "")))
    study.log(f"table: {out_dir / 'results.md'}")
    return result


def _learning_curve_rows(study: Study, dft_v: dict) -> list[dict]:
    """learning_curve.json's models, each with its targets met (:func:`tolerance_count`)."""
    curve = _read_json(study.workdir / "learning_curve.json")
    out = []
    for p in (curve or {}).get("points", []):
        cols = emlp_columns(p)
        out.append({"n_configurations": p["n_configurations"], "all": bool(p.get("all")),
                    "model": p.get("model"),
                    "converged": (p.get("optimized") or {}).get("converged"),
                    **{col: tolerance_count(dft_v, cols[col], TARGETS[col])
                       for col in TARGETS}})
    return out


def _training_summary(study: Study) -> list[dict]:
    """Each member's training (best epoch and validation errors from its log.csv)."""
    import csv

    out = []
    for run in member_dirs(study):
        log = run / "log.csv"
        rows = list(csv.DictReader(log.open())) if log.exists() else []
        if not rows:
            continue
        best = min(rows, key=lambda r: float(r["val_loss"]))
        keep = ("epoch", "val_loss", "val_energy_mae", "val_forces_mae", "val_pair_forces_mae",
                "val_stress_mae")
        out.append({"run": str(run), "epochs": len(rows),
                    "best": {k: float(best[k]) for k in keep if k in best and best[k] != ""}})
    return out


def _fmt(v: float | None, n: str) -> str:
    if v is None:
        return "–"
    if n == "%":
        return f"{v:+.1f}"
    if n.startswith("e"):
        return f"{v:.3f}"
    return f"{v:.4g}" if abs(v) < 1000 else f"{v:.1f}"


def _cell(row: dict, col: str, n: str, n_members: int) -> str:
    """A column's ensemble mean, ``± spread`` when the ensemble has more than one member."""
    text = _fmt(row[col], n)
    if n_members > 1 and row[col] is not None and row.get(f"{col}_std") is not None:
        text += f" ± {_fmt(row[f'{col}_std'], n)}"
    return text


def _dev_cell(row: dict, dev: str, ok: str) -> str:
    mark = {True: " ✓", False: " ✗"}.get(row[ok], "")
    return _fmt(row[dev], "%") + mark


def markdown(result: dict, notes: str = "") -> str:
    s = result["summary"]
    geometry = ("the DFT optimum (`optimize` stage: positions and cell, P2₁)"
                if s.get("dft_geometry") == "optimized" else
                "the input geometry (the paper's QE cell and positions, not re-optimised at our"
                " level)")
    ens = s.get("ensemble") or {}
    n_members = int(ens.get("n_members") or 0)
    lines = ["# beta-glycine: DFT vs eMLP", "",
             "Generated by `examples/beta_glycine/run_study.py table`.", ""]
    if notes:
        lines += [notes.strip(), ""]
    if s.get("warnings"):
        lines += ["**Warnings:**", "", *(f"- ⚠ {w}" for w in s["warnings"]), ""]
    opt_lines = [f"member {o['member']} (seed {o['seed']}): converged={o['converged']},"
                 f" {o['iterations']} iterations, {o['reason'] or 'ok'}"
                 for o in s.get("emlp_optimisation") or []]
    lines += [
        f"- DFT level: `{s['labeler_level']}`",
        f"- labeled configurations: {s['n_configurations']} ({s['n_fd_calculations']}"
        f" finite-difference calculations, {s['n_field_set']} field-set and"
        f" {s['n_stress_set']} stress-set samples; {s['n_failures']} failures);"
        f" {s.get('n_training_configurations', '–')} of them used for training",
        f"- wall time per point: {_fmt(s['wall_time_per_point_s'], 't')} s;"
        f" total DFT time {_fmt(s['total_dft_time_h'], 't')} h",
        f"- finite differences: {s['fd_settings']}",
        f"- eMLP ensemble: {n_members} member(s), family {ens.get('family')}, start"
        f" {ens.get('init_from') or 'random (from scratch)'} (`{ens.get('ensemble')}`)",
        f"- eMLP BO cell optimisation: {'; '.join(opt_lines) or '–'}",
        f"- training: {s['training']}", "",
        "Columns: **DFT** = our finite-difference DFT (ion-clamped ε, clamped-ion C and proper e,"
        f" d = e:C⁻¹ of those) at {geometry}; **eMLP@DFT** = eMLP clamped-ion tensors at that same"
        " geometry, pairs relaxed (the like-for-like comparison; dev. % vs DFT);"
        " **eMLP opt.** = eMLP lattice and clamped-ion tensors at its own BO-optimised cell"
        " (dev. %); **eMLP rel.** = eMLP relaxed-ion tensors there (the paper's kind for C, e,"
        " d); **paper PBE / paper eMLP** = the paper's numbers (relaxed-ion C, e, d; other DFT"
        " settings, not expected to match). eMLP values are the ensemble mean ± the spread"
        " (population standard deviation over the members); ✓/✗: within/outside issue 52's"
        " tolerance (lattice 2 %, ε 10 %, C11-C66 15 %, e 25 % or 0.02 C/m²).", "",
        "| quantity | DFT | eMLP@DFT | dev. % | eMLP opt. | dev. % | eMLP rel. | paper PBE |"
        " paper eMLP |",
        "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        n = r["quantity"]
        lines.append(
            f"| {n} | {_fmt(r['dft'], n)} |"
            f" {_cell(r, 'emlp_clamped_at_dft_geometry', n, n_members)} |"
            f" {_dev_cell(r, 'deviation_at_dft_geometry_pct', 'within_tolerance_at_dft_geometry')}"
            f" | {_cell(r, 'emlp_clamped', n, n_members)} |"
            f" {_dev_cell(r, 'deviation_pct', 'within_tolerance')} |"
            f" {_cell(r, 'emlp_relaxed_ion', n, n_members)} | {_fmt(r['paper_pbe'], n)} |"
            f" {_fmt(r['paper_emlp'], n)} |")
    for col, label in (("emlp_clamped_at_dft_geometry", "eMLP@DFT (same geometry)"),
                       ("emlp_clamped", "eMLP at its own optimised cell")):
        t = s["tolerance"][col]
        lines += ["", f"{label}: {t['n_within']} of {t['n_targets']} targets within tolerance"
                  f" of our DFT: {', '.join(t['within']) or 'none'}; outside:"
                  f" {', '.join(t['outside']) or 'none'}"
                  + (f"; not compared: {', '.join(t['missing'])}" if t["missing"] else "")
                  + "."]
    if s.get("learning_curve"):
        lines += ["", "## Learning curve", "",
                  "One model (member 0's seed and start) per size, on the first N"
                  " configurations of a fixed, seeded order; targets within tolerance of our"
                  " DFT.", "",
                  "| configurations | eMLP@DFT | eMLP opt. | BO optimisation converged |",
                  "|---|---|---|---|"]
        for p in s["learning_curve"]:
            at, op = p["emlp_clamped_at_dft_geometry"], p["emlp_clamped"]
            lines.append(f"| {p['n_configurations']}{' (all)' if p['all'] else ''} |"
                         f" {at['n_within']} of {at['n_targets']} |"
                         f" {op['n_within']} of {op['n_targets']} |"
                         f" {'yes' if p['converged'] else 'NO ⚠'} |")
    lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------------- helpers
def _is_fd(s: Structure) -> bool:
    """A finite-difference calculation (at the input or the optimised reference)."""
    return s.info["key"].split("/")[0] in ("ref", "ref-opt")


def _resolve(path) -> Path:
    p = Path(path)
    return p if p.is_absolute() or p.exists() else HERE / p


def _write_json(path: Path, data) -> None:
    _write_text(path, json.dumps(data, indent=1, default=_jsonable))


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, ReferenceTensors):
        return x.as_dict()
    return str(x)


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def run(stages: list[str], cfg: dict, labeler: Callable | None = None,
        until: dt.datetime | None = None, log=print, shard: tuple[int, int] = (0, 1)) -> Study:
    """Run ``stages`` in order (``"all"``: optimize, label, reference, train, emlp, curve,
    table)."""
    study = Study(copy.deepcopy(cfg), labeler, log)
    order = []
    for s in stages:
        order += (["optimize", "label", "reference", "train", "emlp", "curve", "table"]
                  if s == "all"
                  else [s])
    for s in order:
        if s not in STAGES:
            raise SystemExit(f"unknown stage {s!r} ({', '.join(STAGES)}, all)")
        {"optimize": lambda: stage_optimize(study),
         "label": lambda: stage_label(study, until, shard),
         "reference": lambda: stage_reference(study), "train": lambda: stage_train(study),
         "sample": lambda: stage_sample(study),
         "emlp": lambda: stage_emlp(study), "curve": lambda: stage_curve(study),
         "table": lambda: stage_table(study)}[s]()
    return study


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("stages", nargs="+", help=f"{', '.join(STAGES)} or all; key=value overrides")
    p.add_argument("--config", default=str(HERE / "config.yaml"))
    p.add_argument("--until", help="label: start no calculation after HH:MM (UTC)")
    p.add_argument("--shard", default="0/1",
                   help="label: I/N = every N-th task from I, own store (parallel workers)")
    p.add_argument("--quiet", action="store_true", help="label: no progress bar")
    args = p.parse_args(argv)
    stages = [s for s in args.stages if "=" not in s]
    overrides = [s for s in args.stages if "=" in s] + (["progress=false"] if args.quiet else [])
    until = None
    if args.until:
        hh, mm = (int(x) for x in args.until.split(":"))
        now = dt.datetime.now(dt.timezone.utc)
        until = now.replace(hour=hh, minute=mm, second=0, microsecond=0)
        if until < now - dt.timedelta(hours=12):
            until += dt.timedelta(days=1)
    shard = tuple(int(x) for x in args.shard.split("/"))
    run(stages, load_config(args.config, overrides), until=until, shard=shard,
        log=lambda m: print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {m}", flush=True))


if __name__ == "__main__":
    sys.exit(main())
