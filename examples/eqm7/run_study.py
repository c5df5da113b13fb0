"""The paper's molecular study on mini-eQM7 (issue 15): train, evaluate, DFT, IR, MD, tables.

Stages (each resumable: work whose output file exists is skipped; outputs are written to a
temporary file and renamed, so a killed run leaves no half-written result)::

    train           4 augmented + 4 non-augmented models (seeds of the config) on the card's
                    train/val split -> WORKDIR/models/GROUP/seedK/best.pt (+ done.json);
                    an unfinished model resumes from its last.pt
    evaluate        Table 2 (static) and Table 3 (dynamic) errors of every model on the test
                    molecules of the card, and on the authors' six molecules
                    (../shared/data/eqm7_pbe0_subset.xyz) when that file exists
                    -> WORKDIR/eval/SET/MODEL.json
    dft             DFT reference of every test molecule at the configured level (of the
                    second test set's molecules the static part only): optimised
                    geometry, Boys centres, dipole, polarizability (finite fields), harmonic
                    frequencies and IR intensities (Hessian by central differences of the
                    forces, dft.hessian; Born charges from the field-perturbed forces)
                    -> DATA/references/LEVEL/NAME.json (sub-steps cached in
                    DATA/references/LEVEL/NAME/, so a killed molecule resumes where it
                    stopped; small immutable files to commit with the data set)
    polarizability  every model at the DFT geometries (pairs relaxed from the DFT centres),
                    polarizability vs DFT -> WORKDIR/polarizability/MODEL.json (test
                    molecules) and WORKDIR/polarizability/pbe0_subset/MODEL.json
    ir              every model: optimisation from the DFT geometry, harmonic IR
                    -> WORKDIR/ir/MODEL.json
    md              NVT runs (500 fs, 300 K, 0.5 fs) per test molecule x model (at most
                    md.max_molecules of them) -> WORKDIR/md/MODEL/NAME/{trajectory.xyz,
                    analysis.json}
    table           RESULTS_DIR/results.json + results.md (paper's numbers beside ours, with
                    a baseline the earlier study's too; issue 15's or 51's targets with the
                    measured values) and the figures of the
                    chosen groups' models: Figure 4 PNG (aziridine, 3-(methylamino)but-2-enal),
                    Figure 3 PNGs
    export          the augmented ensemble as a pretrained model (float32 weights + a model
                    card with the measured errors from results.json) -> the package's
                    src/emlpack/pretrained/NAME/ when status is final, else
                    WORKDIR/pretrained/NAME/ (load it with load_pretrained(NAME, root=...))
    all             every stage above in this order

``split: val`` (default ``test``) points the molecule stages at the card's validation
molecules instead, for choices that must never see the test ones (the bake-off of issue 51,
``bakeoff.py``): evaluate scores the shards' validation configurations (-> WORKDIR/eval/val/),
polarizability, ir and md use the references in DATA/references/LEVEL/validation (written by
``validation_references.py``: polarizabilities, no Hessian, so ir skips) and the validation
molecules (-> WORKDIR/polarizability/val/, WORKDIR/ir/val/, WORKDIR/md/MODEL/NAME); the
second test set is not used; dft, table and export refuse (they are the test molecules'). The
outputs do not collide with a test-split run's, and the bake-off uses a workdir of its own per
candidate anyway. The train stage is the same with either split (the card's train/val split).

Usage (from the project root)::

    OMP_NUM_THREADS=1 python examples/eqm7/run_study.py all
    python examples/eqm7/run_study.py train evaluate table training.max_time_minutes=30
    python examples/eqm7/run_study.py dft dft.level=quick workdir=/tmp/eqm7

A second study runs from a config of its own: ``--config examples/eqm7/v2/config.yaml`` (the
study v2 of issue 51) names ``base: ../config.yaml`` and holds only what differs (workdir,
results folder, recipe, ``targets: issue51``, ``baseline``: the earlier study's results.json,
whose numbers every table shows beside ours and the paper's, and the ship rule against it
that the export into the package obeys; examples/eqm7/v2/README.md).

``key=value`` arguments override the YAML config (dots for nesting, values parsed as YAML;
``train.KEY=VALUE`` entries are passed to the training config, see config.yaml). Each stage
shows a progress bar over its units of work (models, DFT parts) on stderr: rate and time left
on a terminal, a plain line every tenth of the work otherwise (:mod:`emlpack.progress`);
``--quiet`` (or ``progress=false``) shows none.
"""

from __future__ import annotations

import argparse
import copy
import csv
import datetime as dt
import json
import os
import shutil
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]  # the project
STAGES = ("train", "evaluate", "dft", "polarizability", "ir", "md", "table", "export")

#: The paper's numbers (emlp-paper.tex): Table 2 (static), Table 3 (dynamic), the MD section
#: (Figure 3) and the IR section (Figure 4). Energies meV/atom, forces meV/Å, dipole D,
#: polarizability bohr^3, rates %, frequencies cm^-1.
PAPER = {
    "static": {
        "intrinsic": {"energy": 170.55, "forces": 1106.8, "pair_forces": 385.9},
        "noaug": {"mae": {"energy": (4.45, 0.11), "forces": (48.8, 0.3),
                          "pair_forces": (43.8, 0.2)},
                  "median": {"energy": (3.02, 0.13), "forces": (27.9, 0.2),
                             "pair_forces": (30.1, 0.2)}},
        "aug": {"mae": {"energy": (4.95, 0.25), "forces": (52.1, 0.3),
                        "pair_forces": (50.3, 0.4)},
                "median": {"energy": (3.45, 0.39), "forces": (29.8, 0.2),
                           "pair_forces": (34.6, 0.3)}},
    },
    "dynamic": {
        "intrinsic": {"energy": 174.93, "forces": 1177.0, "dipole": 1.229,
                      "polarizability": 6.70},
        "noaug": {"mae": {"energy": (40.8, 21.1), "forces": (104.0, 23.2),
                          "dipole": (0.169, 0.042), "polarizability": (0.72, 0.44)},
                  "median": {"energy": (3.15, 0.13), "forces": (30.0, 0.6),
                             "dipole": (0.035, 0.001), "polarizability": (0.26, 0.01)},
                  "error_rate": (2.4, 0.8), "polarizability_error_rate": (0.2, 0.4)},
        "aug": {"mae": {"energy": (49.3, 33.2), "forces": (137.8, 63.8),
                        "dipole": (0.286, 0.014), "polarizability": (0.54, 0.09)},
                "median": {"energy": (3.45, 0.18), "forces": (32.9, 0.5),
                           "dipole": (0.078, 0.005), "polarizability": (0.31, 0.03)},
                "error_rate": (0.4, 0.1), "polarizability_error_rate": (0.0, 0.0)},
    },
    "md": {"noaug_unstable_pct": 9.8, "aug_unstable_pct": 0.0},
    # the paper's data, architecture and training (eQM7 section and Table 1)
    "setup": {"configurations": 3434000, "molecules": 6868, "n_features": 512, "n_filters": 128,
              "n_rbf": 32, "n_interactions": 4, "message_norm": 70.0, "batch_size": 64,
              "lr": 3e-4, "hours": 288.0},
    "ir": {"frequency_mae_cm-1": 15.0},
}
GROUP_LABEL = {"aug": "augmented", "noaug": "non-augmented"}
#: results.md's title (``title`` in config.yaml replaces it, e.g. the v2 study's)
DEFAULT_TITLE = "mini-eQM7: the paper's molecular study"
#: the model groups: name -> trained with the paper's augmentation
GROUPS = {"aug": True, "noaug": False}
#: the IR molecules of Figure 4 (names in molecules.csv)
IR_MOLECULES = {"qm7-0011": "aziridine", "extra-0000": "3-(methylamino)but-2-enal"}
#: bands of the DFT frequency (cm⁻¹) for the IR errors by kind of mode: torsions, out-of-plane
#: and skeletal bends; C-C/C-N/C-O stretches and X-H bends, C=C/C=O/C=N; triple bonds;
#: X-H stretches
IR_BANDS = ((0.0, 1000.0), (1000.0, 1800.0), (1800.0, 2600.0), (2600.0, 4500.0))


# ---------------------------------------------------------------------- config
def load_config(path: str | Path, overrides: list[str] = ()) -> dict:
    """config.yaml with ``key=value`` overrides; ``train.KEY=VALUE`` goes to the training
    configuration of every model (``training.overrides``)."""
    from emlpack.overrides import OverrideError, apply_overrides, load_yaml

    cfg = _with_base(Path(path), load_yaml)
    try:
        apply_overrides(cfg, [t for t in overrides if not t.startswith("train.")])
    except OverrideError as exc:
        raise SystemExit(str(exc)) from None
    train = [t[len("train."):] for t in overrides if t.startswith("train.")]
    if train:
        t = cfg.setdefault("training", {})
        t["overrides"] = [*(t.get("overrides") or []), *train]
    cfg.setdefault("workdir", "runs/eqm7")
    cfg.setdefault("results_dir", str(HERE))
    cfg.setdefault("data", "datasets/mini-eqm7")
    cfg.setdefault("seeds", [0, 1, 2, 3])
    cfg.setdefault("split", "test")
    return cfg


def merge_config(base: dict, update: dict) -> dict:
    """``base`` with ``update`` merged in: mappings key by key (recursively), anything else
    (lists included) replaced."""
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_config(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _with_base(path: Path, load_yaml, seen: tuple[Path, ...] = ()) -> dict:
    """The config at ``path``; one with ``base: FILE`` (relative to its own folder) is that
    file's config with its own keys merged over it (:func:`merge_config`), so a second study
    (``v2/config.yaml``) states only what differs from the first."""
    path = path.resolve()
    if path in seen:
        raise SystemExit(f"{path}: base configs form a cycle")
    cfg = load_yaml(path.read_text()) or {}
    base = cfg.pop("base", None)
    if not base:
        return cfg
    base_path = Path(base) if Path(base).is_absolute() else path.parent / base
    if not base_path.is_file():
        raise SystemExit(f"{path}: base {base}: no such file")
    return merge_config(_with_base(base_path, load_yaml, (*seen, path)), cfg)


#: the molecules a study is judged on (``split``): the card's split names
SPLITS = ("test", "val")


class Study:
    """Paths and shared state of one study run; ``work`` counts the work actually done
    (models trained, evaluations, DFT molecules, MD runs, ...), so callers can check that a
    re-run skipped everything."""

    def __init__(self, cfg: dict, log=print) -> None:
        self.cfg = cfg
        self.workdir = Path(cfg["workdir"])
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.data = Path(cfg["data"])
        self.log = log
        self.work: Counter = Counter()
        self._shards = None
        _ = self.split  # a bad split: one clear line before any work

    @property
    def split(self) -> str:
        """The card's split whose molecules the molecule stages use (``split``): ``test`` (the
        study's tables) or ``val`` (choices that must not see the test molecules)."""
        split = str(self.cfg.get("split") or "test")
        if split not in SPLITS:
            raise SystemExit(f"split: {' or '.join(SPLITS)}, got {split!r}")
        return split

    def sets(self) -> tuple[str, ...]:
        """The molecule sets of the model stages: the split's own (``test`` or ``val``), then
        with split test the second test set (``pbe0_subset``, the authors' six molecules)."""
        return ("test", "pbe0_subset") if self.split == "test" else (self.split,)

    def require_test_split(self, stage: str, why: str) -> None:
        """Stop ``stage`` with one line when the study runs on the validation molecules."""
        if self.split != "test":
            raise SystemExit(f"{stage}: not with split {self.split} ({why})")

    def progress(self, items, stage: str, unit: str):
        """``items`` with a progress bar on stderr (:func:`emlpack.progress.progress`: rate
        and time left on a terminal, a plain line every tenth otherwise; none with the
        config's ``progress: false``, ``--quiet``)."""
        from emlpack.progress import progress

        return progress(list(items), desc=stage, unit=unit,
                        enabled=bool(self.cfg.get("progress", True)))

    @property
    def dft_dir(self) -> Path:
        """Where the DFT references of the split's molecules live: ``dft.dir``, by default
        ``DATA/references/LEVEL`` beside the campaign's shards (hours of DFT per molecule:
        small immutable files, committed with the data set; the level in the path keeps a
        test level from ever mixing with the paper's); with split val its ``validation/``
        folder (``validation_references.py``)."""
        from emlpack.qm.levels import parse_level

        d = self.cfg.get("dft", {})
        if d.get("dir"):
            base = Path(d["dir"])
        else:
            base = self.data / "references" / parse_level(d.get("level", "paper")).name \
                .replace("/", "_")
        return base if self.split == "test" else base / "validation"

    # ------------------------------------------------------------------ data
    def shards(self):
        from emlpack.data.shards import read_shards

        if self._shards is None:
            self._shards = read_shards(self.data)
        return self._shards

    def train_domain(self) -> dict:
        """Elements and largest molecule of the training split (what the models saw)."""
        from emlpack.data.dataset import training_domain

        data = self.shards()
        return training_domain([data.structures[i] for i in data.split_indices()["train"]])

    def molecules(self) -> list[dict]:
        from emlpack.data.shards import read_molecule_table

        return read_molecule_table(self.data)

    def split_molecules(self) -> list[dict]:
        """The card's molecules of the study's split, test or validation (optionally limited
        by ``molecules``/``max_molecules``)."""
        rows = [m for m in self.molecules() if m["split"] == self.split]
        names = self.cfg.get("molecules")
        if names:
            rows = [m for m in rows if m["name"] in set(names)]
        limit = self.cfg.get("max_molecules")
        return rows[: int(limit)] if limit else rows

    def second_set_molecules(self) -> list[dict]:
        """The second test set's molecules (``evaluate.second_test_set_molecules``: name ->
        SMILES), for their static DFT references; optionally limited by ``molecules``."""
        listed = self.cfg.get("evaluate", {}).get("second_test_set_molecules") or {}
        names = self.cfg.get("molecules")
        return [{"name": name, "smiles": smiles, "split": "pbe0_subset"}
                for name, smiles in listed.items() if not names or name in set(names)]

    def md_molecules(self) -> list[dict]:
        """The split's molecules of the md stage: at most ``md.max_molecules`` of them, evenly
        spaced in the card's order (null: all)."""
        return _subsample(self.split_molecules(), self.cfg.get("md", {}).get("max_molecules"))

    def ir_molecules(self) -> list[str]:
        """The split's molecules of the harmonic IR comparison (``ir.molecules``; null: every
        one of the split's, the 15 test molecules of the card): the ir stage optimises the
        models from their DFT optima and its frequency MAE covers them all (a molecule without
        a finished DFT Hessian is listed as missing, a failed optimisation as excluded)."""
        names = [m["name"] for m in self.split_molecules()]
        listed = (self.cfg.get("ir") or {}).get("molecules")
        if not listed:
            return names
        unknown = sorted(set(listed) - set(names))
        if unknown:
            raise SystemExit(f"ir.molecules: {unknown} are not {self.split} molecules of the"
                             " card (or are left out by molecules/max_molecules)")
        return [n for n in names if n in set(listed)]

    def reference_molecules(self, set_name: str | None = None) -> list[dict]:
        """The molecules of ``set_name`` (None: the split's, ``test`` or ``val``: the card's;
        ``pbe0_subset``: the second test set's) whose DFT references the model stages compare
        with."""
        set_name = set_name or self.split
        if set_name not in self.sets():
            raise SystemExit(f"{set_name}: not a molecule set of split {self.split}"
                             f" ({', '.join(self.sets())})")
        return self.split_molecules() if set_name == self.split else self.second_set_molecules()

    # ------------------------------------------------------------------ models
    def groups(self) -> dict[str, bool]:
        """The model groups (name: augmented), restricted to ``cfg["groups"]`` when given."""
        groups = GROUPS
        chosen = self.cfg.get("groups") or list(groups)
        unknown = sorted(set(chosen) - set(groups))
        if unknown:
            raise SystemExit(f"groups: unknown {unknown} (known: {sorted(groups)})")
        return {name: aug for name, aug in groups.items() if name in chosen}

    def model_dir(self, group: str, seed: int) -> Path:
        return self.workdir / "models" / group / f"seed{seed}"

    def models(self) -> list[tuple[str, str, Path]]:
        """``(group, name, best.pt)`` of every finished model (train stage done)."""
        out = []
        for group in self.groups():
            for seed in self.cfg["seeds"]:
                run = self.model_dir(group, seed)
                if (run / "done.json").exists() and (run / "best.pt").exists():
                    out.append((group, f"{group}-s{seed}", run / "best.pt"))
        return out

    def require_models(self) -> list[tuple[str, str, Path]]:
        models = self.models()
        if not models:
            raise SystemExit(f"{self.workdir / 'models'}: no trained model (run the train stage)")
        return models


# ---------------------------------------------------------------------- helpers
def _write_text(path: Path, text: str) -> None:
    from emlpack._files import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text)


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    return str(x)


def _write_json(path: Path, data) -> None:
    _write_text(path, json.dumps(data, indent=1, default=_jsonable))


def _read_json(path: Path):
    return json.loads(path.read_text()) if path.exists() else None


def _resolve(path) -> Path:
    p = Path(path)
    return p if p.is_absolute() or p.exists() else HERE / p


def train_config_path(training: dict) -> Path:
    """The training config file of the study's ``training`` section (``config``, default
    train.yaml, relative to this folder unless it exists from the working directory)."""
    return _resolve(training.get("config", "train.yaml"))


def _subsample(items: list, limit: int | None) -> list:
    """At most ``limit`` items, evenly spaced (all when ``limit`` is falsy)."""
    if not limit or len(items) <= int(limit):
        return list(items)
    idx = np.unique(np.linspace(0, len(items) - 1, int(limit)).round().astype(int))
    return [items[i] for i in idx]


def mean_std(values) -> dict:
    """``{"mean", "std", "n", "values"}`` over models (std with ddof=1; 0 for one value)."""
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if v.size == 0:
        return {"mean": None, "std": None, "n": 0, "values": []}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "n": int(v.size), "values": v.tolist()}


def _cached(path: Path, compute):
    """An ``.npz`` sub-result: loaded when present, else computed (dict of arrays) and saved."""
    if path.exists():
        with np.load(path) as d:
            return {k: d[k] for k in d.files}
    from emlpack._files import write_npz_atomic

    out = {k: np.asarray(v) for k, v in compute().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_npz_atomic(path, **out)
    return out


def _load(path: Path):
    from emlpack.train.evaluate import load_for_evaluation

    return load_for_evaluation(path)


# ---------------------------------------------------------------------- train
def model_overrides(training: dict, group: str, seed: int | str) -> list[str]:
    """The training overrides of one model: ``training.overrides`` then the group's own
    ``training.group_overrides[GROUP]``, with ``{group}`` and ``{seed}`` replaced (e.g. each
    member fine-tuned from its own earlier run: ``training.init_weights=.../{group}/seed{seed}/
    best.pt``)."""
    extra = (training.get("group_overrides") or {}).get(group, [])
    return [str(o).replace("{group}", group).replace("{seed}", str(seed))
            for o in [*training.get("overrides", []), *extra]]


def step_schedule(training: dict, n_train: int) -> list[str]:
    """Training overrides for a schedule given in optimizer steps (``training.steps``, the
    rate halved every ``training.decay_steps``), so that runs on data sets of other sizes take
    the same steps on the same schedule: ``max_epochs = round(steps / steps_per_epoch)``, no
    time limit, no early stopping (the best validation epoch is kept). None: train.yaml's
    epochs and time limit."""
    from emlpack.train.config import load_config as load_train_config

    steps = training.get("steps")
    if steps is None:
        return []
    batch = int(load_train_config(train_config_path(training),
                                  training.get("overrides", []))
                ["training"]["batch_size"])
    per_epoch = max(1, -(-int(n_train) // batch))
    decay = float(training.get("decay_steps") or steps)
    return [f"training.max_epochs={max(1, round(float(steps) / per_epoch))}",
            f"training.decay_epochs={decay / per_epoch}",
            "training.max_time_minutes=null", "training.patience=1000000"]


def training_progress(run: Path) -> dict | None:
    """How far the training in ``run`` is, from its ``last.pt``: ``cpu_seconds`` (CPU seconds
    over all resumes, ``training.max_cpu_minutes``; None for a run before 2026-12-02) and
    ``epochs``; None without a last.pt."""
    from emlpack.nn.checkpoint import read_checkpoint

    if not (run / "last.pt").exists():
        return None
    state = read_checkpoint(run / "last.pt")["metadata"].get("training") or {}
    return {"cpu_seconds": state.get("cpu_seconds"), "epochs": int(state.get("epoch", 0))}


def stage_train(study: Study) -> list[Path]:
    from emlpack.train.config import load_config as load_train_config
    from emlpack.train.trainer import train

    t = study.cfg.get("training", {})
    split = study.shards().split_indices()
    n_data = len(study.shards().structures)
    schedule = step_schedule(t, len(split["train"]))
    paths = []
    runs = [(g, a, seed) for g, a in study.groups().items() for seed in study.cfg["seeds"]]
    for group, augmented, seed in study.progress(runs, "train", "model"):
        run = study.model_dir(group, seed)
        done = run / "done.json"
        if done.exists():
            study.log(f"train: {group} seed {seed} done ({run}), skipped")
            trained_on = (_read_json(done) or {}).get("n_configurations")
            if trained_on is not None and trained_on != n_data:
                study.log(f"train: WARNING {run} was trained on {trained_on}"
                          f" configurations, the data set now has {n_data}: use a new"
                          " workdir (or delete the models) to train on the new data")
            paths.append(run / "best.pt")
            continue
        if not len(split["train"]) or not len(split["val"]):
            raise SystemExit(
                f"train: {study.data} has {len(split['train'])} training and"
                f" {len(split['val'])} validation configurations; both are needed (the"
                " validation molecules select the best epoch)")
        overrides = [f"data.path={study.data}", f"output.dir={run}",
                     f"augmentation.enabled={str(augmented).lower()}",
                     f"training.seed={seed}", "output.progress=false",
                     *schedule, *model_overrides(t, group, seed)]
        if t.get("snapshots"):  # trainings longer than a session: committed snapshots
            overrides += [f"output.snapshot_dir={Path(t['snapshots']) / group / f'seed{seed}'}",
                          "output.snapshot_commit=true"]
        cfg = load_train_config(train_config_path(t), overrides)
        t0 = time.perf_counter()
        best = train(cfg)  # resumes from last.pt when a previous run was cut off
        study.work["train"] += 1
        if not Path(best).exists():
            raise SystemExit(f"train: {run}: no best.pt after training (no finite"
                             " validation loss); see its log.csv")
        rows = list(csv.DictReader((run / "log.csv").open())) if (run / "log.csv").exists() \
            else []
        best_row = min(rows, key=lambda r: float(r["val_loss"])) if rows else {}
        _write_json(done, {"best": str(best), "epochs": len(rows),
                           "cpu_seconds": (training_progress(run) or {}).get("cpu_seconds"),
                           "n_configurations": n_data,
                           "n_train": int(len(split["train"])),
                           "n_val": int(len(split["val"])),
                           "wall_s_this_call": time.perf_counter() - t0,
                           "best_epoch": best_row.get("epoch"),
                           "best_val": {k: float(v) for k, v in best_row.items()
                                        if k.startswith("val_") and v not in ("", None)}})
        study.log(f"train: {group} seed {seed} -> {best}")
        paths.append(best)
    return paths


# ---------------------------------------------------------------------- evaluate
def test_sets(study: Study) -> dict[str, list]:
    """The configurations the evaluate stage scores, by set: ``{"test": [...], "pbe0_subset":
    [...]}`` (the second only when its file exists), with split val ``{"val": [...]}`` (the
    shards' validation configurations, no second set)."""
    e = study.cfg.get("evaluate", {})
    data = study.shards()
    split = data.split_indices()
    sets = {study.split: _subsample([data.structures[i] for i in split[study.split]],
                                    e.get("max_structures"))}
    second = e.get("second_test_set")
    if "pbe0_subset" in study.sets() and second and Path(second).exists():
        from emlpack.data.dataset import load_data

        structures, _ = load_data(second)
        sets["pbe0_subset"] = _subsample(structures, e.get("max_structures_second"))
    return sets


def stage_evaluate(study: Study) -> dict:
    from emlpack.train.evaluate import evaluate

    e = study.cfg.get("evaluate", {})
    models = study.require_models()
    sets = test_sets(study)
    second = e.get("second_test_set")
    if "pbe0_subset" in study.sets() and "pbe0_subset" not in sets:
        study.log(f"evaluate: {second} not found; the second test set is skipped")
    out = {}
    for set_name, structures in sets.items():
        if not structures:
            study.log(f"evaluate: no {set_name} structures yet, skipped")
    todo = [(set_name, structures, m) for set_name, structures in sets.items() if structures
            for m in models]
    for set_name, structures, (group, name, path) in study.progress(todo, "evaluate", "model"):
        target = study.workdir / "eval" / set_name / f"{name}.json"
        if target.exists():
            study.log(f"evaluate: {set_name}/{name} exists, skipped")
            continue
        model, reference, _ = _load(path)
        t0 = time.perf_counter()
        metrics, _ = evaluate(model, reference, structures,
                              dynamic=bool(e.get("dynamic", True)))
        metrics.update(model=str(path), group=group, name=name, set=set_name,
                       wall_s=time.perf_counter() - t0)
        metrics.get("dynamic", {}).pop("structures", None)  # per-structure records: large
        _write_json(target, metrics)
        study.work["evaluate"] += 1
        out[(set_name, name)] = metrics
        study.log(f"evaluate: {set_name}/{name}: static F MAE"
                  f" {1000 * metrics['static']['forces']['mae']:.1f} meV/Å")
    return out


# ---------------------------------------------------------------------- dft
def _start_geometry(study: Study, row: dict) -> tuple[np.ndarray, np.ndarray, str]:
    """Where the DFT optimisation starts: the campaign's prepared geometry (its cheap level), else
    one prepared here at the campaign's preparation level, cached as DFT_DIR/NAME/start.npz."""
    prepared = study.data / "prepared" / f"{row['name']}.npz"
    if prepared.exists():
        with np.load(prepared) as d:
            return d["numbers"].astype(int), d["positions"].astype(float), \
                f"prepared ({d['level']})"

    def prepare():
        from emlpack.data.store import StoreError
        from emlpack.qm.campaign import campaign_recipe, load_settings
        from emlpack.qm.labeling import prepare_task

        try:
            prep = load_settings(study.data)["recipe"]["prepare"]
        except StoreError:  # a data set not made by `emlp campaign`: its default preparation
            prep = campaign_recipe()["prepare"]
        mol = prepare_task((row["name"], row["smiles"]), prep["level"], optimize=True,
                           fmax=float(prep["fmax"]), seed=0, hessian=False)
        return {"numbers": mol.numbers, "positions": mol.positions,
                "origin": f"prepared for the reference ({prep['level']})"}

    d = _cached(study.dft_dir / row["name"] / "start.npz", prepare)
    return d["numbers"].astype(int), d["positions"].astype(float), str(d["origin"])


def bfgs_start_hessian(hessian: np.ndarray, floor: float = 0.5) -> np.ndarray:
    """A positive definite BFGS start (eV/Å²) from a cheap-level Hessian: its eigenvalues
    below ``floor`` (translations, rotations, soft or negative modes) raised to ``floor``."""
    h = 0.5 * (hessian + hessian.T)
    evals, vecs = np.linalg.eigh(h)
    return (vecs * np.maximum(evals, floor)) @ vecs.T


def _start_hessian(numbers: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """BFGS's start (eV/Å²): the GFN2-xTB Hessian at ``positions``, made positive definite.

    ASE's default, 70 eV/Å² x identity, is far too stiff for torsions: from an MMFF geometry
    3-(methylamino)but-2-enal took 89 BFGS steps at GFN2-xTB with it and 15 with this start."""
    from ase import Atoms
    from tblite.ase import TBLite

    from emlpack.qm.labeling import finite_difference_hessian

    atoms = Atoms(numbers=numbers, positions=positions)
    atoms.calc = TBLite(method="GFN2-xTB", verbosity=0)
    return bfgs_start_hessian(finite_difference_hessian(atoms))


def harmonic_ir(hessian: np.ndarray, born: np.ndarray, numbers, positions) -> dict:
    """Frequencies (cm^-1, imaginary negative) and IR intensities (km/mol) from a Cartesian
    Hessian (eV/Å²) and dipole derivatives dmu_a/dR_ib (3, 3N; e), as
    :mod:`emlpack.properties.ir`."""
    from ase.data import atomic_masses

    from emlpack.geometry import normal_modes
    from emlpack.units import IR_KM_PER_MOL_PER_E2_AMU, WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU

    masses = atomic_masses[np.asarray(numbers, dtype=int)]
    evals, vecs = normal_modes(hessian, np.asarray(positions), masses)
    freqs = np.sign(evals) * np.sqrt(np.abs(evals)) * WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU
    inv_sqrt_m = 1.0 / np.sqrt(np.repeat(masses, 3))
    dmu_dq = born @ (vecs * inv_sqrt_m[:, None])
    return {"frequencies": freqs, "intensities": IR_KM_PER_MOL_PER_E2_AMU * (dmu_dq**2).sum(0)}


def _steps_from_trajectory(traj: Path, steps_dir: Path) -> None:
    """The frames of an ASE optimisation trajectory (the references' working file before
    2026-11-27) as step files ``steps_dir/NNNN.npz`` (positions, energy, forces), once; a frame
    cut by a kill ends the conversion there."""
    from ase.io import Trajectory

    from emlpack._files import write_npz_atomic

    if not traj.exists() or any(steps_dir.glob("[0-9]*.npz")):
        return
    try:
        with Trajectory(traj) as frames:
            for k, frame in enumerate(frames):
                write_npz_atomic(steps_dir / f"{k:04d}.npz", positions=frame.positions,
                                 energy=frame.get_potential_energy(),
                                 forces=frame.get_forces())
    except Exception:  # noqa: BLE001 - a frame cut by a kill: the frames before it stay
        pass


def dft_static(study: Study, row: dict, labeler) -> dict:
    """Static DFT reference of one molecule (``NAME.json``): BFGS optimum, energy, Boys centres,
    dipole, polarizability and Born charges from central finite fields; every sub-step cached
    under DFT_DIR/NAME/."""
    from ase import Atoms
    from ase.optimize import BFGS

    from emlpack.qm.finite_field import FiniteFieldError, finite_field_response
    from emlpack.qm.labeling import labeler_calculator

    d = study.cfg.get("dft", {})
    cache = study.dft_dir / row["name"]
    numbers, start, origin = _start_geometry(study, row)
    t0 = time.perf_counter()

    def optimise():
        # resumable step by step on any machine: every BFGS step is a small immutable file
        # NAME/opt/NNNN.npz (committed with the references); a resume on the same machine
        # reads BFGS's saved Hessian (.bfgs.json, working state), elsewhere it replays the
        # steps from the start Hessian, as the uninterrupted run built it
        from ase.calculators.singlepoint import SinglePointCalculator

        from emlpack._files import write_npz_atomic

        steps_dir, restart = cache / "opt", cache / ".bfgs.json"
        steps_dir.mkdir(parents=True, exist_ok=True)
        _steps_from_trajectory(cache / ".opt.traj", steps_dir)  # runs before 2026-11-27
        frames = []
        for f in sorted(steps_dir.glob("[0-9]*.npz")):
            with np.load(f) as s:
                frame = Atoms(numbers=numbers, positions=s["positions"])
                frame.calc = SinglePointCalculator(frame, energy=float(s["energy"]),
                                                   forces=s["forces"])
                frames.append(frame)
        atoms = Atoms(numbers=numbers, positions=frames[-1].positions if frames else start)
        atoms.calc = labeler_calculator(labeler)
        opt = BFGS(atoms, logfile=None, maxstep=0.1, restart=str(restart))
        if opt.state is None:  # a start, or a resume without BFGS's saved Hessian
            opt.H0 = _start_hessian(numbers, frames[0].positions if frames else start)
            if frames:
                opt.replay_trajectory(frames)

        def save_step():
            if frames and np.abs(atoms.positions - frames[-1].positions).max() < 1e-12:
                return  # the resumed run's first call: that step is saved already
            frame = atoms.copy()
            frame.calc = SinglePointCalculator(frame, energy=atoms.get_potential_energy(),
                                               forces=atoms.get_forces())
            frames.append(frame)
            write_npz_atomic(steps_dir / f"{len(frames) - 1:04d}.npz",
                             positions=frame.positions, energy=frame.get_potential_energy(),
                             forces=frame.get_forces())

        opt.attach(save_step)
        done = max(0, len(frames) - 1)
        fmax, max_steps = float(d.get("fmax", 0.01)), int(d.get("max_steps", 100))
        converged = opt.run(fmax=fmax, steps=max(0, max_steps - done))
        if not converged:  # a reference at a non-stationary point: never a silent success
            raise RuntimeError(
                f"BFGS did not reach fmax {fmax:g} eV/Å in {max_steps} steps (largest force"
                f" {np.abs(atoms.get_forces()).max():.3f} eV/Å); its steps are kept in"
                f" {steps_dir}: raise dft.max_steps and delete {row['name']}.failed.json to"
                " go on from the last one")
        return {"positions": atoms.positions, "converged": bool(converged),
                "steps": max(0, len(frames) - 1),
                "max_force": np.abs(atoms.get_forces()).max()}

    opt = _cached(cache / "opt.npz", optimise)
    pos = opt["positions"]

    def ground():
        r = labeler(numbers, pos, forces=True, localize=True)
        if not r.ok:
            raise RuntimeError(f"{row['name']}: DFT failed at the optimum: {r.error}")
        return {"energy": r.energy, "forces": r.forces, "dipole": r.dipole, "pairs": r.pairs}

    g = _cached(cache / "ground.npz", ground)
    f_au = float(d.get("field_au", 1e-3))
    try:
        resp = finite_field_response(labeler, numbers, pos, f_au, forces=True, cache=cache)
    except FiniteFieldError as exc:
        raise RuntimeError(f"{row['name']}: DFT failed: {exc}") from None
    alpha, born = resp.polarizability_bohr3, resp.born_charges
    return {
        "name": row["name"], "smiles": row["smiles"], "level": labeler.level.name,
        "start_geometry": origin, "numbers": numbers.tolist(), "positions": pos.tolist(),
        "optimisation": {"converged": bool(opt["converged"]), "steps": int(opt["steps"]),
                         "max_force": float(opt["max_force"]),
                         "fmax": float(d.get("fmax", 0.01))},
        "energy": float(g["energy"]), "max_force_at_optimum": float(np.abs(g["forces"]).max()),
        "pairs": g["pairs"].tolist(), "dipole_e_A": g["dipole"].tolist(),
        "field_step_au": f_au,
        "polarizability_bohr3": alpha.tolist(),
        "polarizability_isotropic_bohr3": float(np.trace(alpha) / 3),
        "born_charges_e": born.tolist(),
        "wall_s_this_call": time.perf_counter() - t0,
    }


def dft_vibrations(study: Study, static: dict, labeler) -> dict:
    """Harmonic reference of one molecule at its static reference's optimum (``NAME.ir.json``):
    Hessian (central differences of the forces along ``dft.hessian_directions``, resumable per
    displacement in DFT_DIR/NAME/vib-internal/ or, Cartesian, NAME/vib/; or PySCF's analytic
    one), frequencies and IR intensities with the static Born charges."""
    from ase import Atoms

    from emlpack.qm.labeling import finite_difference_hessian, labeler_calculator, pyscf_hessian

    d = study.cfg.get("dft", {})
    cache = study.dft_dir / static["name"]
    numbers, pos = np.array(static["numbers"]), np.array(static["positions"])
    t0 = time.perf_counter()
    method = str(d.get("hessian", "finite-difference"))
    if method not in ("finite-difference", "analytic"):
        raise ValueError(f"dft.hessian: 'finite-difference' or 'analytic', got {method!r}")

    def hessian():
        if method == "analytic":
            return {"hessian": pyscf_hessian(labeler, numbers, pos), "method": method}
        atoms = Atoms(numbers=numbers, positions=pos)
        atoms.calc = labeler_calculator(labeler)
        delta = float(d.get("hessian_delta", 0.005))
        directions = str(d.get("hessian_directions", "internal"))
        folder = cache / ("vib" if directions == "cartesian" else f"vib-{directions}")
        hess = finite_difference_hessian(atoms, delta, cache=folder, directions=directions,
                                         reverse=bool(d.get("hessian_reverse", False)))
        return {"hessian": hess, "method": f"{method} (central, {delta:g} Å, {directions}"
                f" directions)"}

    h = _cached(cache / "hessian.npz", hessian)
    hess = h["hessian"]
    ir = harmonic_ir(hess, np.array(static["born_charges_e"]), numbers, pos)
    return {
        "name": static["name"], "level": static["level"], "hessian_eV_A2": hess.tolist(),
        "hessian_method": str(h["method"]) if "method" in h else "analytic",
        "frequencies_cm-1": ir["frequencies"].tolist(),
        "intensities_km_per_mol": ir["intensities"].tolist(),
        "wall_s_this_call": time.perf_counter() - t0,
    }


def dft_plan(rows: list[dict], figure: list[str], static_only: list[dict] = (),
             ir_cost: Callable[[str], float | None] | None = None) -> list[tuple[dict, str]]:
    """(molecule, part) in the order the dft stage computes them: the IR figure's molecules
    completely, then every other molecule's ``static`` reference, then those of
    ``static_only`` (the second test set's: polarizabilities, no Hessian), then the ``ir``
    ones (hours each), cheapest first by ``ir_cost(name)`` when given (None: unknown, last),
    so that the IR frequency MAE covers the most test molecules soonest."""
    first = [r for r in rows if r["name"] in figure]
    rest = [r for r in rows if r["name"] not in figure]
    hessians = rest
    if ir_cost is not None:
        costs = {r["name"]: ir_cost(r["name"]) for r in rest}
        hessians = sorted(rest, key=lambda r: (costs[r["name"]] is None, costs[r["name"]] or 0))
    return ([(r, part) for r in first for part in ("static", "ir")]
            + [(r, "static") for r in [*rest, *static_only]] + [(r, "ir") for r in hessians])


def stage_dft(study: Study) -> dict:
    """The DFT references in the order that gives results soonest (``dft_plan``): the IR
    figure's molecules completely (``NAME.json`` then ``NAME.ir.json``), then every other test
    molecule's static reference (polarizabilities), then the second test set's, then the test
    molecules' Hessians (hours each), cheapest first (``reference_split.reference_cost``: force
    calls left x basis functions^2.5)."""
    study.require_test_split("dft", "the validation molecules' references come from"
                             " examples/eqm7/validation_references.py")
    from emlpack.qm.pyscf_labeler import PySCFLabeler

    d = study.cfg.get("dft", {})
    # one labeler for every small step of a molecule (BFGS, fields, Hessian displacements):
    # each SCF starts from the density of the step before
    # keep_heap: a process that does nothing but this stage (references.sh) keeps its freed
    # memory between force calls instead of page-faulting it in again (PySCFLabeler)
    labeler = PySCFLabeler(d.get("level", "paper"), boys_starts=int(d.get("boys_starts", 3)),
                           threads=d.get("threads"), reuse_density=True,
                           keep_heap=bool(d.get("keep_heap", False)))
    figure = study.cfg.get("ir", {}).get("figure_molecules", list(IR_MOLECULES))
    out: dict = {}
    if str(HERE) not in sys.path:
        sys.path.insert(0, str(HERE))
    from reference_split import reference_cost  # the Hessian's cost: calls left x basis^2.5

    plan = dft_plan(study.split_molecules(), figure, study.second_set_molecules(),
                    ir_cost=lambda name: reference_cost(study.dft_dir, name))
    for row, part in study.progress(plan, "dft", "part"):
        name = row["name"]
        target = study.dft_dir / (f"{name}.json" if part == "static" else f"{name}.ir.json")
        failed = study.dft_dir / f"{name}.failed.json"
        if target.exists() or (part == "ir" and "frequencies_cm-1"
                               in (_read_json(study.dft_dir / f"{name}.json") or {})):
            study.log(f"dft: {name} {part} exists, skipped")
            continue
        if _read_json(failed):
            study.log(f"dft: {name} failed before (see {failed.name}), skipped; delete that"
                      " file to retry")
            continue
        static = _read_json(study.dft_dir / f"{name}.json")
        if part == "ir" and static is None:
            continue  # its static reference failed
        study.log(f"dft: {name} ({row['smiles']}) {part} at {labeler.level.name}")
        try:
            res = (dft_static(study, row, labeler) if part == "static"
                   else dft_vibrations(study, static, labeler))
        except Exception as exc:  # noqa: BLE001 - one molecule must not stop the stage
            _write_json(failed, {"name": name, "part": part,
                                 "error": f"{type(exc).__name__}: {exc}"})
            study.log(f"dft: {name} {part} FAILED: {exc}")
            continue
        _write_json(target, res)
        study.work["dft"] += 1
        out.setdefault(name, {}).update(res)
        what = (f"alpha_iso {res['polarizability_isotropic_bohr3']:.2f} bohr³" if part == "static"
                else f"{len(res['frequencies_cm-1'])} modes")
        study.log(f"dft: {name} {part}: {what}, {res['wall_s_this_call']:.0f} s")
    return out


def dft_results(study: Study, set_name: str | None = None) -> dict[str, dict]:
    """The finished DFT references of the molecules of ``set_name`` (Study.reference_molecules;
    None: the split's), by name: the static reference (``NAME.json``) with the harmonic one
    (``NAME.ir.json``) merged in when it is finished."""
    out = {}
    for row in study.reference_molecules(set_name):
        r = _read_json(study.dft_dir / f"{row['name']}.json")
        if r is not None:
            r.update(_read_json(study.dft_dir / f"{row['name']}.ir.json") or {})
            out[row["name"]] = r
    return out


def ir_references(study: Study) -> dict[str, dict]:
    """The DFT references of the IR molecules (``Study.ir_molecules``) whose harmonic part
    (frequencies, intensities) is finished."""
    listed = set(study.ir_molecules())
    return {m: r for m, r in dft_results(study).items()
            if "frequencies_cm-1" in r and m in listed}


def dft_structure(r: dict):
    """The DFT optimum of a static reference (``NAME.json``) with its Boys centres as pairs."""
    from emlpack.structure import Structure

    return Structure(numbers=np.array(r["numbers"]), positions=np.array(r["positions"]),
                     pairs=np.array(r["pairs"]).reshape(-1, 3), source=f"DFT optimum {r['name']}")


# ---------------------------------------------------------------------- polarizability
def stage_file(study: Study, stage: str, name: str, set_name: str | None = None) -> Path:
    """WORKDIR/STAGE/MODEL.json (the card's test molecules) or WORKDIR/STAGE/SET/MODEL.json
    (``set_name`` None: the split's, so ``val`` with split val)."""
    folder = study.workdir / stage
    set_name = set_name or study.split
    return (folder if set_name == "test" else folder / set_name) / f"{name}.json"


def _at_dft_optima(study: Study, stage: str, row: Callable[[object, object], dict],
                   set_name: str | None = None, only: list[str] | None = None) -> None:
    """Stage ``stage`` of every model at the DFT optimum of every reference molecule of
    ``set_name`` (None: the split's; ``only``: of these names alone): ``row(model,
    structure)`` (the DFT structure with its Boys centres) gives one molecule's JSON row; the
    model's file (``stage_file``) is skipped when it holds every reference molecule."""
    set_name = set_name or study.split
    refs = dft_results(study, set_name)
    if only is not None:
        refs = {m: r for m, r in refs.items() if m in set(only)}
    if not refs:
        source = ("the dft stage" if set_name != "val"
                  else "examples/eqm7/validation_references.py")
        study.log(f"{stage}: no DFT reference of the {set_name} molecules yet ({source}),"
                  " skipped")
        return
    for group, name, path in study.progress(study.require_models(), stage, "model"):
        target = stage_file(study, stage, name, set_name)
        if target.exists() and set(_read_json(target)["molecules"]) >= set(refs):
            study.log(f"{stage}: {set_name}/{name} exists, skipped")
            continue
        model, _, _ = _load(path)
        rows = {mol: row(model, dft_structure(r)) for mol, r in refs.items()}
        _write_json(target, {"group": group, "name": name, "model": str(path),
                             "set": set_name, "molecules": rows})
        study.work[stage] += 1
        study.log(f"{stage}: {set_name}/{name}: {len(rows)} molecules")


def stage_polarizability(study: Study) -> None:
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.response import molecule_response

    def row(model, s) -> dict:
        res = relax_pairs(model, s)[0]
        shift = float(np.linalg.norm(res.pairs - s.pairs, axis=1).max()) if s.n_pairs else 0.
        failure = res.reason or (f"a pair moved {shift:.2f} Å from its DFT centre"
                                 if shift > 0.5 else "")
        out = {"failure": failure, "max_pair_shift": shift}
        if not failure:
            try:
                resp = molecule_response(model, s.copy(pairs=res.pairs), relax_cores=False)
                out["polarizability_bohr3"] = resp.as_dict()["polarizability_bohr3"]
            except (np.linalg.LinAlgError, ValueError) as exc:
                out["failure"] = f"response failed: {exc}"
        return out

    for set_name in study.sets():
        _at_dft_optima(study, "polarizability", row, set_name)


def isotropic_error(tensor, reference) -> float:
    """|Δα_iso| / α_iso of a model's polarizability tensor against the DFT one (bohr³ both)."""
    ref = float(np.trace(np.asarray(reference))) / 3.0
    return abs(float(np.trace(np.asarray(tensor))) / 3.0 - ref) / ref


def polarizability_summary(study: Study, set_name: str | None = None) -> dict | None:
    """Polarizability errors of every model (and group ensemble) at the DFT optima of the
    molecules of ``set_name`` (None: the split's; the polarizability stage's files), None
    before any: components (bohr³: MAE, median), failures (``error_rate``) and the isotropic
    polarizability's relative error (``isotropic_median``: median of |Δα_iso|/α_iso over the
    molecules, ``isotropic_within_10pct``: how many within 10 %, of ``isotropic_compared``)."""
    refs = dft_results(study, set_name)
    per_group: dict[str, dict] = {}
    for group, name, _ in study.models():
        r = _read_json(stage_file(study, "polarizability", name, set_name))
        if r is None:
            continue
        err, iso, fails = [], [], 0
        for mol, row in r["molecules"].items():
            if mol not in refs:
                continue
            if row["failure"]:
                fails += 1
                continue
            err.append(np.array(row["polarizability_bohr3"])
                       - np.array(refs[mol]["polarizability_bohr3"]))
            iso.append(isotropic_error(row["polarizability_bohr3"],
                                        refs[mol]["polarizability_bohr3"]))
        e = np.abs(np.concatenate([x.ravel() for x in err])) if err else np.zeros(0)
        per_group.setdefault(group, {})[name] = {
            "mae": float(e.mean()) if e.size else None,
            "median": float(np.median(e)) if e.size else None,
            "isotropic_median": float(np.median(iso)) if iso else None,
            "isotropic_within_10pct": int(sum(x <= 0.1 for x in iso)),
            "isotropic_compared": len(iso),
            "error_rate": fails / max(len(r["molecules"]), 1), "n_molecules": len(r["molecules"]),
            "tensors": {m: row.get("polarizability_bohr3") for m, row in r["molecules"].items()}}
    if not per_group or not refs:
        return None
    comps = np.concatenate([np.ravel(r["polarizability_bohr3"]) for r in refs.values()])
    out = {"n_molecules": len(refs),
           "intrinsic_mae": float(np.abs(comps - np.median(comps)).mean()), "groups": {}}
    for group, models in per_group.items():
        # the ensemble: mean tensor over the group's models that did not fail
        ens_err = []
        for mol, ref in refs.items():
            ts = [m["tensors"].get(mol) for m in models.values()]
            ts = [t for t in ts if t is not None]
            if ts:
                ens_err.append(np.mean(ts, axis=0) - np.array(ref["polarizability_bohr3"]))
        e = np.abs(np.ravel(ens_err)) if ens_err else np.zeros(0)
        out["groups"][group] = {
            "per_model": {n: {k: v for k, v in m.items() if k != "tensors"}
                          for n, m in models.items()},
            "mae": mean_std([m["mae"] for m in models.values()]),
            "median": mean_std([m["median"] for m in models.values()]),
            "error_rate": mean_std([m["error_rate"] for m in models.values()]),
            "isotropic_median": mean_std([m["isotropic_median"] for m in models.values()]),
            # how many molecules each model puts within 10 % of DFT's α_iso (of n_molecules:
            # a failed molecule counts as not within)
            "isotropic_within_10pct": mean_std([m["isotropic_within_10pct"]
                                                for m in models.values()]),
            "ensemble_mae": float(e.mean()) if e.size else None,
            "ensemble_median": float(np.median(e)) if e.size else None,
        }
    return out


# ---------------------------------------------------------------------- ir
def stage_ir(study: Study) -> None:
    from emlpack.bonding import bonding_changes
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.ir import ir_spectrum
    from emlpack.properties.optimize import optimize

    c = study.cfg.get("ir", {})

    def row(model, s) -> dict:
        res = relax_pairs(model, s)[0]
        if res.reason:
            return {"failure": f"pair relaxation at the DFT geometry: {res.reason}"}
        try:
            o = optimize(model, s.copy(pairs=res.pairs), fmax=float(c.get("fmax", 1e-4)),
                         max_iterations=int(c.get("max_iterations", 100)))
            spec = ir_spectrum(model, o.structure)
        except (np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
            return {"failure": f"{type(exc).__name__}: {exc}"}
        changes = bonding_changes(s.numbers, s.positions, o.structure.positions)
        out = {"failure": "", "converged": bool(o.converged), "iterations": int(o.iterations),
               "reason": o.reason, "bonding_changes": changes,
               "rmsd_vs_dft_A": float(np.sqrt(((o.structure.positions - s.positions) ** 2)
                                              .sum(1).mean())),
               "frequencies": spec.frequencies.tolist(),
               "intensities": spec.intensities.tolist()}
        if changes:
            out["failure"] = "bonding changed: " + "; ".join(changes)
        elif o.pair_check:
            out["failure"] = f"broken electron pairs: {o.pair_check}"
        else:
            out["failure"] = not_a_minimum(out["frequencies"])
        return out

    if study.split != "test" and not ir_references(study):
        study.log(f"ir: no harmonic DFT reference of the {study.split} molecules"
                  f" ({study.dft_dir} holds polarizabilities), skipped")
        return
    _at_dft_optima(study, "ir", row, only=study.ir_molecules())


def not_a_minimum(frequencies) -> str:
    """A failure when the harmonic frequencies (cm⁻¹, imaginary ones negative) hold an
    imaginary mode (the optimisation ended on a saddle point, as ``emlp ir`` warns), else ''."""
    f = np.asarray(frequencies, dtype=float)
    n = int((f < 0).sum())
    return f"not a minimum: {n} imaginary mode(s) (lowest {f.min():.1f} cm⁻¹)" if n else ""


def ir_failure(row: dict) -> str:
    """Why a row of the ir stage has no spectrum to compare ('' when it has one): its recorded
    failure, or a saddle point (files written before the stage checked for one)."""
    return row.get("failure") or not_a_minimum(row.get("frequencies", []))


def freq_errors(a, b) -> tuple[np.ndarray, np.ndarray] | None:
    """The model's frequencies ``a`` minus the DFT ones ``b`` (cm⁻¹), modes matched in
    ascending order, and ``b`` sorted; None when the mode counts differ."""
    a, b = np.sort(np.asarray(a)), np.sort(np.asarray(b))
    if len(a) != len(b) or not len(a):
        return None
    return a - b, b


def band_errors(errors: list[tuple[np.ndarray, np.ndarray]]) -> list[dict]:
    """MAE and mean signed error (cm⁻¹) of the pooled modes in each of :data:`IR_BANDS` (by
    the DFT frequency)."""
    if not errors:
        return [{"band": list(band), "n": 0, "mae": None, "mean_error": None}
                for band in IR_BANDS]
    e = np.concatenate([d for d, _ in errors])
    ref = np.concatenate([b for _, b in errors])
    out = []
    for lo, hi in IR_BANDS:
        m = (ref >= lo) & (ref < hi)
        out.append({"band": [lo, hi], "n": int(m.sum()),
                    "mae": float(np.abs(e[m]).mean()) if m.any() else None,
                    "mean_error": float(e[m].mean()) if m.any() else None})
    return out


def bands_over_models(per_model) -> list[dict]:
    """Each band's modes per model (``n``), MAE and mean error as mean ± std over the models,
    from the models' :func:`band_errors` (``per_model``: dicts with ``"bands"``)."""
    bands = [m["bands"] for m in per_model]
    return [{"band": list(band), "n": [b[k]["n"] for b in bands],
             "mae": mean_std([b[k]["mae"] for b in bands]),
             "mean_error": mean_std([b[k]["mean_error"] for b in bands])}
            for k, band in enumerate(IR_BANDS)]


def best_uniform_scale(errors: list[tuple[np.ndarray, np.ndarray]]) -> dict | None:
    """The uniform scale factor s of the model's frequencies that minimises the MAE of the
    pooled modes against DFT (cm⁻¹), as ``errors`` (model minus DFT, DFT) of
    :func:`freq_errors`: the median of DFT/model weighted by the model frequency (Σ|s a - b| =
    Σ a |s - b/a|); ``mae`` at s and ``mae_unscaled`` (s = 1). Modes at or below 0 ignored."""
    if not errors:
        return None
    a = np.concatenate([d + b for d, b in errors])
    b = np.concatenate([b for _, b in errors])
    a, b = a[a > 0], b[a > 0]
    if not len(a):
        return None
    order = np.argsort(b / a)
    ratio, weight = (b / a)[order], a[order]
    s = float(ratio[np.searchsorted(np.cumsum(weight), 0.5 * weight.sum())])
    return {"factor": s, "mae": float(np.abs(s * a - b).mean()),
            "mae_unscaled": float(np.abs(a - b).mean())}


def rmsd_mae_pearson(per_model) -> float | None:
    """Whether a molecule's frequency error follows its optimum's distance from DFT's: the
    Pearson correlation of ``per_molecule`` MAE and ``rmsd_per_molecule`` over every (model,
    molecule) with both; None for fewer than 3 or a constant side."""
    pairs = np.array([(m["rmsd_per_molecule"][mol], mae) for m in per_model
                      for mol, mae in m["per_molecule"].items()
                      if mae is not None and mol in m["rmsd_per_molecule"]])
    if len(pairs) < 3 or not np.ptp(pairs, axis=0).all():
        return None
    return float(np.corrcoef(pairs.T)[0, 1])


def ir_summary(study: Study) -> dict | None:
    from ase import Atoms

    refs = ir_references(study)
    # the listed molecules (ir.molecules: every test molecule) without a finished DFT Hessian
    missing = [m for m in study.ir_molecules() if m not in refs]
    out: dict = {"n_molecules": len(refs), "n_listed": len(study.ir_molecules()),
                 "missing": missing, "groups": {},
                 "molecules": {m: {"formula": Atoms(numbers=r["numbers"]).get_chemical_formula(),
                                   "modes": len(r["frequencies_cm-1"])}
                               for m, r in sorted(refs.items())}}
    for group, name, _ in study.models():
        r = _read_json(stage_file(study, "ir", name))
        if r is None:
            continue
        # a failed optimisation (bonding changed: another molecule, e.g. a tautomer; broken
        # pairs; a saddle point) has no spectrum to compare: excluded from the MAE, listed
        per_mol, excluded, errors, rmsd = {}, {}, [], {}
        for mol, row in r["molecules"].items():
            if mol not in refs:
                continue
            why = ir_failure(row)
            if why:
                excluded[mol] = why
            elif "frequencies" in row:
                err = freq_errors(row["frequencies"], refs[mol]["frequencies_cm-1"])
                per_mol[mol] = None if err is None else float(np.abs(err[0]).mean())
                if row.get("rmsd_vs_dft_A") is not None:
                    rmsd[mol] = float(row["rmsd_vs_dft_A"])
                if err is not None:
                    errors.append(err)
        vals = [v for v in per_mol.values() if v is not None]
        g = out["groups"].setdefault(group, {"per_model": {}})
        g["per_model"][name] = {
            "frequency_mae": float(np.mean(vals)) if vals else None,
            "per_molecule": per_mol,
            "bands": band_errors(errors),
            "uniform_scale": best_uniform_scale(errors),
            # the model's optimum against the DFT one (Å): mean and largest over the molecules
            # (not aligned: the optimisation moves no rigid body, the Kabsch-aligned RMSD of
            # aug-s0's optima of qm7-1404, qm7-0031 and extra-0000 is within 0.004 Å)
            "rmsd_vs_dft": float(np.mean(list(rmsd.values()))) if rmsd else None,
            "rmsd_vs_dft_max": max(rmsd.values()) if rmsd else None,
            "rmsd_per_molecule": rmsd,
            "excluded": excluded,
            "failures": {m: ir_failure(row) for m, row in r["molecules"].items()
                         if ir_failure(row)}}
    if not out["groups"]:
        return None
    for g in out["groups"].values():
        g["frequency_mae"] = mean_std([m["frequency_mae"] for m in g["per_model"].values()])
        g["rmsd_vs_dft"] = mean_std([m["rmsd_vs_dft"] for m in g["per_model"].values()])
        g["rmsd_vs_dft_max"] = max((m["rmsd_vs_dft_max"] for m in g["per_model"].values()
                                    if m["rmsd_vs_dft_max"] is not None), default=None)
        g["bands"] = bands_over_models(g["per_model"].values())
        scales = [m["uniform_scale"] for m in g["per_model"].values() if m["uniform_scale"]]
        g["uniform_scale"] = {k: mean_std([x[k] for x in scales])
                              for k in ("factor", "mae", "mae_unscaled")} if scales else None
        g["per_molecule"] = {mol: mean_std([m["per_molecule"].get(mol)
                                            for m in g["per_model"].values()])
                             for mol in out["molecules"]}
        g["compared"] = sum(len(m["per_molecule"]) for m in g["per_model"].values())
        g["rmsd_mae_pearson"] = rmsd_mae_pearson(g["per_model"].values())
        g["excluded"] = {f"{name}/{mol}": why for name, m in g["per_model"].items()
                         for mol, why in m["excluded"].items()}
    return out


def figure4(study: Study, out_dir: Path) -> list[str]:
    """Figure 4 (``out_dir/figure4_ir.png``): the harmonic IR spectra of the figure's
    molecules, DFT against the mean spectrum of each group of the study's models; the curves'
    labels (none drawn: no DFT Hessian of those molecules yet)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from emlpack._files import write_figure_atomic
    from emlpack.properties.ir import lorentzian

    c = study.cfg.get("ir", {})
    fwhm = float(c.get("fwhm", 10.0))
    refs = ir_references(study)
    mols = [m for m in c.get("figure_molecules", list(IR_MOLECULES)) if m in refs]
    if not mols:
        mols = list(refs)[:2]
    if not mols:
        return []
    per_model = {name: _read_json(stage_file(study, "ir", name))
                 for _, name, _ in study.models()}
    grid = np.arange(0.0, 4000.0, 1.0)
    labels: list[str] = []
    fig, axes = plt.subplots(1, len(mols), figsize=(6.5 * len(mols), 4.2), squeeze=False)
    for ax, mol in zip(axes[0], mols, strict=True):
        ref = refs[mol]
        ax.plot(grid, lorentzian(grid, ref["frequencies_cm-1"], ref["intensities_km_per_mol"],
                                 fwhm), "k", lw=1.2, label=f"DFT ({ref['level']})")
        labels.append(f"{mol}: DFT ({ref['level']})")
        for k, (group, colour) in enumerate((("aug", "C2"), ("noaug", "C3"))):
            rows = [r["molecules"].get(mol, {}) for name, r in per_model.items()
                    if r and name.startswith(group + "-")]
            curves = [lorentzian(grid, row["frequencies"], row["intensities"], fwhm)
                      for row in rows if "frequencies" in row and not ir_failure(row)]
            if curves:
                label = f"eMLP {GROUP_LABEL[group]} (mean of {len(curves)})"
                ax.plot(grid, np.mean(curves, axis=0), color=colour, lw=1.0,
                        ls="-" if k == 0 else "--", label=label)
                labels.append(f"{mol}: {label}")
        ax.set_title(f"{IR_MOLECULES.get(mol, mol)} ({mol})")
        ax.set_xlabel("wavenumber (cm$^{-1}$)")
        ax.set_ylabel(f"absorbance (km/mol/cm$^{{-1}}$, FWHM {fwhm:g} cm$^{{-1}}$)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_figure_atomic(out_dir / "figure4_ir.png", fig, dpi=110)
    plt.close(fig)
    return labels


# ---------------------------------------------------------------------- md
def _md_start(study: Study, row: dict):
    """The DFT optimum with its Boys centres, else the start geometry (pairs guessed)."""
    from emlpack.structure import Structure

    r = _read_json(study.dft_dir / f"{row['name']}.json")
    if r is not None:
        return dft_structure(r), "DFT optimum"
    from ase import Atoms

    from emlpack.pairs.guess import guess_pairs

    numbers, pos, origin = _start_geometry(study, row)
    pairs = guess_pairs(Atoms(numbers=numbers, positions=pos))
    return Structure(numbers=numbers, positions=pos, pairs=pairs, source=row["name"]), \
        f"{origin}, pairs guessed"


def stage_md(study: Study) -> None:
    from ase.calculators.calculator import CalculationFailed

    from emlpack.bonding import bonding_changes
    from emlpack.dynamics.analysis import TrajectoryAnalysisError, analyze_trajectory
    from emlpack.dynamics.md import MDWatchdogError, run_md
    from emlpack.io.extxyz import read_structures

    c = study.cfg.get("md", {})
    dt_fs = float(c.get("dt_fs", 0.5))
    steps = int(round(float(c.get("time_fs", 500.0)) / dt_fs))
    discard = int(c.get("discard_steps", 10))
    for group, name, path in study.progress(study.require_models(), "md", "model"):
        model = None
        for row in study.md_molecules():
            run = study.workdir / "md" / name / row["name"]
            target = run / "analysis.json"
            if target.exists():
                continue
            if model is None:
                model, _, _ = _load(path)
            s, origin = _md_start(study, row)
            stopped = ""
            t0 = time.perf_counter()
            try:
                run_md(model, s, steps, run, dt_fs=dt_fs,
                       temperature_K=float(c.get("temperature_K", 300.0)), ensemble="nvt",
                       seed=int(c.get("seed", 0)), relax=str(c.get("relax", "corrected")),
                       checkpoint_every=int(c.get("checkpoint_every", 50)),
                       log_every=int(c.get("log_every", 100)))
            except (MDWatchdogError, CalculationFailed) as exc:
                stopped = f"{type(exc).__name__}: {exc}"
            out: dict = {"group": group, "model": name, "molecule": row["name"],
                         "start": origin, "steps": steps, "stopped": stopped,
                         "wall_s": time.perf_counter() - t0}
            try:
                a = analyze_trajectory(run, discard_steps=discard)
                out["analysis"] = a.as_dict()
                out["classification"] = "unstable" if stopped else a.classification
            except (TrajectoryAnalysisError, FileNotFoundError) as exc:
                out["analysis"] = None
                out["classification"] = "unstable"
                out["analysis_error"] = str(exc)
            frames = read_structures(run / "trajectory.xyz") if (run / "trajectory.xyz") \
                .exists() else []
            changes: list[str] = []
            for f in frames:
                changes = bonding_changes(s.numbers, s.positions, f.positions)
                if changes:
                    out["bonding_changed_at_step"] = int(f.info.get("step", -1))
                    break
            out["bonding_changed"] = bool(changes)
            out["bonding_changes"] = changes
            out["n_frames"] = len(frames)
            _write_json(target, out)
            study.work["md"] += 1
            study.log(f"md: {name}/{row['name']}: {out['classification']}"
                      + (f", bonding changed ({changes[0]})" if changes else "")
                      + (f", stopped: {stopped}" if stopped else ""))


def figure3(study: Study, summary: dict, out_dir: Path) -> dict[str, list[str]]:
    """Figure 3 of the runs in ``summary`` (:func:`md_summary`, with its analyses):
    ``out_dir/figure3_md.png`` (panel a: slope against largest jump of every run, coloured by
    group) and ``figure3_series.png`` (panels b, c: the conserved quantity of one run of each
    class, among the runs whose trajectory is in the work directory). Returns each file's
    groups or runs shown."""
    from emlpack.dynamics.analysis import (
        ConservedAnalysis,
        plot_conserved,
        plot_conserved_series,
    )

    if not summary["analyses"]:
        return {}
    out_dir.mkdir(parents=True, exist_ok=True)
    discard = int(study.cfg.get("md", {}).get("discard_steps", 10))
    runs, groups = [], []
    for r in summary["analyses"]:
        a = r["analysis"]
        runs.append(ConservedAnalysis(
            source=r["model"] + "/" + r["molecule"], n_atoms=a["n_atoms"],
            n_frames=a["n_frames"], n_discarded=a["n_discarded"],
            first_step=a["first_step"], last_step=a["last_step"],
            stride_steps=a["stride_steps"], duration=a["duration_fs"],
            slope=a["slope_eV_per_fs_per_atom"], intercept=a["intercept_eV_per_atom"],
            max_jump=a["max_jump_eV_per_atom"], max_jump_step=a["max_jump_step"],
            residual_std=a["residual_std_eV_per_atom"], drift=a["drift_eV_per_atom"],
            classification=a["classification"], stopped=r["stopped"] or ""))
        groups.append(GROUP_LABEL[r["group"]])
    counts = [f"{GROUP_LABEL[g]}: {v['stable']}/{v['transition']}/{v['unstable']}"
              for g, v in summary["groups"].items()]
    plot_conserved(runs, out_dir / "figure3_md.png", labels=[""] * len(runs), groups=groups,
                   title="runs stable/transition/unstable\n" + "; ".join(counts))
    shown = {"figure3_md.png": counts}
    # panels (b) and (c): one run of each class present (stable, transition, unstable) among
    # the runs whose trajectory is here (study_outputs.py restores analyses only), whole 500 fs
    # runs first (one the watchdog stopped shows only its start); the legend gives the study's
    # class (a stopped run is unstable whatever its trajectory shows)
    examples = {}
    for r in sorted(summary["analyses"], key=lambda r: bool(r["stopped"])):
        if (study.workdir / "md" / r["model"] / r["molecule"] / "trajectory.xyz").exists():
            examples.setdefault(r["classification"], r)
    if examples:
        labels = [f"{r['model']}/{r['molecule']}" for r in examples.values()]
        plot_conserved_series(
            [study.workdir / "md" / r["model"] / r["molecule"] for r in examples.values()],
            out_dir / "figure3_series.png", labels=labels, discard_steps=discard,
            classes=[r["classification"] + (" (stopped by the watchdog)" if r["stopped"]
                                            else "") for r in examples.values()])
        shown["figure3_series.png"] = labels
    return shown


def md_summary(study: Study) -> dict | None:
    rows = []
    for _, name, _ in study.models():
        for row in study.md_molecules():
            r = _read_json(study.workdir / "md" / name / row["name"] / "analysis.json")
            if r is not None:
                rows.append(r)
    if not rows:
        return None
    groups: dict = {}
    for r in rows:
        g = groups.setdefault(r["group"], {"runs": 0, "stable": 0, "transition": 0,
                                           "unstable": 0, "bonding_changed": 0, "stopped": 0,
                                           "max_jump_max": None})
        g["runs"] += 1
        g[r["classification"]] += 1
        g["bonding_changed"] += int(r["bonding_changed"])
        g["stopped"] += int(bool(r["stopped"]))
        jump = (r.get("analysis") or {}).get("max_jump_eV_per_atom")
        if jump is not None:
            g["max_jump_max"] = max(jump, g["max_jump_max"] or 0.0)
    for g in groups.values():
        g["unstable_pct"] = 100.0 * g["unstable"] / g["runs"]
    return {"groups": groups, "runs": rows,
            "analyses": [r for r in rows if r.get("analysis")]}


# ---------------------------------------------------------------------- table
def eval_summary(study: Study, set_name: str) -> dict | None:
    """Mean ± std over each group's models of every Table 2/3 entry on ``set_name``."""
    per = {}
    for group, name, _ in study.models():
        r = _read_json(study.workdir / "eval" / set_name / f"{name}.json")
        if r is not None:
            per.setdefault(group, []).append(r)
    if not per:
        return None
    out: dict = {"groups": {}}
    for group, rs in per.items():
        g: dict = {"models": [r["name"] for r in rs], "n_structures": rs[0]["n_structures"],
                   "static": {}, "dynamic": {}}
        out["intrinsic_static"] = rs[0]["intrinsic"]
        for stat in ("mae", "median"):
            g["static"][stat] = {k: mean_std([r["static"][k][stat] for r in rs])
                                 for k in ("energy", "forces", "pair_forces")}
        if all("pair_field_slope" in r["static"] for r in rs):
            g["static"]["pair_field_slope"] = mean_std(
                [r["static"]["pair_field_slope"] for r in rs])
        if all("dynamic" in r for r in rs):
            out["intrinsic_dynamic"] = rs[0]["dynamic"]["intrinsic"]
            for stat in ("mae", "median"):
                g["dynamic"][stat] = {k: mean_std([r["dynamic"][k][stat] for r in rs])
                                      for k in ("energy", "forces", "dipole")}
            g["dynamic"]["error_rate"] = mean_std([r["dynamic"]["error_rate"] for r in rs])
        out["groups"][group] = g
    return out


def _ir_bands_md(ir: dict) -> list[str]:
    """The frequency errors by band of the DFT frequency (``ir_summary``'s ``bands``)."""
    groups = {g: v for g, v in ir["groups"].items() if v.get("bands")}
    if not groups:
        return []
    lines = ["By band of the DFT frequency (the compared molecules' modes pooled; MAE and mean"
             " signed error, model minus DFT, mean (± std) over models, cm⁻¹; modes per model"
             " in brackets):", "",
             "| band [cm⁻¹] | " + " | ".join(f"{GROUP_LABEL[g]}: MAE | {GROUP_LABEL[g]}:"
                                              " mean error" for g in groups) + " |",
             "|---|" + "---|---|" * len(groups)]
    for k, band in enumerate(IR_BANDS):
        cells = []
        for v in groups.values():
            b = v["bands"][k]
            n = sorted(set(b["n"]))
            count = f"{n[0]}" if len(n) == 1 else f"{n[0]}-{n[-1]}"
            cells += [f"{_ms(b['mae'])} [{count}]", _ms(b["mean_error"])]
        lines.append(f"| {band[0]:g}-{band[1]:g} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _ir_molecules_md(ir: dict, base: dict | None = None, label: str | None = None) -> list[str]:
    """The frequency MAE of each test molecule with a DFT Hessian (``ir_summary``'s
    ``per_molecule``), mean (± std) over the models that compared it; with ``base`` (the
    earlier study's ``ir_summary``) its columns named ``label`` beside ours."""
    groups = {g: v for g, v in ir["groups"].items() if v.get("per_molecule")}
    if not groups or not ir.get("molecules"):
        return []
    columns = [(GROUP_LABEL[g], v) for g, v in groups.items()]
    if base:
        columns += [(f"{GROUP_LABEL[g]}, {label}", v) for g, v in base["groups"].items()
                    if v.get("per_molecule")]
    lines = ["By molecule (frequency MAE, cm⁻¹, mean (± std) over the models; in brackets the"
             " models compared when an optimisation failed):", "",
             "| molecule | formula | modes | " + " | ".join(c for c, _ in columns) + " |",
             "|---|---|---|" + "---|" * len(columns)]
    for mol, info in ir["molecules"].items():
        name = IR_MOLECULES.get(mol)
        cells = []
        for _, v in columns:
            d = v["per_molecule"].get(mol) or {}
            n, n_models = d.get("n", 0), len(v["per_model"])
            cells.append(_ms(d) + (f" [{n} of {n_models}]" if n < n_models else ""))
        lines.append(f"| {mol}{f' ({name})' if name else ''} | {info['formula']} |"
                     f" {info['modes']} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _uniform_scale_md(ir: dict) -> list[str]:
    """Each group's best uniform scale factor of the frequencies (``ir_summary``)."""
    groups = {g: v["uniform_scale"] for g, v in ir["groups"].items() if v.get("uniform_scale")}
    if not groups:
        return []
    return ["A uniform scale factor of the model's frequencies (each model's best, minimising"
            " its pooled modes' MAE; mean (± std) over models): " + "; ".join(
                f"{GROUP_LABEL[g]} {_ms(v['factor'], digits=3)}, MAE {_ms(v['mae_unscaled'])}"
                f" -> {_ms(v['mae'])} cm⁻¹" for g, v in groups.items()) + ".", ""]


def _rmsd_correlation_md(ir: dict) -> str:
    r = {g: v["rmsd_mae_pearson"] for g, v in ir["groups"].items()
         if v.get("rmsd_mae_pearson") is not None}
    if not r:
        return ""
    return (" Across the compared optimisations (one per model and molecule) a molecule's"
            " frequency MAE and its optimum's RMSD correlate with Pearson r = "
            + ", ".join(f"{v:.2f} ({GROUP_LABEL[g]})" for g, v in r.items()) + ".")


def _ms(d: dict | None, scale: float = 1.0, digits: int = 1) -> str:
    if not d or d.get("mean") is None:
        return "–"
    if d["n"] == 1:
        return f"{scale * d['mean']:.{digits}f}"
    return f"{scale * d['mean']:.{digits}f} (± {scale * d['std']:.{digits}f})"


def _paper(p) -> str:
    return f"{p[0]:g} (± {p[1]:g})"


def _val(v, digits: int = 1, scale: float = 1.0) -> str:
    return "–" if v is None else f"{scale * v:.{digits}f}"


def targets(result: dict) -> list[dict]:
    """Issue 15's targets with the measured values (None when not measured yet)."""
    out = []
    ev = (result.get("evaluation") or {}).get("test")
    ratio = None
    if ev and "aug" in ev["groups"]:
        f = ev["groups"]["aug"]["static"]["mae"]["forces"]["mean"]
        ratio = f / ev["intrinsic_static"]["forces"] if f else None
    out.append({"target": "static core-force MAE (augmented) <= 1/10 of the intrinsic"
                          " variability (paper 1/23)",
                "measured": None if ratio is None else f"1/{1 / ratio:.1f}" if ratio else "0",
                "met": None if ratio is None else ratio <= 0.1})
    rate = noaug = None
    if ev and "aug" in ev["groups"] and ev["groups"]["aug"]["dynamic"]:
        rate = 100 * ev["groups"]["aug"]["dynamic"]["error_rate"]["mean"]
        if "noaug" in ev["groups"] and ev["groups"]["noaug"]["dynamic"]:
            noaug = 100 * ev["groups"]["noaug"]["dynamic"]["error_rate"]["mean"]
    out.append({"target": "augmented dynamic error rate <= 2 % (paper 0.4 %), below the"
                          " non-augmented models'",
                "measured": None if rate is None else
                f"{rate:.2f} % (non-augmented {_val(noaug, 2)} %)",
                # "below": strictly, unless both are zero (nothing left to improve); not
                # known until the non-augmented models are evaluated
                "met": None if rate is None or (rate <= 2.0 and noaug is None) else bool(
                    rate <= 2.0 and (rate < noaug or rate == noaug == 0.0))})
    pol = result.get("polarizability")
    med = None
    if pol and "aug" in pol["groups"]:
        med = pol["groups"]["aug"]["median"]["mean"]
    out.append({"target": "polarizability median error (augmented) <= 0.5 bohr³ (paper 0.31)",
                "measured": None if med is None else f"{med:.3f} bohr³",
                "met": None if med is None else med <= 0.5})
    ir = result.get("ir")
    mae = None
    if ir and "aug" in ir["groups"]:
        mae = ir["groups"]["aug"]["frequency_mae"]["mean"]
    n_test = result["data"]["by_split"]["test"]["molecules"]
    partial = (f" ({ir['n_molecules']} of {n_test} molecules so far)"
               if ir and ir["n_molecules"] < n_test else "")
    if mae is not None and ir["groups"]["aug"].get("excluded"):
        n = len(ir["groups"]["aug"]["excluded"])
        partial += f"; {n} failed optimisation{'s' if n > 1 else ''} excluded"
    out.append({"target": "harmonic IR frequency MAE (augmented) <= 30 cm⁻¹ (paper ~15)",
                "measured": None if mae is None else f"{mae:.1f} cm⁻¹{partial}",
                "met": None if mae is None else mae <= 30.0})
    md = result.get("md")
    g = (md or {}).get("groups", {}).get("aug")
    ok = None
    if g:
        ok = (g["max_jump_max"] is not None and g["max_jump_max"] < 0.01
              and g["unstable"] == 0 and g["bonding_changed"] == 0)
    out.append({"target": "every augmented MD run: max |ΔE_cons| < 0.01 eV/atom and no change"
                          " of bonding",
                "measured": None if not g else
                f"{g['runs']} runs, largest jump {_val(g['max_jump_max'], 5)} eV/atom,"
                f" {g['unstable']} unstable, {g['bonding_changed']} with bonding changed",
                "met": ok})
    return out


def _part(name: str, value, limit: float, better: str) -> dict:
    """One measured part of a target: ``value`` against ``limit``, ``better`` "lower" (met
    when value <= limit) or "higher" (value >= limit); value None: not measured."""
    return {"name": name, "value": None if value is None else float(value), "limit": limit,
            "better": better}


def part_met(part: dict) -> bool | None:
    """Whether one part of a target is met (None: not measured)."""
    if part["value"] is None:
        return None
    return (part["value"] <= part["limit"] if part["better"] == "lower"
            else part["value"] >= part["limit"])


def parts_met(parts: list[dict]) -> bool | None:
    """A target of several parts: False when any measured part misses, None when none misses
    but one is not measured, else True."""
    met = [part_met(p) for p in parts]
    return False if False in met else None if None in met else True


def targets_issue51(result: dict) -> list[dict]:
    """Issue 51's targets (its Targets section: the test molecules, augmented models) with
    the measured values: each ``{"key", "target", "measured", "met", "parts"}``, the parts
    the numbers :func:`ship_rule` compares (value None: not measured). Reads a results.json
    of any version (v1's lacks the isotropic counts: that part is then not measured)."""
    out = []

    def add(key: str, target: str, measured: str | None, parts: list[dict]) -> None:
        measured = measured if any(p["value"] is not None for p in parts) else None
        out.append({"key": key, "target": target, "measured": measured,
                    "met": parts_met(parts), "parts": parts})

    ev = (result.get("evaluation") or {}).get("test") or {}
    aug = (ev.get("groups") or {}).get("aug") or {}
    static = aug.get("static") or {}
    f = (((static.get("mae") or {}).get("forces")) or {}).get("mean")
    ratio = f / ev["intrinsic_static"]["forces"] if f is not None else None
    add("core_forces", "static core-force MAE (augmented) <= 1/10 of the intrinsic variability"
        " (paper 1/23)", None if ratio is None else f"1/{1 / ratio:.1f}" if ratio else "0",
        [_part("MAE / intrinsic variability", ratio, 0.1, "lower")])
    slope = (static.get("pair_field_slope") or {}).get("mean")
    add("pair_field_slope", "pair-field slope (augmented) <= 0.10", _val(slope, 3),
        [_part("slope", slope, 0.10, "lower")])
    pol = ((result.get("polarizability") or {}).get("groups") or {}).get("aug") or {}
    med = (pol.get("median") or {}).get("mean")
    within = (pol.get("isotropic_within_10pct") or {}).get("mean")
    n_pol = (result.get("polarizability") or {}).get("n_molecules")
    add("polarizability", "polarizability (augmented): component median error <= 0.8 bohr³"
        " and isotropic value within 10 % of DFT for >= 13 of the 15 molecules",
        f"median {_val(med, 2)} bohr³; α_iso within 10 % of DFT's: " + (
            f"{within:g} of {n_pol} molecules (mean over models)" if within is not None
            else "not recorded"),
        [_part("component median error [bohr³]", med, 0.8, "lower"),
         _part("molecules with α_iso within 10 %", within, 13, "higher")])
    ir = result.get("ir") or {}
    g = (ir.get("groups") or {}).get("aug")
    n_test = result["data"]["by_split"]["test"]["molecules"]
    mae = excluded = missing = None
    if g:
        mae = (g.get("frequency_mae") or {}).get("mean")
        excluded = len(g.get("excluded") or {})
        # molecules of the list without a DFT Hessian (a results.json before ir.molecules: the
        # test molecules less those compared)
        missing = (len(ir["missing"]) if "missing" in ir
                   else max(n_test - ir.get("n_molecules", 0), 0))
    add("ir_frequencies", "harmonic IR frequency MAE (augmented) <= 30 cm⁻¹ over the 15"
        " molecules, no optimisation excluded",
        f"{_val(mae, 1)} cm⁻¹ over {ir.get('n_molecules')} molecules; {excluded} failed"
        f" optimisation(s) excluded" + (f"; {missing} without a DFT Hessian" if missing else ""),
        [_part("frequency MAE [cm⁻¹]", mae, 30.0, "lower"),
         _part("optimisations excluded", excluded, 0, "lower"),
         _part("molecules without a DFT Hessian", missing, 0, "lower")])
    dyn = aug.get("dynamic") or {}
    rate = (dyn.get("error_rate") or {}).get("mean")
    rate = None if rate is None else 100 * rate
    add("dynamic_error_rate", "augmented dynamic error rate <= 1 % (paper 0.4 %)",
        None if rate is None else f"{rate:.2f} %", [_part("error rate [%]", rate, 1.0, "lower")])
    md = ((result.get("md") or {}).get("groups") or {}).get("aug") or {}
    add("md", "augmented MD: >= 57 of 60 runs stable, none with changed bonding",
        f"{md.get('stable')} of {md.get('runs')} stable, {md.get('bonding_changed')} with"
        " bonding changed" if md else None,
        [_part("stable runs", md.get("stable"), 57, "higher"),
         _part("runs with changed bonding", md.get("bonding_changed"), 0, "lower")])
    return out


#: the target sets a study reports (``targets`` in config.yaml): issue 15's (v1) or issue 51's
TARGETS = {"issue15": targets, "issue51": targets_issue51}


def _target_set(cfg: dict) -> str:
    name = str(cfg.get("targets") or "issue15")
    if name not in TARGETS:
        raise SystemExit(f"targets: one of {', '.join(TARGETS)}, got {name!r}")
    return name


def ship_rule(ours: list[dict], baseline: list[dict]) -> dict:
    """Issue 51, item 7: a new ensemble ships under the old name when it beats the old one on
    every target the old one misses. ``ours``, ``baseline``: :func:`targets_issue51` of each
    study. On a target the baseline misses (or did not measure), ours beats it when it meets
    the target, or when every part is met or strictly better than the baseline's (a part the
    baseline did not measure must be met); a part ours did not measure never beats. Returns
    ``{"ship": bool, "not_beaten": [{"key", "target", "why"}], "regressed": [...]}``,
    ``regressed`` (not part of the rule, reported beside it): targets the baseline meets and
    ours does not."""
    mine = {t["key"]: t for t in ours}
    not_beaten, regressed = [], []
    for base in baseline:
        t = mine.get(base["key"])
        if t is None:
            not_beaten.append({"key": base["key"], "target": base["target"],
                               "why": "not measured"})
            continue
        if base["met"] is True:
            if t["met"] is not True:
                regressed.append({"key": t["key"], "target": t["target"],
                                  "why": "met before, " + ("not measured" if t["met"] is None
                                                           else "missed now")})
            continue
        if t["met"] is True:
            continue
        base_parts = {p["name"]: p for p in base.get("parts") or ()}
        why = []
        for p in t["parts"]:
            b = base_parts.get(p["name"], {}).get("value")
            if p["value"] is None:
                why.append(f"{p['name']}: not measured")
            elif part_met(p):
                continue
            elif b is None:
                why.append(f"{p['name']}: {p['value']:.4g} misses {p['limit']:g}, and the"
                           " baseline's is not recorded")
            elif not (p["value"] < b if p["better"] == "lower" else p["value"] > b):
                why.append(f"{p['name']}: {p['value']:.4g}, baseline {b:.4g} (target"
                           f" {'<=' if p['better'] == 'lower' else '>='} {p['limit']:g})")
        if why:
            not_beaten.append({"key": t["key"], "target": t["target"], "why": "; ".join(why)})
    return {"ship": not not_beaten, "not_beaten": not_beaten, "regressed": regressed}


def training_setup(best: Path) -> dict | None:
    """What one model's training was, from its run folder (``config.yaml`` as resolved,
    ``log.csv``): architecture, batch, learning rate, optimizer steps and hours of training
    (the sum of its epoch times); None without them."""
    import yaml

    from emlpack.nn.potential import ModelConfig

    run = best.parent
    if not (run / "config.yaml").exists() or not (run / "log.csv").exists():
        return None
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    rows = list(csv.DictReader((run / "log.csv").open()))
    # the short-range parameters (SchNet's; a run before the families saved them flat)
    m, t = ModelConfig.from_dict(cfg["model"]).short_range, cfg["training"]
    return {**{k: m.get(k) for k in ("n_features", "n_filters", "n_rbf", "n_interactions",
                                     "message_norm")},
            "batch_size": t["batch_size"], "lr": t["lr"], "dtype": t.get("dtype"),
            "steps": int(rows[-1]["step"]) if rows else 0,
            "hours": sum(float(r["epoch_time"] or 0) for r in rows) / 3600}


def data_summary(study: Study) -> dict:
    """The data set's size, split and training domain; ``complete``: the campaign's target is
    reached (None for a folder without the campaign's settings, e.g. a prefix of shards)."""
    from emlpack.errors import EmlpackError
    from emlpack.qm.campaign import campaign_target

    try:
        complete = bool(campaign_target(study.data)[1]["reached"])
    except (EmlpackError, OSError, KeyError, ValueError):  # no campaign.yaml, say
        complete = None
    data = study.shards()
    split = data.split_indices()
    mols = {k: len({data.structures[i].info.get("molecule_id") for i in v})
            for k, v in split.items()}
    return {"path": str(study.data), "shards": len(data.shards),
            "configurations": len(data.structures),
            "by_split": {k: {"configurations": int(len(v)), "molecules": mols[k]}
                         for k, v in split.items()},
            "molecules_listed": len(data.molecules),
            "hydrides": data.hydrides is not None, "failures": len(data.failures),
            "complete": complete, "train_domain": study.train_domain()}


def stage_table(study: Study, out_dir: Path | None = None) -> dict:
    study.require_test_split("table", "the study's tables are the test molecules'; the"
                             " bake-off's is examples/eqm7/bakeoff.py table")
    out_dir = Path(out_dir or study.cfg.get("results_dir", HERE))
    models = study.models()
    training = {}
    for _, name, path in models:
        training[name] = _read_json(path.parent / "done.json")
    result = {
        "generated": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "status": study.cfg.get("status", "preliminary"),
        "data": data_summary(study),
        "models": {name: str(path) for _, name, path in models},
        "training": training,
        "training_setup": {name: training_setup(path) for _, name, path in models},
        "train_config": study.cfg.get("training", {}),
        "dft_level": study.cfg.get("dft", {}).get("level", "paper"),
        "evaluation": {s: eval_summary(study, s) for s in ("test", "pbe0_subset")},
        "polarizability": polarizability_summary(study),
        "polarizability_pbe0_subset": polarizability_summary(study, "pbe0_subset"),
        "ir": ir_summary(study),
        "md": md_summary(study),
        "paper": PAPER,
    }
    # the figures of this table's models, beside results.md (a stage run on some groups
    # only does not decide what the table shows)
    figures = {}
    if result["ir"]:
        figures["figure4_ir.png"] = figure4(study, out_dir)
    if result["md"]:
        figures.update(figure3(study, result["md"], out_dir))
        result["md"].pop("analyses", None)
    result["figures"] = {name: shown for name, shown in figures.items() if shown}
    second = study.cfg.get("evaluate", {}).get("second_test_set")
    if result["evaluation"]["pbe0_subset"] is None:
        result["evaluation"]["pbe0_subset_note"] = (
            f"{second}: not found or not evaluated; the second test set was skipped")
    if study.cfg.get("title"):
        result["title"] = study.cfg["title"]
    result["targets_of"] = _target_set(study.cfg)
    result["targets"] = TARGETS[result["targets_of"]](result)
    baseline = load_baseline(study.cfg)
    if baseline:
        path = _resolve(study.cfg["baseline"]["results"])
        result["baseline"] = {
            "label": study.cfg["baseline"].get("label") or "v1",
            "results": _repo_relative(path), "generated": baseline.get("generated"),
            # its figures from results.md's folder (links beside ours)
            "relative_dir": os.path.relpath(path.resolve().parent, out_dir.resolve()),
            "targets": TARGETS[result["targets_of"]](baseline)}
        if result["targets_of"] == "issue51":
            result["ship"] = ship_rule(result["targets"], result["baseline"]["targets"])
    _write_json(out_dir / "results.json", result)
    _write_text(out_dir / "results.md", markdown(result, study_notes(study.cfg), baseline))
    study.work["table"] += 1
    study.log(f"table: {out_dir / 'results.md'}")
    return result


def _repo_relative(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def load_baseline(cfg: dict) -> dict | None:
    """The earlier study's results.json (``baseline.results``, e.g. v1's
    ``examples/eqm7/results.json`` for the v2 study), whose numbers the tables show beside
    ours; None without ``baseline``. A missing file stops the table with one line."""
    b = cfg.get("baseline") or {}
    if not b.get("results"):
        return None
    path = _resolve(b["results"])
    if not path.is_file():
        raise SystemExit(f"baseline.results {b['results']}: no such file")
    return json.loads(path.read_text())


def _first_clause(reason: str) -> str:
    """A failure's first clause (up to the first ';'), its parentheses closed."""
    head = reason.split(";")[0]
    return head + ")" * max(head.count("(") - head.count(")"), 0)


def _figure_md(result: dict, names: tuple[str, ...]) -> list[str]:
    """Markdown images of those of ``names`` that ``stage_table`` drew beside results.md."""
    return [f"![{n}]({n})" for n in names if n in result.get("figures", ())]


def _base_note(label: str | None) -> str:
    return (f" {label}: the same rows of the earlier study (its committed results.json)."
            if label else "")


def _static_md(ev: dict, title: str, base: dict | None = None,
               label: str | None = None) -> list[str]:
    """Table 2 of one test set: ours, the paper's and, with ``base`` (the earlier study's
    evaluation of the same set, its rows named ``label``), the earlier study's beside them."""
    keys = ("energy", "forces", "pair_forces")
    i = ev["intrinsic_static"]
    p = PAPER["static"]
    base_groups = (base or {}).get("groups") or {}
    lines = [f"### Table 2 (static errors): {title}", "",
             "Electron pairs at the DFT centres. Ours: mean (± std over models); paper: the"
             " paper's test set (eQM7, 4 models per group)."
             + _base_note(label if base else None), "",
             "| | energy [meV/atom] | core forces [meV/Å] | pair forces [meV/Å] |",
             "|---|---|---|---|",
             "| intrinsic variability (MAE), ours | "
             + " | ".join(f"{1000 * i[k]:.1f}" for k in keys) + " |",
             "| intrinsic variability (MAE), paper | "
             + " | ".join(f"{p['intrinsic'][k]:g}" for k in keys) + " |"]
    for group in ("noaug", "aug"):
        g, b = ev["groups"].get(group), base_groups.get(group)
        for stat, stat_label in (("mae", "MAE"), ("median", "median error")):
            if g:
                lines.append(f"| {GROUP_LABEL[group]}: {stat_label}, ours | " + " | ".join(
                    _ms(g["static"][stat][k], 1000, 1) for k in keys) + " |")
            if b:
                lines.append(f"| {GROUP_LABEL[group]}: {stat_label}, {label} | " + " | ".join(
                    _ms(b["static"][stat][k], 1000, 1) for k in keys) + " |")
            lines.append(f"| {GROUP_LABEL[group]}: {stat_label}, paper | " + " | ".join(
                _paper(p[group][stat][k]) for k in keys) + " |")
    slopes = {group: g["static"]["pair_field_slope"] for group, g in ev["groups"].items()
              if "pair_field_slope" in g["static"]}
    base_slopes = {group: g["static"]["pair_field_slope"] for group, g in base_groups.items()
                   if "pair_field_slope" in g["static"]}
    if slopes:
        lines += ["", "Pair field response (slope of the pair-force error on the field force qE;"
                  " 0: the pairs respond to a field as the DFT centres do, 0.5: about twice too"
                  " soft, polarizabilities about twice too large): " + "; ".join(
                      f"{GROUP_LABEL[group]} {_ms(s, 1, 2)}"
                      + (f" ({label} {_ms(base_slopes[group], 1, 2)})"
                         if group in base_slopes else "") for group, s in slopes.items())
                  + "."]
    return lines + [""]


def _dynamic_md(ev: dict, pol: dict | None, title: str, base: dict | None = None,
                base_pol: dict | None = None, label: str | None = None) -> list[str]:
    """Table 3 of one test set: ours, the paper's and, with ``base`` and ``base_pol`` (the
    earlier study's evaluation and polarizability summary of the same set), its rows named
    ``label`` beside them."""
    keys = ("energy", "forces", "dipole")
    p = PAPER["dynamic"]
    i = ev.get("intrinsic_dynamic")
    if not i:
        return []
    base_groups = (base or {}).get("groups") or {}
    scale = {"energy": 1000, "forces": 1000, "dipole": 1}
    digits = {"energy": 1, "forces": 1, "dipole": 3}
    lines = [f"### Table 3 (dynamic errors): {title}", "",
             "Electron pairs relaxed; polarizability at the DFT optima of the test molecules"
             " (components, pairs relaxed, cores clamped) against our DFT finite-field values."
             + _base_note(label if base else None),
             "",
             "| | energy [meV/atom] | core forces [meV/Å] | dipole norm [D] |"
             " polarizability [bohr³] |", "|---|---|---|---|---|",
             "| intrinsic variability (MAE), ours | " + " | ".join(
                 f"{scale[k] * i[k]:.{digits[k]}f}" for k in keys)
             + f" | {_val(pol and pol['intrinsic_mae'], 2)} |",
             "| intrinsic variability (MAE), paper | " + " | ".join(
                 f"{p['intrinsic'][k]:g}" for k in keys) + f" | {p['intrinsic']['polarizability']}"
             " |"]
    for group in ("noaug", "aug"):
        rows = [("ours", ev["groups"].get(group), (pol or {}).get("groups", {}).get(group))]
        if base:
            rows.append((label, base_groups.get(group),
                         (base_pol or {}).get("groups", {}).get(group)))
        for stat, stat_label in (("mae", "MAE"), ("median", "median error")):
            for who, g, pg in rows:
                if g and g["dynamic"]:
                    lines.append(
                        f"| {GROUP_LABEL[group]}: {stat_label}, {who} | " + " | ".join(
                            _ms(g["dynamic"][stat][k], scale[k], digits[k]) for k in keys)
                        + f" | {_ms(pg[stat], 1, 2) if pg else '–'} |")
            lines.append(f"| {GROUP_LABEL[group]}: {stat_label}, paper | " + " | ".join(
                _paper(p[group][stat][k]) for k in keys)
                + f" | {_paper(p[group][stat]['polarizability'])} |")
        for who, g, pg in rows:
            if g and g["dynamic"]:
                lines.append(f"| {GROUP_LABEL[group]}: error rate, {who} |"
                             f" {_ms(g['dynamic']['error_rate'], 100, 1)} % | | |"
                             f" {_ms(pg['error_rate'], 100, 1) + ' %' if pg else '–'} |")
        lines.append(f"| {GROUP_LABEL[group]}: error rate, paper | {_paper(p[group]['error_rate'])}"
                     f" % | | | {_paper(p[group]['polarizability_error_rate'])} % |")
    return lines + [""]


def study_notes(cfg: dict) -> str:
    """The paragraph under results.md's title: the text of ``notes_file`` when set (a
    committed file, e.g. ``shipped/notes.md``), else ``notes``."""
    path = cfg.get("notes_file")
    if not path:
        return cfg.get("notes", "") or ""
    if not Path(path).is_file():
        raise SystemExit(f"notes_file {path}: no such file")
    return Path(path).read_text()


def markdown(result: dict, notes: str = "", baseline: dict | None = None) -> str:
    """results.md of ``result`` (:func:`stage_table`'s results.json). ``baseline``: the
    earlier study's results.json (``result["baseline"]`` says where it is and names its rows,
    e.g. v1), whose numbers every table then shows beside ours and the paper's."""
    d = result["data"]
    info = result.get("baseline") or {}
    label = info.get("label", "v1") if baseline else None
    base = baseline or {}
    lines = [f"# {result.get('title') or DEFAULT_TITLE}", "",
             f"Generated by `examples/eqm7/run_study.py table` on {result['generated']}."
             f" Status: **{result['status']}**.", ""]
    if notes:
        lines += [notes.strip(), ""]
    if baseline:
        lines += [f"Beside ours and the paper's numbers: **{label}**, the earlier study"
                  f" (`{info.get('results')}`, generated {baseline.get('generated')}), on the"
                  " same test molecules.", ""]
    lines += [
        f"- data: `{d['path']}`, {d['shards']} shard(s), {d['configurations']} configurations"
        f" (train {d['by_split']['train']['configurations']} of"
        f" {d['by_split']['train']['molecules']} molecules, val"
        f" {d['by_split']['val']['configurations']} of {d['by_split']['val']['molecules']},"
        f" test {d['by_split']['test']['configurations']} of"
        f" {d['by_split']['test']['molecules']}); {d['molecules_listed']} molecules listed;"
        f" hydride references: {'yes' if d['hydrides'] else 'no'}",
        f"- models: {', '.join(result['models']) or 'none'}; best validation (held-out"
        " molecules) core-force MAE [meV/Å]: " + ", ".join(
            f"{n} {_val((t or {}).get('best_val', {}).get('val_forces_mae'), 1, 1000)}"
            f" (epoch {(t or {}).get('best_epoch')}, trained on {(t or {}).get('n_train')}"
            " configurations)" for n, t in result["training"].items()),
        f"- DFT reference level (dft stage): `{result['dft_level']}`", ""]
    for set_name, title in (("test", "test molecules of the card"),
                            ("pbe0_subset", "the authors' six molecules (eqm7_pbe0_subset.xyz)")):
        ev = result["evaluation"].get(set_name)
        if not ev:
            lines += [f"*{title}: not evaluated"
                      + (f" ({result['evaluation'].get('pbe0_subset_note')})"
                         if set_name == "pbe0_subset" else "") + ".*", ""]
            continue
        n = next(iter(ev["groups"].values()))["n_structures"]
        base_ev = (base.get("evaluation") or {}).get(set_name)
        pol_key = "polarizability" if set_name == "test" else "polarizability_pbe0_subset"
        pol, base_pol = result.get(pol_key), base.get(pol_key)
        lines += _static_md(ev, f"{title}, {n} configurations", base_ev, label)
        lines += _dynamic_md(ev, pol, f"{title}, {n} configurations", base_ev, base_pol, label)
        if pol:
            lines += [f"Polarizability: {pol['n_molecules']} molecules with a DFT reference"
                      " (our labeler, the labels' level, at its optimum);"
                      " ensemble (mean tensor of a group) MAE / median: "
                      + ", ".join(f"{GROUP_LABEL[g]} {_val(v['ensemble_mae'], 3)} /"
                                  f" {_val(v['ensemble_median'], 3)} bohr³"
                                  for g, v in pol["groups"].items())
                      + (f" ({label}: " + ", ".join(
                          f"{GROUP_LABEL[g]} {_val(v['ensemble_mae'], 3)} /"
                          f" {_val(v['ensemble_median'], 3)}"
                          for g, v in base_pol["groups"].items()) + ")" if base_pol else "")
                      + "."]
            iso = {g: v["isotropic_within_10pct"] for g, v in pol["groups"].items()
                   if v.get("isotropic_within_10pct")}
            if iso:
                lines.append("Isotropic polarizability within 10 % of DFT's: " + ", ".join(
                    f"{GROUP_LABEL[g]} {_ms(v)}" for g, v in iso.items())
                    + f" of {pol['n_molecules']} molecules (mean (± std) over models).")
            lines.append("")
    ir = result["ir"]
    lines += ["### Figure 4 and harmonic IR frequencies", ""]
    if ir:
        n_test = result["data"]["by_split"]["test"]["molecules"]
        of = (f"the {ir['n_molecules']} of {n_test} test molecules with a DFT Hessian so far"
              if ir["n_molecules"] < n_test else f"{ir['n_molecules']} test molecules")
        base_ir = base.get("ir")
        lines += [f"Frequency MAE over {of} (modes matched in"
                  " ascending order), mean (± std) over models: "
                  + ", ".join(f"{GROUP_LABEL[g]} {_ms(v['frequency_mae'], 1, 1)} cm⁻¹"
                              for g, v in ir["groups"].items())
                  + (f"; {label} ({base_ir['n_molecules']} molecules): " + ", ".join(
                      f"{GROUP_LABEL[g]} {_ms(v['frequency_mae'], 1, 1)} cm⁻¹"
                      f" ({len(v.get('excluded') or {})} excluded)"
                      for g, v in base_ir["groups"].items()) if base_ir else "")
                  + f"; paper ~{PAPER['ir']['frequency_mae_cm-1']:g} cm⁻¹.", ""]
        if ir.get("missing"):
            lines += [f"Without a finished DFT Hessian (not compared yet):"
                      f" {', '.join(ir['missing'])}.", ""]
        lines += _ir_bands_md(ir)
        lines += _uniform_scale_md(ir)
        lines += _ir_molecules_md(ir, base_ir, label)
        rmsd = [f"{GROUP_LABEL[g]} {_ms(v['rmsd_vs_dft'], 1, 3)} Å (largest"
                f" {_val(v['rmsd_vs_dft_max'], 3)})" for g, v in ir["groups"].items()
                if (v.get("rmsd_vs_dft") or {}).get("mean") is not None]
        if rmsd:
            lines += ["The models' optima (each model optimises from the DFT optimum; the spectra"
                      " are each method's at its own minimum, as in the paper) lie away from the"
                      " DFT optimum by an RMSD of " + ", ".join(rmsd) + " (mean over the"
                      " compared molecules, then mean (± std) over models)."
                      + _rmsd_correlation_md(ir), ""]
        for g, v in ir["groups"].items():
            if v.get("excluded"):  # an optimisation that failed has no spectrum to compare
                lines += [f"{GROUP_LABEL[g].capitalize()}: {v['compared']} optimisation"
                          f"{'s' if v['compared'] != 1 else ''}"
                          f" compared, {len(v['excluded'])} excluded (the figure's mean"
                          " spectra too): " + "; ".join(f"{k} ({_first_clause(why)})" for k, why
                                                       in v["excluded"].items()) + ".", ""]
        lines += [*_figure_md(result, ("figure4_ir.png",)), ""]
        lines += _base_figures_md(result, baseline, ("figure4_ir.png",))
    else:
        lines += ["*not computed yet (dft and ir stages).*", ""]
    md = result["md"]
    lines += ["### Figure 3: MD stability (500 fs NVT, 300 K, 0.5 fs)", ""]
    if md:
        lines += ["| | runs | stable | transition | unstable | bonding changed | stopped |"
                  " largest jump [eV/atom] |", "|---|---|---|---|---|---|---|---|"]
        base_md = (base.get("md") or {}).get("groups") or {}
        for g, v in md["groups"].items():
            for who, row in (("", v), (f", {label}", base_md.get(g))):
                if row:
                    lines.append(
                        f"| {GROUP_LABEL[g]}{who} | {row['runs']} | {row['stable']} |"
                        f" {row['transition']} | {row['unstable']} | {row['bonding_changed']}"
                        f" | {row['stopped']} | {_val(row['max_jump_max'], 5)} |")
        lines += ["", f"Paper: {PAPER['md']['noaug_unstable_pct']} % of the non-augmented runs"
                  " unstable, none of the augmented ones (the paper does not check bonding)."
                  " Panel a: slope against largest jump of every run with a trajectory to"
                  " analyse (crosses: stopped by the watchdog, counted unstable wherever their"
                  " trajectory up to the stop puts them; a run stopped within the first steps"
                  " has no point); panels b, c: the conserved quantity of one run of each"
                  " class.", ""]
        lines += [*_figure_md(result, ("figure3_md.png", "figure3_series.png")), ""]
        lines += _base_figures_md(result, baseline, ("figure3_md.png", "figure3_series.png"))
    else:
        lines += ["*not run yet (md stage).*", ""]
    lines += differences_md(result)
    lines += targets_md(result, label if baseline else None)
    return "\n".join(lines) + "\n"


def _met(met: bool | None) -> str:
    return "–" if met is None else ("yes" if met else "no")


def targets_md(result: dict, label: str | None = None) -> list[str]:
    """The targets table (``result["targets"]``, of issue 15 or 51: ``targets_of``); with
    ``label`` the earlier study's values and verdicts beside ours (``result["baseline"]
    ["targets"]``) and the ship rule's verdict (``result["ship"]``, :func:`ship_rule`)."""
    issue = str(result.get("targets_of") or "issue15").replace("issue", "issue ")
    base = {t["key"]: t for t in (result.get("baseline") or {}).get("targets") or ()
            if "key" in t} if label else {}
    if not base:
        lines = [f"### Targets of {issue}", "", "| target | measured | met |", "|---|---|---|"]
        for t in result["targets"]:
            lines.append(f"| {t['target']} | {t['measured'] or 'not measured yet'} |"
                         f" {_met(t['met'])} |")
        return lines
    ship = result.get("ship") or {}
    missed = {n["key"]: n["why"] for n in ship.get("not_beaten", ())}
    lines = [f"### Targets of {issue}", "",
             f"| target | measured | met | {label} | {label} met | beats {label} where"
             f" {label} misses |", "|---|---|---|---|---|---|"]
    for t in result["targets"]:
        b = base.get(t.get("key"), {})
        beats = ("(met)" if b.get("met") is True else
                 f"no: {missed[t['key']]}" if t.get("key") in missed else "yes")
        lines.append(f"| {t['target']} | {t['measured'] or 'not measured yet'} |"
                     f" {_met(t['met'])} | {b.get('measured') or 'not measured'} |"
                     f" {_met(b.get('met'))} | {beats} |")
    if ship:
        verdict = ("**yes**: it beats it on every target it misses" if ship["ship"] else
                   "**no**: not beaten on " + ", ".join(n["key"] for n in ship["not_beaten"]))
        lines += ["", f"Ship rule (issue 51, item 7: the new augmented ensemble becomes the"
                  f" pretrained `mini-eqm7` when it beats {label} on every target {label}"
                  f" misses): {verdict}."]
        if ship.get("regressed"):
            lines.append("Met by " + label + " and not by ours (reported, not part of the"
                         " rule): " + "; ".join(f"{r['key']} ({r['why']})"
                                               for r in ship["regressed"]) + ".")
    return lines


def _base_figures_md(result: dict, baseline: dict | None, names: tuple[str, ...]) -> list[str]:
    """Links to the earlier study's figures of ``names`` (drawn beside its results.md)."""
    info = result.get("baseline") or {}
    where = info.get("relative_dir")
    shown = [n for n in names if n in ((baseline or {}).get("figures") or ())]
    if not baseline or where is None or not shown:
        return []
    label = info.get("label", "v1")
    return [f"{label}'s: " + ", ".join(f"[{n}]({Path(where) / n})" for n in shown) + ".", ""]


def differences_md(result: dict) -> list[str]:
    """Why our numbers differ from the paper's: data volume, architecture and training time
    side by side (from ``results.json``), and the pairs' field response that follows."""
    d, p = result["data"], PAPER["setup"]
    molecules = sum(v["molecules"] for v in d["by_split"].values())
    lines = ["### Why our numbers differ from the paper's", "",
             f"- **Data.** {d['configurations']} configurations of {molecules} molecules"
             f" ({d['configurations'] / max(molecules, 1):.0f} per molecule) against the"
             f" paper's {p['configurations']:,} of {p['molecules']} (500 per molecule):"
             f" {p['configurations'] / max(d['configurations'], 1):,.0f}x fewer. Our test"
             " molecules are the card's, held out by molecule, not the paper's test set."]
    setups = [s for s in (result.get("training_setup") or {}).values() if s]
    if setups:
        a = setups[0]
        same = all({k: s[k] for k in a if k not in ("steps", "hours")}
                   == {k: a[k] for k in a if k not in ("steps", "hours")} for s in setups)
        lines.append(
            f"- **Architecture.** F={a['n_features']}, G={a['n_filters']}, N={a['n_rbf']},"
            f" T={a['n_interactions']}, message normalisation J={a['message_norm']:g}"
            f" ({a['dtype']}){'' if same else ' (first model; the others differ)'} against"
            f" the paper's F={p['n_features']}, G={p['n_filters']}, N={p['n_rbf']},"
            f" T={p['n_interactions']}, J={p['message_norm']:g}: a size that trains on one"
            " CPU core (README: at equal time the wider, deeper model did no better).")
        steps = sorted({s["steps"] for s in setups})
        hours = np.array([s["hours"] for s in setups])
        decay = (result.get("train_config") or {}).get("decay_steps")
        lines.append(
            f"- **Training.** {'/'.join(str(x) for x in steps)} optimizer steps per model,"
            f" batch {a['batch_size']}, learning rate {a['lr']:g}"
            + (f" halved every {decay} steps" if decay else "")
            + f"; {hours.mean():.1f} h per"
            f" model (mean; {hours.min():.1f}-{hours.max():.1f}) on one shared CPU core,"
            f" against the paper's {p['hours']:g} h per model on V100 GPUs, batch"
            f" {p['batch_size']}, learning rate {p['lr']:g} halved every 30 epochs (~1.6 M"
            " steps). Training, more than data, limits"
            " these errors (learning_curve.md).")
    ev = (result.get("evaluation") or {}).get("test") or {}
    slope = ((ev.get("groups") or {}).get("aug", {}).get("static", {})
             .get("pair_field_slope") or {}).get("mean")
    if slope is not None:
        lines.append(
            f"- **What follows.** The augmented models' pair-force error has a slope of"
            f" {slope:.2f} on the field force qE (0 when the pairs respond to a field as the"
            " DFT centres do): their electron pairs are too soft, so polarizabilities come out"
            " too large and less holds two pairs apart in MD than in the paper's augmented"
            " models (README and docs/pretrained.md: regression dilution of the pairs'"
            " stiffness).")
    aug = ((result.get("ir") or {}).get("groups") or {}).get("aug") or {}
    soft = next((b for b in aug.get("bands", ()) if b["band"][0] == 0.0), None)
    rmsd = (aug.get("rmsd_vs_dft") or {}).get("mean")
    if soft and soft["mae"]["mean"] is not None and rmsd is not None:
        lines.append(
            f"- **IR.** The frequency error is largest on the soft modes (below"
            f" {soft['band'][1]:g} cm⁻¹: MAE {soft['mae']['mean']:.0f} cm⁻¹, mean error"
            f" {soft['mean_error']['mean']:+.0f}): torsions and bends, the flattest"
            f" directions of the surface. The augmented models' minima lie"
            f" {rmsd:.2f} Å (RMSD) from the DFT ones, and at the DFT optimum their surfaces"
            " are concave along some of these modes (README: `ir_modes.py`).")
    return lines + [""]


# ---------------------------------------------------------------------- export
def stage_export(study: Study) -> Path:
    """The ``export.group`` ensemble (default: augmented) as a pretrained model with its card.

    Into the package (``src/emlpack/pretrained/NAME``) only when the study's ``status`` is
    ``final`` (the full campaign data set); a preliminary ensemble goes to
    ``WORKDIR/pretrained/NAME`` so that no half-trained model ships by accident."""
    study.require_test_split("export", "its card quotes the test molecules' errors")
    from emlpack.pretrained import PRETRAINED_DIR, export_pretrained

    e = study.cfg.get("export", {}) or {}
    name = e.get("name", "mini-eqm7")
    group = e.get("group", "aug")
    results = _read_json(Path(study.cfg.get("results_dir", HERE)) / "results.json")
    if results is None:
        raise SystemExit("export: no results.json (run the table stage first: the card quotes"
                         " its measured errors)")
    models = [path for g, _, path in study.require_models() if g == group]
    if not models:
        raise SystemExit(f"export: no trained model in group {group!r}")
    final = study.cfg.get("status") == "final"
    folder = Path(e["dir"]) if e.get("dir") else (
        PRETRAINED_DIR / name if final else study.workdir / "pretrained" / name)
    if folder.resolve() == (PRETRAINED_DIR / name).resolve():
        ship_check(results, name)
        keep_previous(name, e.get("keep_previous_as"), study.log)
    results_md = Path(study.cfg.get("results_dir", HERE)) / "results.md"
    try:
        results_md = results_md.resolve().relative_to(ROOT)
    except ValueError:
        pass
    calibration, check = spread_calibration(study, models)
    card = model_card(results, name, group, len(models), results_md, calibration, check)
    files = export_pretrained(models, folder, card,
                              notice=preliminary_notice(results, name, group),
                              data_path=e.get("data_label"), domain=study.train_domain(),
                              spread_calibration=calibration)
    study.work["export"] += 1
    where = "the package" if final and not e.get("dir") else str(folder)
    study.log(f"export: {len(models)} {GROUP_LABEL[group]} models -> {folder} ({where};"
              f" {sum(f.stat().st_size for f in files) / 1e6:.2f} MB)")
    return folder


def ship_check(results: dict, name: str) -> None:
    """Stop an export into the package under ``name`` when the study's ship rule
    (``results["ship"]``, written by the table stage of a study with a baseline and issue
    51's targets) does not hold, naming the targets not beaten; a study without one (v1's)
    passes."""
    ship = results.get("ship")
    if ship is None or ship["ship"]:
        return
    why = "; ".join(f"{n['key']} ({n['why']})" for n in ship["not_beaten"])
    label = (results.get("baseline") or {}).get("label", "v1")
    raise SystemExit(f"export: not shipped as {name}: it does not beat {label} on every target"
                     f" {label} misses (issue 51, item 7): {why}. export.dir=FOLDER writes it"
                     " elsewhere")


def keep_previous(name: str, keep_as: str | None, log=print, root: Path | None = None) -> None:
    """Before the package's ``name`` is replaced: copy its installed members and card to
    ``keep_as`` (e.g. ``mini-eqm7-v1``) unless that name has a folder of its own already, so
    users of the earlier ensemble load the same files under that name
    (:data:`emlpack.pretrained.ALIASES` served it from ``name`` until now)."""
    from emlpack.pretrained import PRETRAINED_DIR, model_files

    root = root or PRETRAINED_DIR
    if not keep_as or model_files(name, root) == [] or (root / keep_as).is_dir() and any(
            (root / keep_as).glob("model-*.pt")):
        return
    shutil.copytree(root / name, root / keep_as, dirs_exist_ok=True)
    card = root / keep_as / "card.md"
    if card.is_file():
        card.write_text(card.read_text().rstrip("\n") + f"\n\nShipped as `{name}` until"
                        f" {dt.date.today():%Y-%m-%d}; loadable as `{keep_as}` since.\n")
    log(f"export: the installed {name} kept as {keep_as} ({root / keep_as})")


def spread_calibration(study: Study, models: list[Path]) -> tuple[dict | None, dict | None]:
    """The exported ensemble's spread thresholds, calibrated on the validation molecules'
    configurations (``export.spread_quantile`` of their spreads, pairs relaxed as users get
    them; the shipped float32 weights), and how often they warn on the test molecules'
    configurations (``check``: the fractions and the medians of spread and error). ``(None,
    None)`` with a log line when the validation split is too small
    (``export.spread_min_configurations``): the calculator then keeps its heuristic ones."""
    import torch

    from emlpack.calculators.calibration import (
        calibrate_spread,
        spread_and_error,
        warned_fraction,
    )
    from emlpack.calculators.ensemble import SpreadThresholds, as_ensemble

    e = study.cfg.get("export", {}) or {}
    ensemble = as_ensemble(models, torch.float32).to(torch.float64)  # the shipped weights
    data = study.shards()
    split = data.split_indices()
    val = [data.structures[i] for i in split["val"]]
    n = len({s.info.get("molecule_id") for s in val})
    try:
        calibration = calibrate_spread(
            ensemble, val, f"the {n} validation molecule{'s' if n != 1 else ''}",
            float(e.get("spread_quantile", 0.95)),
            min_configurations=int(e.get("spread_min_configurations", 20)))
    except ValueError as exc:
        study.log(f"export: no spread calibration ({exc}); the calculator keeps its heuristic"
                  " thresholds")
        return None, None
    test = spread_and_error(ensemble, [data.structures[i] for i in split["test"]])
    check = {"configurations": len(test["energy_spread"]), "failed": len(test["failed"]),
             "warned": warned_fraction(test, SpreadThresholds.calibrated(calibration,
                                                                         len(ensemble))),
             "median": {k: float(np.median(test[k])) for k in test if k != "failed"}}
    study.log(f"export: spread thresholds {calibration['energy_eV_per_atom']:.4f} eV/atom,"
              f" {calibration['forces_eV_per_A']:.3f} eV/Å ({calibration['configurations']}"
              f" validation configurations); they warn on {check['warned']['either']:.0%} of"
              f" {check['configurations']} test configurations")
    return calibration, check


def preliminary_notice(result: dict, name: str, group: str) -> str | None:
    """The line every calculation with a preliminary export reports among its warnings; None
    for a final study or models trained on the complete data set (the card then says what the
    study still computes)."""
    if result["status"] == "final" or result["data"].get("complete"):
        return None
    d = result["data"]["by_split"]["train"]
    g = (((result.get("evaluation") or {}).get("test") or {}).get("groups") or {}).get(group)
    errors = ""
    if g:
        mae = g["static"]["mae"]
        errors = (f"; on unseen test molecules its core-force MAE is"
                  f" {1000 * mae['forces']['mean']:.0f} meV/Å and its energy MAE"
                  f" {1000 * mae['energy']['mean']:.0f} meV/atom (the paper's: 52 meV/Å,"
                  " 5 meV/atom)")
    return (f"{name} is a preliminary ensemble, trained on {d['configurations']} configurations"
            f" of {d['molecules']} molecules, not its complete data set{errors}:"
            f" check important results with DFT (its card: emlpack/pretrained/{name}/card.md)")


def model_card(result: dict, name: str, group: str, n_models: int,
               results_md: str | Path = "examples/eqm7/results.md",
               calibration: dict | None = None, check: dict | None = None) -> str:
    """The model card (Markdown) of the exported ensemble, from the study's ``results.json``
    (``results_md``: where its tables are, quoted in the card; ``calibration``, ``check``: its
    spread thresholds and their test, :func:`spread_calibration`)."""
    d = result["data"]
    by = d["by_split"]
    ev = (result.get("evaluation") or {}).get("test") or {}
    g = (ev.get("groups") or {}).get(group)
    pol = ((result.get("polarizability") or {}).get("groups") or {}).get(group)
    ir = ((result.get("ir") or {}).get("groups") or {}).get(group)
    md = ((result.get("md") or {}).get("groups") or {}).get(group)
    cfg = result.get("train_config", {})
    members = [name for name in result.get("models", {}) if name.startswith(f"{group}-s")]
    seeds = [name.removeprefix(f"{group}-s") for name in members]
    runs = [(result.get("training") or {}).get(name) for name in members]
    done = sorted({(run["epochs"], run["n_train"]) for run in runs if run})
    epochs = "".join(f"{e} epochs over {n} training configurations; " for e, n in done)
    if cfg.get("steps"):
        epochs += (f"{int(cfg['steps'])} optimizer steps, the learning rate halved every"
                   f" {int(cfg.get('decay_steps') or cfg['steps'])}; ")
    overrides = ", ".join(f"`{o}`" for o in model_overrides(cfg, group, "{seed}"))
    lines = [
        f"# {name}: an eMLP ensemble trained on mini-eQM7", "",
        f"Status: **{result['status']}** (generated {result['generated']} by"
        " `examples/eqm7/run_study.py export`).", ""]
    n_ir = (result.get("ir") or {}).get("n_molecules") or 0
    md_ran = sorted({r["model"] for r in (result.get("md") or {}).get("runs", [])
                     if r.get("group") == group})
    trained = ((f"Trained on the complete data set ({d['configurations']} configurations,"
                " the campaign's target)" if d.get("complete") else
                f"Trained on {d['configurations']} configurations")
               + ", with a small architecture trained on 2 CPU cores; its"
               " errors below are several times the paper's (the paper trained on 3.4 million"
               " configurations), so check what matters with DFT and watch the ensemble spread"
               " and the warnings.")
    if result["status"] != "final" and d.get("complete"):
        remaining = []  # what the card's lines still wait for (the non-augmented models
        # are the study's comparison, not a line of this card)
        if len(md_ran) < n_models:
            remaining.append("every member's MD")
        if n_ir < by["test"]["molecules"]:
            remaining.append("the IR frequencies of every test molecule")
        pending = (f" The study's remaining results ({', '.join(remaining)}) are still being"
                   " computed: the lines below give what is measured so far, and say on how"
                   " much." if remaining else
                   " The study's final export replaces this card once its tables are reviewed.")
        lines += [f"**Study in progress.** {trained}" + pending, ""]
    elif result["status"] == "final":  # the caution stays: the errors are the same
        lines += [f"**Accuracy.** {trained}", ""]
    else:
        lines += [
            f"**Preliminary.** Trained on the {d['configurations']} configurations labeled so"
            " far, a fraction of the campaign's target (1500 configurations of 250 molecules),"
            " with a small architecture trained on 2 CPU cores. Its errors below are"
            " several times the paper's: use it to explore and to set up workflows, check what"
            " matters with DFT, and watch the ensemble spread and the warnings. The final"
            " ensemble replaces it when the data set is complete.", ""]
    lines += [
        "## Level of theory", "",
        "Labels: PBE0/aug-cc-pVTZ with density fitting (aug-cc-pVTZ-JKFIT), restricted"
        " Kohn-Sham, PySCF; energies, forces under random homogeneous fields up to 0.01 au,"
        " Foster-Boys centres as the electron pairs (the paper's level).", "",
        "## Data", "",
        f"{d['configurations']} configurations ({d['shards']} shards of"
        " `datasets/mini-eqm7/`): train"
        f" {by['train']['configurations']} configurations of {by['train']['molecules']}"
        f" molecules, validation {by['val']['configurations']} of {by['val']['molecules']},"
        f" test {by['test']['configurations']} of {by['test']['molecules']} (split by"
        " molecule, fixed in `molecules.csv` before labeling); normal-mode sampling at 600 and"
        " 800 K, torsions and dimers with CH4/NH3/H2O as in the paper.", "",
        "## Models", "",
        f"{n_models} {GROUP_LABEL[group]} models (seeds {', '.join(seeds)};"
        f" {epochs}training config `examples/eqm7/train.yaml`"
        f"{' with overrides ' + overrides if overrides else ''}),"
        " weights stored in float32."
        " With several members the calculator and every command report the mean and the"
        " spread (`energy_std`, `forces_std`, `dipole_std`, ...) and warn when the spread is"
        " large.", "",
        "## Measured on molecules the models never saw (the card's test molecules)", ""]
    if g:
        s, dyn = g["static"], g["dynamic"]
        lines += [
            "| quantity | MAE | median |", "|---|---|---|",
            f"| energy, static [meV/atom] | {_ms(s['mae']['energy'], 1000)} |"
            f" {_ms(s['median']['energy'], 1000)} |",
            f"| core forces, static [meV/Å] | {_ms(s['mae']['forces'], 1000)} |"
            f" {_ms(s['median']['forces'], 1000)} |",
            f"| pair forces, static [meV/Å] | {_ms(s['mae']['pair_forces'], 1000)} |"
            f" {_ms(s['median']['pair_forces'], 1000)} |"]
        if dyn:
            lines += [
                f"| energy, pairs relaxed [meV/atom] | {_ms(dyn['mae']['energy'], 1000)} |"
                f" {_ms(dyn['median']['energy'], 1000)} |",
                f"| core forces, pairs relaxed [meV/Å] | {_ms(dyn['mae']['forces'], 1000)} |"
                f" {_ms(dyn['median']['forces'], 1000)} |",
                f"| dipole norm [D] | {_ms(dyn['mae']['dipole'], 1, 3)} |"
                f" {_ms(dyn['median']['dipole'], 1, 3)} |"]
        if pol:
            lines.append(f"| polarizability [bohr³] | {_ms(pol['mae'], 1, 2)} |"
                         f" {_ms(pol['median'], 1, 2)} |")
        lines += ["", "Mean (± std) over the models; the full tables with the paper's values"
                  f" beside ours: `{results_md}`."]
        if dyn:
            lines.append(f"Error rate of the pair relaxations: {_ms(dyn['error_rate'], 100)} %.")
    else:
        lines.append("*Not evaluated.*")
    if ir:
        over = (f" over the {n_ir} of {by['test']['molecules']} test molecules with a DFT"
                " Hessian so far" if n_ir and n_ir < by["test"]["molecules"] else "")
        excluded = ir.get("excluded") or {}
        failed = (f"; {len(excluded)} of {ir['compared'] + len(excluded)} optimisations"
                  " left out, failed: " + "; ".join(
                      f"{k} ({_first_clause(why)})" for k, why in excluded.items())
                  if excluded else "")
        bands = "; ".join(f"{b['band'][0]:g}-{b['band'][1]:g}: {_val(b['mae']['mean'])} /"
                          f" {_val(b['mean_error']['mean'], 1)}" for b in ir.get("bands", ())
                          if b["mae"]["mean"] is not None)
        lines.append(f"Harmonic IR frequencies: MAE {_ms(ir['frequency_mae'], 1, 1)} cm⁻¹"
                     f" against PBE0/aug-cc-pVTZ{over} (modes in ascending order{failed})."
                     + (f" By band of the DFT frequency (cm⁻¹; MAE / mean error, model minus"
                        f" DFT, mean over members): {bands}." if bands else "")
                     + (f" The members' optimised geometries lie {_ms(ir['rmsd_vs_dft'], 1, 3)}"
                        f" Å (RMSD, largest {_val(ir['rmsd_vs_dft_max'], 2)} Å) from the DFT"
                        " optima." if (ir.get("rmsd_vs_dft") or {}).get("mean") is not None
                        else ""))
    if md:
        of = (f" (members {', '.join(m.removeprefix(f'{group}-s') for m in md_ran)} of"
              f" {n_models} so far)" if 0 < len(md_ran) < n_models else "")
        lines.append(f"MD (500 fs NVT at 300 K){of}: {md['runs']} runs, {md['stable']} stable,"
                     f" {md['transition']} transition, {md['unstable']} unstable,"
                     f" {md['bonding_changed']} with bonding changed.")
    lines += ["", "## Uncertainty", "", *spread_card(calibration, check)]
    size = (d.get("train_domain") or {}).get("max_heavy_atoms")
    largest = (f" Its training molecules have at most {size} heavy atoms (the data set's"
               " target: up to 7); the calculator warns on a larger molecule." if size else "")
    lines += [
        "", "## Domain", "",
        "Neutral closed-shell molecules of H, C, N and O near their equilibrium geometry"
        " (thermal distortions up to ~800 K) and in homogeneous fields up to 0.01 au (0.51"
        f" V/Å).{largest} Other elements are refused (one line naming them); larger or"
        " charged molecules, crystals and reactive geometries are outside the training data:"
        " the calculator warns on a large ensemble spread and changed bonding, and a failed"
        " pair relaxation is an error naming the member.", "",
        "## Energies", "",
        "Total energies are on the DFT scale: the DFT energies of the four reference hydrides"
        " (H2, CH4, NH3, H2O at the same level) are added back to the model's relative energy,"
        " so `atoms.get_potential_energy()` compares directly with a PySCF PBE0/aug-cc-pVTZ"
        " total energy (docs/pretrained.md).", "",
        "## How to cite", "",
        "Cools-Ceuppens, M.; Dambre, J.; Verstraelen, T. Modeling Electronic Response"
        " Properties with an Explicit-Electron Machine Learning Potential. J. Chem. Theory"
        " Comput. 2022, 18, 1672-1691. doi:10.1021/acs.jctc.1c00978 — and emlpack.", ""]
    return "\n".join(lines)


def spread_card(calibration: dict | None, check: dict | None) -> list[str]:
    """The model card's lines on the spread warnings: the calibrated thresholds and how they
    fare on the test molecules, or that the heuristic ones are used."""
    from emlpack.calculators.ensemble import SpreadThresholds

    if not calibration:
        h = SpreadThresholds()
        return [f"The spread warnings use heuristic thresholds ({h.energy} eV/atom for the"
                f" energy, {h.forces} eV/Å for the largest force component): they are not"
                " calibrated for this ensemble."]
    lines = [
        f"The calculator warns when the spread across the members exceeds"
        f" {calibration['energy_eV_per_atom']:.4f} eV/atom (energy) or"
        f" {calibration['forces_eV_per_A']:.3f} eV/Å (largest force component), every command"
        " on the energy: the"
        f" {calibration['quantile']:.0%} quantiles of the spreads on the"
        f" {calibration['configurations']} configurations of {calibration['set']}, with the"
        f" pairs {calibration['pairs']} (none of these molecules was trained on; stored in"
        " every member as `spread_calibration`)."]
    if check:
        w, m = check["warned"], check["median"]
        lines[0] += (
            f" On the {check['configurations']} configurations of the test molecules they warn"
            f" on {w['energy']:.0%} (energy) and {w['forces']:.0%} (forces); there the median"
            f" error is {m['energy_error'] / max(m['energy_spread'], 1e-300):.1f}x the median"
            f" spread for energies and {m['force_error'] / max(m['force_spread'], 1e-300):.1f}x"
            " for the largest force component, so a quiet spread is no proof of accuracy.")
    return lines


# ---------------------------------------------------------------------- driver
def run(stages: list[str], cfg: dict, log=print) -> Study:
    """Run ``stages`` in order (``"all"``: every stage)."""
    study = Study(copy.deepcopy(cfg), log)
    order: list[str] = []
    for s in stages:
        order += list(STAGES) if s == "all" else [s]
    for s in order:
        if s not in STAGES:
            raise SystemExit(f"unknown stage {s!r} ({', '.join(STAGES)}, all)")
    for s in order:
        t0 = time.perf_counter()
        {"train": stage_train, "evaluate": stage_evaluate, "dft": stage_dft,
         "polarizability": stage_polarizability, "ir": stage_ir, "md": stage_md,
         "table": stage_table, "export": stage_export}[s](study)
        log(f"{s}: {time.perf_counter() - t0:.1f} s")
    return study


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("stages", nargs="+", help=f"{', '.join(STAGES)} or all; key=value overrides")
    p.add_argument("--config", default=str(HERE / "config.yaml"))
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars (a stage's bar: rate and time left on a terminal, a"
                   " plain line every tenth of its work otherwise)")
    args = p.parse_args(argv)
    stages = [s for s in args.stages if "=" not in s]
    overrides = [s for s in args.stages if "=" in s] + (["progress=false"] if args.quiet else [])
    run(stages, load_config(args.config, overrides),
        log=lambda m: print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {m}", flush=True))


if __name__ == "__main__":
    sys.exit(main())
