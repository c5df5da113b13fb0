"""The bake-off of mini-eQM7 v2 (issue 51): training recipes at equal CPU time, judged on the
card's validation molecules.

Each candidate of ``bakeoff.yaml`` is a list of training overrides (train.yaml's recipe, another
family, a pretrained start, a loss term) and the epochs per halving of its learning rate. Per
candidate, one model (seed 0, augmented) is trained for exactly ``cpu_minutes`` CPU minutes
(``training.max_cpu_minutes``: the training process's CPU time summed over resumes, no step
schedule, no early stopping) and judged by ``run_study.py``'s stages with ``split: val`` in its
own workdir ``runs/bakeoff/NAME``: train, evaluate (the shards' validation configurations),
polarizability (at the validation references of ``validation_references.py``), md (500 fs at
300 K per validation molecule, ``md_molecules`` of them). Nothing here looks at a test
molecule. Every stage is resumable: a finished output is skipped, an unfinished training goes
on from its last.pt with the CPU budget it has left.

A candidate with a ``pretrain`` section (issue 50's pilot) first trains on another data set
(``pretrain.data``, e.g. the QM7-wide cheap-level set, with its own hydride references) for
``pretrain.cpu_minutes`` in ``WORKDIR/NAME/pretrain`` (the bake-off's seed, group, learning
rate and schedule, the candidate's ``model.*`` overrides so that the weights fit, then
``pretrain.overrides``), then is fine-tuned from that run's best.pt (``pretrain.checkpoint``)
on mini-eQM7 with a fresh optimizer and mini-eQM7's reference (``training.init_weights``) for
the CPU time left: ``cpu_minutes`` less what the pretraining took, so the total equals every
other candidate's. The pretraining reads the shards its data set held when it first started
(frozen in ``shards.json`` of its run folder, and beside its snapshots, committed, so a fresh
clone resumes on the same data while the set grows); it resumes from its last.pt or newest
snapshot with the budget it has left, and it waits (the bake-off goes on with the next
candidate) until its data set holds ``pretrain.min_configurations``.

``table`` writes ``RESULTS_DIR/bakeoff.md`` and ``bakeoff.json``, one row per candidate, from
``run_study``'s summaries (eval_summary, polarizability_summary, md_summary): CPU minutes
spent, epochs, validation core-force and pair-force MAE (static, meV/Å), pair-field slope,
isotropic polarizability error (median |Δα_iso|/α_iso,DFT and how many molecules within 10 %),
median component error (bohr³), dynamic error rate (failed pair relaxations, %), MD stable runs
of all and runs whose bonding changed; a stage not finished shows "pending". With a ``pilot``
section it also writes the pilot's table (``pilot``: the scratch candidate against the
pretrained one, their differences in %, and issue 50's rule: the campaign goes on when
pretraining lowers the validation core-force MAE by >= 15 % or the isotropic polarizability
error by >= 25 %) to ``pilot.results_dir``/pilot.md and pilot.json; the cheap set's card
includes pilot.md (its notes.md: ``<!-- include: ... -->``).

Usage (from the project root)::

    OMP_NUM_THREADS=1 python examples/eqm7/bakeoff.py run [--only NAME ...] [--commit]
    python examples/eqm7/bakeoff.py table [--only NAME ...]
    python examples/eqm7/bakeoff.py pilot     # pilot.md/json only
    python examples/eqm7/bakeoff.py done      # exit status 0 when every candidate is complete
                                              # (or waits for its pretraining data)

``run`` writes the tables after each candidate (``--commit``: and commits them); ``key=value``
arguments override bakeoff.yaml (e.g. ``cpu_minutes=30 md_molecules=3``).
"""

from __future__ import annotations

import argparse
import copy
import datetime as dt
import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import run_study  # noqa: E402  (examples/eqm7/run_study.py)

#: run_study's stages of every candidate, in order
STAGES = ("train", "evaluate", "polarizability", "md")
SET = "val"  # the bake-off's molecules: the card's validation split, never the test one
#: the stage a candidate with a ``pretrain`` section runs first (WORKDIR/NAME/pretrain)
PRETRAIN = "pretrain"
#: the shard list a pretraining froze when it first started (its run folder, its snapshots')
SHARDS_FILE = "shards.json"
PRETRAIN_KEYS = ("data", "cpu_minutes", "min_configurations", "checkpoint", "decay_epochs",
                 "overrides")
#: issue 50's rule (item 4): the cheap-level campaign goes on to its target when pretraining
#: lowers the validation core-force MAE by at least 15 % or the isotropic polarizability error
#: by at least 25 % (fractions of the scratch model's)
PILOT_RULE = {"forces_mae_meV_per_A": 0.15, "isotropic_median_relative_error": 0.25}


# ---------------------------------------------------------------------- config
def load_bakeoff(path: str | Path = HERE / "bakeoff.yaml", overrides: list[str] = ()) -> dict:
    """bakeoff.yaml with ``key=value`` overrides, checked: one clear line for a bad entry."""
    from emlpack.overrides import OverrideError, apply_overrides, load_yaml

    path = Path(path)
    if not path.is_file():
        raise SystemExit(f"{path}: no such file")
    cfg = load_yaml(path.read_text()) or {}
    try:
        apply_overrides(cfg, overrides)
    except OverrideError as exc:
        raise SystemExit(str(exc)) from None
    cfg.setdefault("study", "config.yaml")
    cfg.setdefault("workdir", "runs/bakeoff")
    cfg.setdefault("results_dir", str(HERE))
    cfg.setdefault("cpu_minutes", 120)
    cfg.setdefault("seed", 0)
    cfg.setdefault("group", "aug")
    cfg.setdefault("lr", 1e-3)
    cfg.setdefault("decay_cpu_minutes", None)
    for key in ("train_overrides", "study_overrides"):
        cfg[key] = list(cfg.get(key) or [])
    where = f"{path.name}"
    if not _positive(cfg["cpu_minutes"]):
        raise SystemExit(f"{where}: cpu_minutes must be a positive number, got"
                         f" {cfg['cpu_minutes']!r}")
    if cfg.get("md_molecules") is not None and not (
            isinstance(cfg["md_molecules"], int) and cfg["md_molecules"] > 0):
        raise SystemExit(f"{where}: md_molecules must be null or a positive integer, got"
                         f" {cfg['md_molecules']!r}")
    candidates = cfg.get("candidates")
    if not isinstance(candidates, dict) or not candidates:
        raise SystemExit(f"{where}: candidates must map names to {{decay_epochs, overrides}}")
    for name, c in candidates.items():
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", str(name)):
            raise SystemExit(f"{where}: candidate name {name!r}: letters, digits, . _ - only"
                             " (it names a folder)")
        if not isinstance(c, dict) or not (
                _positive(c.get("decay_epochs")) or (c.get("decay_epochs") is None
                                                     and _positive(cfg["decay_cpu_minutes"]))):
            raise SystemExit(f"{where}: candidate {name}: decay_epochs (a positive number of"
                             " epochs per halving of the learning rate) is required unless"
                             " decay_cpu_minutes (every candidate's) is set")
        c["overrides"] = _overrides(c.get("overrides"), f"{where}: candidate {name}")
        if c.get("pretrain") is not None:
            c["pretrain"] = _check_pretrain(c["pretrain"], cfg, f"{where}: candidate {name}")
    cfg["pilot"] = _check_pilot(cfg.get("pilot"), candidates, where)
    return cfg


def _overrides(over, where: str) -> list[str]:
    """``over`` (None: none) checked as a list of ``key=value`` strings."""
    over = over or []
    if not isinstance(over, list) or not all(isinstance(o, str) and "=" in o for o in over):
        raise SystemExit(f"{where}: overrides must be a list of 'key=value' strings")
    return over


def _check_pretrain(p, bake: dict, where: str) -> dict:
    """A candidate's ``pretrain`` section, checked (one line for a bad entry), with its
    defaults: ``min_configurations`` null (start at once), ``checkpoint`` best, the bake-off's
    schedule unless ``decay_epochs``, no overrides."""
    if not isinstance(p, dict) or not isinstance(p.get("data"), str) or not p["data"]:
        raise SystemExit(f"{where}: pretrain needs data (the data-set folder to pretrain on)")
    unknown = sorted(set(p) - set(PRETRAIN_KEYS))
    if unknown:
        raise SystemExit(f"{where}: pretrain: unknown key(s) {unknown} (known:"
                         f" {', '.join(PRETRAIN_KEYS)})")
    total = bake["cpu_minutes"]
    if not (_positive(p.get("cpu_minutes")) and p["cpu_minutes"] < total):
        raise SystemExit(f"{where}: pretrain.cpu_minutes must be a positive number below"
                         f" cpu_minutes ({total:g}, the total with the fine-tune), got"
                         f" {p.get('cpu_minutes')!r}")
    least = p.get("min_configurations")
    if least is not None and not (isinstance(least, int) and not isinstance(least, bool)
                                  and least > 0):
        raise SystemExit(f"{where}: pretrain.min_configurations must be null or a positive"
                         f" integer, got {least!r}")
    checkpoint = p.get("checkpoint", "best")
    if checkpoint not in ("best", "last"):
        raise SystemExit(f"{where}: pretrain.checkpoint must be best or last, got"
                         f" {checkpoint!r}")
    if not (_positive(p.get("decay_epochs")) or (p.get("decay_epochs") is None
                                                 and _positive(bake["decay_cpu_minutes"]))):
        raise SystemExit(f"{where}: pretrain.decay_epochs (epochs per halving of the learning"
                         " rate) is required unless decay_cpu_minutes is set")
    return {"data": p["data"], "cpu_minutes": p["cpu_minutes"], "min_configurations": least,
            "checkpoint": checkpoint, "decay_epochs": p.get("decay_epochs"),
            "overrides": _overrides(p.get("overrides"), f"{where}: pretrain")}


def _check_pilot(pilot, candidates: dict, where: str) -> dict | None:
    """The ``pilot`` section (None: no pilot table), checked: ``scratch`` a candidate without
    a pretraining, ``pretrained`` one with, ``results_dir`` (default examples/qm7_cheap)."""
    if pilot is None:
        return None
    if not isinstance(pilot, dict):
        raise SystemExit(f"{where}: pilot must map scratch, pretrained and results_dir")
    unknown = sorted(set(pilot) - {"scratch", "pretrained", "results_dir"})
    if unknown:
        raise SystemExit(f"{where}: pilot: unknown key(s) {unknown} (known: scratch,"
                         " pretrained, results_dir)")
    for key, pretrained in (("scratch", False), ("pretrained", True)):
        name = pilot.get(key)
        if name not in candidates or (candidates[name].get("pretrain") is not None) \
                != pretrained:
            raise SystemExit(f"{where}: pilot.{key} must name a candidate"
                             f" {'with' if pretrained else 'without'} a pretrain section, got"
                             f" {name!r}")
    return {"scratch": pilot["scratch"], "pretrained": pilot["pretrained"],
            "results_dir": str(pilot.get("results_dir") or "examples/qm7_cheap")}


def _positive(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and x > 0


def chosen(bake: dict, only: list[str] | None) -> list[str]:
    """The candidates named by ``--only`` (all when none), in bakeoff.yaml's order."""
    names = list(bake["candidates"])
    unknown = sorted(set(only or ()) - set(names))
    if unknown:
        raise SystemExit(f"--only: unknown candidate(s) {unknown} (known: {names})")
    return [n for n in names if not only or n in only]


def _budget(minutes: float, lr: float, schedule: list[str]) -> list[str]:
    """Training overrides: ``minutes`` CPU minutes and no other stop (no wall-time limit, no
    early stopping, epochs unbounded), learning rate ``lr`` on ``schedule``."""
    return [f"training.max_cpu_minutes={minutes}", "training.max_time_minutes=null",
            "training.max_epochs=100000000", "training.patience=null", f"training.lr={lr}",
            *schedule]


def training_overrides(bake: dict, name: str) -> list[str]:
    """The training overrides of candidate ``name``'s model: its CPU budget
    (:func:`finetune_minutes`) and no other stop (no wall-time limit, no early stopping,
    epochs unbounded), lr halved every ``decay_epochs`` (the candidate's) or else every
    ``decay_cpu_minutes`` of CPU time, with a pretraining its start
    (``training.init_weights``: :func:`pretrain_checkpoint`), then ``train_overrides`` and
    the candidate's own."""
    c = bake["candidates"][name]
    schedule = ([f"training.decay_epochs={c['decay_epochs']}"] if c.get("decay_epochs")
                else [f"training.decay_cpu_minutes={bake['decay_cpu_minutes']}"])
    start = ([f"training.init_weights={pretrain_checkpoint(bake, name)}"]
             if c.get("pretrain") else [])
    return [*_budget(finetune_minutes(bake, name), bake["lr"], schedule), *start,
            *bake["train_overrides"], *c["overrides"]]


def schedule_text(bake: dict, name: str) -> str:
    """How candidate ``name``'s learning rate halves, in words."""
    c = bake["candidates"][name]
    if c.get("decay_epochs"):
        return f"every {c['decay_epochs']:g} epochs"
    return f"every {bake['decay_cpu_minutes']:g} CPU minutes"


def study_config(bake: dict) -> dict:
    """run_study's config (``study``) with the bake-off's ``study_overrides``."""
    study = Path(bake["study"])
    return run_study.load_config(study if study.is_absolute() else HERE / study,
                                 bake["study_overrides"])


def candidate_config(bake: dict, name: str) -> dict:
    """run_study's config of candidate ``name``: split val, workdir WORKDIR/NAME, one model
    (``seed``, ``group``), no step schedule, its training overrides, ``md_molecules``."""
    cfg = study_config(bake)
    cfg.update(workdir=str(Path(bake["workdir"]) / name), split=SET,
               seeds=[int(bake["seed"])], groups=[str(bake["group"])])
    t = cfg.setdefault("training", {})
    t.update(steps=None, overrides=[*(t.get("overrides") or []),
                                    *training_overrides(bake, name)])
    t["snapshots"] = str(Path(bake["snapshots"]) / name) if bake.get("snapshots") else None
    if bake.get("md_molecules"):
        cfg.setdefault("md", {})["max_molecules"] = int(bake["md_molecules"])
    return cfg


def check_candidate(bake: dict, name: str) -> None:
    """Stop with one line when candidate ``name``'s training config is wrong, or its
    pretraining's (its data set not a data-set folder, a bad override, a model other than the
    fine-tune's), before any candidate trains."""
    from emlpack.data.shards import is_sharded
    from emlpack.errors import EmlpackError
    from emlpack.nn.potential import ModelConfig
    from emlpack.train.config import load_config as load_train_config

    cfg = candidate_config(bake, name)
    t = cfg["training"]
    group, seed = cfg["groups"][0], cfg["seeds"][0]
    try:
        tuned = load_train_config(run_study.train_config_path(t),
                                  run_study.model_overrides(t, group, seed))
    except (EmlpackError, ValueError) as exc:
        raise SystemExit(f"bakeoff: candidate {name}: {exc}") from None
    p = bake["candidates"][name].get("pretrain")
    if p is None:
        return
    if not is_sharded(p["data"]):
        raise SystemExit(f"bakeoff: candidate {name}: pretrain.data {p['data']}: not a data-set"
                         " folder (no molecules.csv)")
    try:
        pre = pretrain_config(bake, name)
    except (EmlpackError, ValueError) as exc:
        raise SystemExit(f"bakeoff: candidate {name}: pretraining: {exc}") from None
    if ModelConfig.from_dict(pre["model"]) != ModelConfig.from_dict(tuned["model"]):
        raise SystemExit(f"bakeoff: candidate {name}: the pretraining's model differs from the"
                         " fine-tune's (model.* overrides belong in the candidate's overrides,"
                         " which the pretraining takes too, not in pretrain.overrides)")


# ---------------------------------------------------------------------- pretraining
def pretrain_dir(bake: dict, name: str) -> Path:
    """The run folder of candidate ``name``'s pretraining: WORKDIR/NAME/pretrain."""
    return Path(bake["workdir"]) / name / PRETRAIN


def pretrain_snapshots(bake: dict, name: str) -> Path | None:
    """Where the pretraining's snapshots (and the copy of its shard list) are committed:
    SNAPSHOTS/NAME/pretrain (None without ``snapshots``)."""
    return Path(bake["snapshots"]) / name / PRETRAIN if bake.get("snapshots") else None


def pretrain_checkpoint(bake: dict, name: str) -> Path:
    """The checkpoint the fine-tune starts from: the pretraining's best.pt or last.pt
    (``pretrain.checkpoint``)."""
    return pretrain_dir(bake, name) / f"{bake['candidates'][name]['pretrain']['checkpoint']}.pt"


def pretrain_record(bake: dict, name: str) -> dict | None:
    """The finished pretraining of candidate ``name`` (its done.json), None before."""
    path = pretrain_dir(bake, name) / "done.json"
    return json.loads(path.read_text()) if path.is_file() else None


def finetune_minutes(bake: dict, name: str) -> float:
    """CPU minutes of candidate ``name``'s training on mini-eQM7: ``cpu_minutes``, less what
    its pretraining took (the measured CPU time once it finished, its budget before), so the
    two parts together take every candidate's budget. A pretraining that took it all: one
    line."""
    p = bake["candidates"][name].get("pretrain")
    if p is None:
        return bake["cpu_minutes"]
    done = pretrain_record(bake, name)
    spent = done["cpu_seconds"] / 60.0 if done else p["cpu_minutes"]
    left = bake["cpu_minutes"] - spent
    if left <= 0:
        raise SystemExit(f"bakeoff: candidate {name}: its pretraining took {spent:.1f} CPU"
                         f" minutes, all of the {bake['cpu_minutes']:g} of the budget")
    return left


def frozen_shards(bake: dict, name: str) -> dict | None:
    """The shard list candidate ``name``'s pretraining froze when it first started (data,
    shards, configurations, molecules, when): its run folder's shards.json, else the
    committed copy beside its snapshots (a fresh clone); None before it started."""
    for folder in (pretrain_dir(bake, name), pretrain_snapshots(bake, name)):
        if folder is not None and (folder / SHARDS_FILE).is_file():
            return json.loads((folder / SHARDS_FILE).read_text())
    return None


def data_waiting(bake: dict, name: str) -> str | None:
    """Why candidate ``name``'s pretraining cannot start yet (its data set holds fewer
    configurations than ``pretrain.min_configurations``); None when it can or did."""
    from emlpack.data.shards import shard_counts

    p = bake["candidates"][name].get("pretrain")
    if p is None or p["min_configurations"] is None or frozen_shards(bake, name) is not None:
        return None
    n = shard_counts(p["data"])["configurations"]
    if n >= p["min_configurations"]:
        return None
    return (f"{p['data']} holds {n} of the {p['min_configurations']} configurations its"
            " pretraining waits for")


def freeze_shards(bake: dict, name: str) -> dict:
    """Freeze the shard list of candidate ``name``'s pretraining now (every shard its data
    set holds; the set grows while it trains, and a resume must read the same data), with
    their counts; written into its run folder and beside its snapshots (committed)."""
    from emlpack._files import write_text_atomic
    from emlpack.commits import git_commit
    from emlpack.data.shards import shard_counts

    p = bake["candidates"][name]["pretrain"]
    record = {"data": p["data"], **shard_counts(p["data"]),
              "frozen": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    if not record["shards"]:
        raise SystemExit(f"bakeoff: candidate {name}: {p['data']} holds no shard to pretrain on")
    text = json.dumps(record, indent=1)
    for folder in (pretrain_dir(bake, name), pretrain_snapshots(bake, name)):
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)
            write_text_atomic(folder / SHARDS_FILE, text)
    snaps = pretrain_snapshots(bake, name)
    if snaps is not None:
        git_commit([snaps / SHARDS_FILE], f"bake-off: {name}'s pretraining shards (frozen)")
    return record


def pretrain_overrides(bake: dict, name: str, shards: list[str] | None = None) -> list[str]:
    """The training overrides of candidate ``name``'s pretraining: its data set (``shards``:
    the frozen list), its run folder, the bake-off's seed, group (augmentation), learning rate
    and schedule (``pretrain.decay_epochs`` replaces ``decay_cpu_minutes``), the CPU budget
    ``pretrain.cpu_minutes`` and no other stop, ``train_overrides``, the candidate's
    ``model.*`` overrides (the fine-tune starts from these weights), ``pretrain.overrides``;
    snapshots committed to :func:`pretrain_snapshots`."""
    c = bake["candidates"][name]
    p = c["pretrain"]
    if bake["group"] not in run_study.GROUPS:
        raise SystemExit(f"bakeoff: group must be one of {sorted(run_study.GROUPS)}, got"
                         f" {bake['group']!r}")
    augmented = run_study.GROUPS[bake["group"]]
    schedule = ([f"training.decay_epochs={p['decay_epochs']}"] if p.get("decay_epochs")
                else [f"training.decay_cpu_minutes={bake['decay_cpu_minutes']}"])
    out = [f"data.path={p['data']}", f"output.dir={pretrain_dir(bake, name)}",
           f"augmentation.enabled={str(augmented).lower()}", f"training.seed={bake['seed']}",
           "output.progress=false", *_budget(p["cpu_minutes"], bake["lr"], schedule),
           *bake["train_overrides"], *[o for o in c["overrides"] if o.startswith("model.")],
           *p["overrides"]]
    if shards is not None:
        out.append(f"data.shards={json.dumps(list(shards))}")
    snaps = pretrain_snapshots(bake, name)
    if snaps is not None:
        out += [f"output.snapshot_dir={snaps}", "output.snapshot_commit=true"]
    return out


def pretrain_config(bake: dict, name: str, shards: list[str] | None = None) -> dict:
    """The resolved training config of candidate ``name``'s pretraining: the study's training
    config and overrides, then :func:`pretrain_overrides`."""
    from emlpack.train.config import load_config as load_train_config

    t = study_config(bake).get("training", {})
    return load_train_config(run_study.train_config_path(t), [
        *run_study.model_overrides(t, bake["group"], bake["seed"]),
        *pretrain_overrides(bake, name, shards)])


def stage_pretrain(bake: dict, name: str, log=print) -> dict | None:
    """Candidate ``name``'s pretraining: trained (resumed from its last.pt or newest snapshot,
    the budget over all parts) on the shards frozen at its first start; returns its done.json
    (shards, configurations, molecules, training configurations, CPU seconds, epochs, the
    checkpoint the fine-tune starts from). None, with a log line, while its data set holds
    fewer than ``pretrain.min_configurations``."""
    from emlpack._files import write_text_atomic
    from emlpack.nn.checkpoint import read_checkpoint
    from emlpack.train.trainer import train

    done = pretrain_record(bake, name)
    if done is not None:
        log(f"bakeoff: {name}: pretraining done ({pretrain_dir(bake, name)}), skipped")
        return done
    record = frozen_shards(bake, name)
    if record is None:
        waiting = data_waiting(bake, name)
        if waiting:
            log(f"bakeoff: {name}: pretraining waits: {waiting}; next candidate")
            return None
        record = freeze_shards(bake, name)
    p = bake["candidates"][name]["pretrain"]
    run = pretrain_dir(bake, name)
    log(f"bakeoff: {name}: pretraining on {p['data']} ({record['configurations']}"
        f" configurations of {record['molecules']} molecules, {len(record['shards'])} shards;"
        f" {p['cpu_minutes']:g} CPU min) in {run}")
    best = train(pretrain_config(bake, name, record["shards"]))
    if not Path(best).exists():
        raise SystemExit(f"bakeoff: {name}: no best.pt after the pretraining (no finite"
                         f" validation loss); see {run / 'log.csv'}")
    meta = read_checkpoint(run / "last.pt")["metadata"]
    stage = meta["lineage"][-1]
    progress = run_study.training_progress(run) or {}
    done = {**record, "cpu_budget_minutes": p["cpu_minutes"],
            "cpu_seconds": progress.get("cpu_seconds"), "epochs": progress.get("epochs"),
            "n_train": stage["n_train"], "n_val": len(meta["split"]["val"]),
            "levels": stage["levels"], "checkpoint": str(pretrain_checkpoint(bake, name))}
    write_text_atomic(run / "done.json", json.dumps(done, indent=1))
    log(f"bakeoff: {name}: pretrained, {done['cpu_seconds'] / 60:.1f} CPU min,"
        f" {done['epochs']} epochs -> {done['checkpoint']}")
    return done


# ---------------------------------------------------------------------- status
def model_name(bake: dict) -> str:
    return f"{bake['group']}-s{bake['seed']}"


def pending_stages(study: run_study.Study, bake: dict, candidate: str | None = None) -> list[str]:
    """The stages of a candidate (``candidate``, by default the name of the study's workdir)
    whose outputs are not all there yet: ``pretrain`` first for one with a pretraining, then
    run_study's (a polarizability file that lacks a reference molecule, e.g. a validation
    reference that came later, is pending)."""
    candidate = candidate or study.workdir.name
    pre = bool((bake["candidates"].get(candidate) or {}).get("pretrain"))
    name = model_name(bake)
    run = study.model_dir(bake["group"], bake["seed"])
    done = {"train": (run / "done.json").exists() and (run / "best.pt").exists(),
            "evaluate": run_study.stage_file(study, "eval", name, SET).exists()}
    refs = run_study.dft_results(study)
    pol = run_study._read_json(run_study.stage_file(study, "polarizability", name))
    done["polarizability"] = bool(refs) and pol is not None and set(pol["molecules"]) >= set(refs)
    done["md"] = all((study.workdir / "md" / name / row["name"] / "analysis.json").exists()
                     for row in study.md_molecules())
    done[PRETRAIN] = not pre or pretrain_record(bake, candidate) is not None
    return [s for s in (PRETRAIN, *STAGES) if not done[s]]


def is_waiting(bake: dict, name: str) -> bool:
    """Whether candidate ``name`` waits for its pretraining data (:func:`data_waiting`)."""
    return data_waiting(bake, name) is not None


# ---------------------------------------------------------------------- rows
def _group(summary: dict | None, group: str) -> dict:
    return ((summary or {}).get("groups") or {}).get(group) or {}


def _mean(entry: dict | None, scale: float = 1.0) -> float | None:
    v = (entry or {}).get("mean")
    return None if v is None else scale * v


def candidate_row(bake: dict, name: str) -> dict:
    """One candidate's row of the table (bakeoff.json), None where not measured yet."""
    cfg = candidate_config(bake, name)
    study = run_study.Study(copy.deepcopy(cfg), log=lambda m: None)
    group, model = bake["group"], model_name(bake)
    run = study.model_dir(group, bake["seed"])
    pending = pending_stages(study, bake, name)
    done = run_study._read_json(run / "done.json") or {}
    progress = run_study.training_progress(run) or {}
    cpu = done.get("cpu_seconds") or progress.get("cpu_seconds")
    ev = _group(run_study.eval_summary(study, SET), group)
    static, dynamic = ev.get("static") or {}, ev.get("dynamic") or {}
    pol = run_study.polarizability_summary(study)
    per = (_group(pol, group).get("per_model") or {}).get(model) or {}
    md = _group(run_study.md_summary(study), group)
    pre = pretrain_row(bake, name) if bake["candidates"][name].get("pretrain") else None
    mine = None if cpu is None else cpu / 60.0
    total = mine if pre is None else (None if mine is None or pre["cpu_minutes"] is None
                                      else mine + pre["cpu_minutes"])
    return {
        "name": name, "overrides": bake["candidates"][name]["overrides"],
        "decay_epochs": bake["candidates"][name].get("decay_epochs"),
        "schedule": schedule_text(bake, name),
        "cpu_budget_minutes": bake["cpu_minutes"], "workdir": str(study.workdir),
        "complete": not pending, "pending": pending,
        "waiting": None if pre is None else pre["waiting"],
        "pretrain": pre, "finetune_budget_minutes": finetune_minutes(bake, name),
        "total_cpu_minutes": total,
        "training": {"cpu_minutes": mine,
                     "epochs": done.get("epochs") or progress.get("epochs"),
                     "best_epoch": done.get("best_epoch"), "finished": "train" not in pending},
        "validation": {
            "configurations": ev.get("n_structures"),
            "forces_mae_meV_per_A": _mean((static.get("mae") or {}).get("forces"), 1000.0),
            "pair_forces_mae_meV_per_A": _mean((static.get("mae") or {}).get("pair_forces"),
                                               1000.0),
            "pair_field_slope": _mean(static.get("pair_field_slope")),
            "dynamic_error_rate_pct": _mean(dynamic.get("error_rate"), 100.0)},
        "polarizability": {
            "molecules": (pol or {}).get("n_molecules"),
            "isotropic_median_relative_error": per.get("isotropic_median"),
            "isotropic_within_10pct": per.get("isotropic_within_10pct"),
            "isotropic_compared": per.get("isotropic_compared"),
            "component_median_bohr3": per.get("median"),
            "failure_rate": per.get("error_rate")},
        "md": {"molecules": len(study.md_molecules()),
               **{k: md.get(k) for k in ("runs", "stable", "transition", "unstable",
                                         "bonding_changed", "stopped", "max_jump_max")}},
    }


def pretrain_row(bake: dict, name: str) -> dict:
    """The pretraining part of candidate ``name``'s row: its data set, budget, status (done,
    training, waiting or pending; ``waiting``: why), the frozen shards and what they hold,
    training configurations, CPU minutes and epochs so far, the checkpoint the fine-tune
    starts from, its overrides."""
    p = bake["candidates"][name]["pretrain"]
    done = pretrain_record(bake, name)
    frozen = done or frozen_shards(bake, name) or {}
    progress = run_study.training_progress(pretrain_dir(bake, name)) or {}
    waiting = None if frozen else data_waiting(bake, name)
    cpu = (done or {}).get("cpu_seconds") or progress.get("cpu_seconds")
    status = ("done" if done else "training" if progress else "waiting" if waiting
              else "pending")
    return {"data": p["data"], "cpu_budget_minutes": p["cpu_minutes"],
            "min_configurations": p["min_configurations"], "status": status,
            "waiting": waiting, "shards": frozen.get("shards"),
            "n_shards": len(frozen["shards"]) if frozen.get("shards") else None,
            "configurations": frozen.get("configurations"),
            "molecules": frozen.get("molecules"), "frozen": frozen.get("frozen"),
            "n_train": (done or {}).get("n_train"), "levels": (done or {}).get("levels"),
            "cpu_minutes": None if cpu is None else cpu / 60.0,
            "epochs": (done or {}).get("epochs") or progress.get("epochs"),
            "checkpoint": p["checkpoint"], "overrides": p["overrides"],
            "workdir": str(pretrain_dir(bake, name))}


# ---------------------------------------------------------------------- table
def _cell(value, stage: str, row: dict, fmt: str = "{:.1f}") -> str:
    if value is None:
        return "pending" if stage in row["pending"] else "–"
    return fmt.format(value)


def markdown(result: dict) -> str:
    """bakeoff.md: the rows of ``result`` (bakeoff.json) as one table, with the setup."""
    b = result["setup"]
    lines = [
        "# mini-eQM7 v2 bake-off (issue 51): recipes at equal CPU time", "",
        f"Generated by `examples/eqm7/bakeoff.py table` on {result['generated']}. Judged on"
        f" the card's {b['validation_molecules']} validation molecules only (never the test"
        f" ones): static errors on {b['validation_configurations'] or 'the'} validation"
        " configurations of the shards, polarizabilities at"
        f" {b['references']} of {b['validation_molecules']} DFT validation references"
        f" (PBE0/aug-cc-pVTZ, `{b['references_dir']}`), MD {b['md']}.", "",
        f"One model per candidate: seed {b['seed']}, {run_study.GROUP_LABEL[b['group']]},"
        f" {b['cpu_minutes']:g} CPU minutes of training each (`training.max_cpu_minutes`, over"
        f" all resumes; no step schedule, no early stopping; a pretrained candidate: its"
        f" pretraining and its fine-tune together), lr {b['lr']:g} halved as each"
        " candidate says below. A stage not finished yet: pending.", "",
        "| candidate | CPU min | epochs | core-force MAE [meV/Å] | pair-force MAE [meV/Å] |"
        " pair-field slope | α_iso median \\|Δ\\|/DFT | α_iso within 10 % |"
        " α components median [bohr³] | dynamic error rate [%] | MD stable / runs |"
        " MD bonding changed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        t, v, p, m = r["training"], r["validation"], r["polarizability"], r["md"]
        cpu = _cell(t["cpu_minutes"], "train", r)
        epochs = "–" if t["epochs"] is None else str(t["epochs"])
        if "train" in r["pending"]:  # under way (or not started): its progress so far
            cpu = "pending" if t["cpu_minutes"] is None else f"{t['cpu_minutes']:.1f} (training)"
            epochs = "pending" if t["epochs"] is None else f"{t['epochs']} (training)"
        pre = r.get("pretrain")
        if pre is not None:  # the total, pretraining + fine-tune
            if pre["status"] == "waiting":
                cpu = "waiting (pretraining data)"
            elif pre["cpu_minutes"] is not None:
                tuned = "pending" if t["cpu_minutes"] is None else f"{t['cpu_minutes']:.1f}"
                total = "" if r["total_cpu_minutes"] is None or "train" in r["pending"] \
                    else f"{r['total_cpu_minutes']:.1f} = "
                cpu = (f"{total}{pre['cpu_minutes']:.1f} pretraining"
                       f"{'' if pre['status'] == 'done' else ' (training)'} + {tuned}")
        iso = _cell(p["isotropic_median_relative_error"], "polarizability", r, "{:.1%}")
        within = ("pending" if "polarizability" in r["pending"] or p["isotropic_compared"] is None
                  else f"{p['isotropic_within_10pct']} of {p['molecules']}")
        runs = ("pending" if "md" in r["pending"] or m["runs"] is None
                else f"{m['stable']} / {m['runs']}")
        bonding = "pending" if runs == "pending" else str(m["bonding_changed"])
        lines.append(
            f"| {r['name']} | {cpu} | {epochs} |"
            f" {_cell(v['forces_mae_meV_per_A'], 'evaluate', r)} |"
            f" {_cell(v['pair_forces_mae_meV_per_A'], 'evaluate', r)} |"
            f" {_cell(v['pair_field_slope'], 'evaluate', r, '{:.2f}')} | {iso} | {within} |"
            f" {_cell(p['component_median_bohr3'], 'polarizability', r, '{:.2f}')} |"
            f" {_cell(v['dynamic_error_rate_pct'], 'evaluate', r, '{:.2f}')} | {runs} |"
            f" {bonding} |")
    lines += ["", "Columns: CPU minutes the training took (all resumes) and its epochs; static"
              " errors with the pairs at the DFT centres; pair-field slope: of the pair-force"
              " error on the field force qE (0: the pairs respond to a field as the DFT centres"
              " do, 0.5: about twice too soft); isotropic polarizability at the reference"
              " geometry (pairs relaxed from the DFT centres, cores clamped) against DFT, a"
              " failed relaxation counted outside 10 %; dynamic error rate: failed pair"
              " relaxations of the validation configurations; MD: stable runs of those done and"
              " runs whose bonding changed.", "", "Candidates (training overrides of"
              " `examples/eqm7/train.yaml`):", ""]
    for r in result["rows"]:
        over = ", ".join(f"`{o}`" for o in r["overrides"]) or "train.yaml as is"
        lines.append(f"- **{r['name']}**: {pretrain_text(r)}{over}; lr halved {r['schedule']}"
                     f"{'' if r['complete'] else '; pending: ' + ', '.join(r['pending'])}"
                     f"{'; waiting: ' + r['waiting'] if r.get('waiting') else ''}.")
    return "\n".join(lines) + "\n"


def pretrain_text(row: dict) -> str:
    """How a candidate's row was pretrained, in words (empty without a pretraining)."""
    pre = row.get("pretrain")
    if pre is None:
        return ""
    over = ", ".join(f"`{o}`" for o in pre["overrides"])
    data = ""
    if pre["shards"]:
        trained = "" if pre["n_train"] is None else f", {pre['n_train']} for training"
        data = (f" ({pre['configurations']} configurations of {pre['molecules']} molecules in"
                f" shards {pre['shards'][0]}-{pre['shards'][-1]}, frozen {pre['frozen']}"
                f"{trained})")
    return (f"pretrained on `{pre['data']}`{data} for {pre['cpu_budget_minutes']:.4g} CPU min"
            f"{' (' + over + ')' if over else ''}, then fine-tuned from its"
            f" {pre['checkpoint']}.pt for the rest ({row['finetune_budget_minutes']:.1f} CPU"
            " min): ")


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def setup(bake: dict, name: str) -> dict:
    """The bake-off's setup as the tables state it (CPU budget, seed, group, lr, MD, the
    validation molecules, configurations and references), from candidate ``name``'s study."""
    study = run_study.Study(candidate_config(bake, name), log=lambda m: None)
    c = study.cfg.get("md", {})
    md = (f"{c.get('time_fs', 500.0):g} fs NVT at {c.get('temperature_K', 300.0):g} K on"
          f" {len(study.md_molecules())} of them")
    val = study.shards().split_indices()[SET]
    return {"cpu_minutes": bake["cpu_minutes"], "seed": bake["seed"], "group": bake["group"],
            "lr": bake["lr"], "md": md, "data": str(study.data),
            "validation_molecules": len(study.split_molecules()),
            "validation_configurations": len(run_study._subsample(
                list(val), study.cfg.get("evaluate", {}).get("max_structures"))),
            "references": len(run_study.dft_results(study)),
            "references_dir": str(study.dft_dir),
            "train_overrides": bake["train_overrides"],
            "study_overrides": bake["study_overrides"]}


def table(bake: dict, names: list[str], log=print) -> dict:
    """bakeoff.json and bakeoff.md in ``results_dir`` with the rows of ``names``; with a
    ``pilot`` section whose candidates are among them, the pilot's table too
    (:func:`pilot`)."""
    rows = [candidate_row(bake, name) for name in names]
    result = {
        "generated": _now(),
        "setup": setup(bake, names[0]),
        "complete": all(r["complete"] for r in rows),
        "rows": rows,
    }
    out = Path(bake["results_dir"])
    run_study._write_json(out / "bakeoff.json", result)
    run_study._write_text(out / "bakeoff.md", markdown(result))
    log(f"bakeoff: {out / 'bakeoff.md'} ({sum(r['complete'] for r in rows)} of {len(rows)}"
        " candidates complete)")
    p = bake.get("pilot")
    by_name = {r["name"]: r for r in rows}
    if p is not None and p["scratch"] in by_name and p["pretrained"] in by_name:
        pilot(bake, log, by_name[p["scratch"]], by_name[p["pretrained"]], result["setup"])
    return result


# ---------------------------------------------------------------------- pilot
def _gain(scratch: float | None, pretrained: float | None) -> float | None:
    """How much lower ``pretrained`` is than ``scratch``, as a fraction of ``scratch``
    (positive: pretraining lowers it); None when either is missing or ``scratch`` is 0."""
    if scratch is None or pretrained is None or scratch == 0:
        return None
    return (scratch - pretrained) / scratch


#: the pilot's columns: (label, row section, key, format, compared as absolute values)
PILOT_COLUMNS = (
    ("core-force MAE [meV/Å]", "validation", "forces_mae_meV_per_A", "{:.1f}", False),
    ("pair-force MAE [meV/Å]", "validation", "pair_forces_mae_meV_per_A", "{:.1f}", False),
    ("pair-field slope", "validation", "pair_field_slope", "{:.2f}", True),
    ("α_iso median \\|Δ\\|/DFT", "polarizability", "isotropic_median_relative_error",
     "{:.1%}", False),
)
#: the stages the pilot's rule needs of both models (MD is in the bake-off's table only)
PILOT_STAGES = (PRETRAIN, "train", "evaluate", "polarizability")


def verdict(scratch: dict, pretrained: dict) -> dict:
    """Issue 50's rule (:data:`PILOT_RULE`) on the rows of the scratch and the pretrained
    model: ``decision`` continue (pretraining lowers the validation core-force MAE by >= 15 %
    or the isotropic polarizability error by >= 25 %), stop (neither), or pending (a stage
    the rule needs is not finished: ``pending``); ``gains`` (fractions, positive: lower with
    pretraining) and ``met`` (the criteria met)."""
    sections = {"forces_mae_meV_per_A": "validation",
                "isotropic_median_relative_error": "polarizability"}
    gains = {key: _gain(scratch[sec][key], pretrained[sec][key])
             for key, sec in sections.items()}
    pending = sorted({f"{r['name']}: {st}" for r in (scratch, pretrained)
                      for st in r["pending"] if st in PILOT_STAGES})
    met = [key for key, g in gains.items() if g is not None and g >= PILOT_RULE[key]]
    decision = "pending" if pending else "continue" if met else "stop"
    return {"decision": decision, "gains": gains, "met": met, "pending": pending,
            "rule": dict(PILOT_RULE)}


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:+.1f} %"


def verdict_text(v: dict) -> str:
    """The rule's outcome in words (a Markdown paragraph)."""
    f = v["gains"]["forces_mae_meV_per_A"]
    a = v["gains"]["isotropic_median_relative_error"]
    lowered = (f"with pretraining the validation core-force MAE changes by"
               f" {_pct(None if f is None else -f)} (the rule asks for"
               f" -{100 * PILOT_RULE['forces_mae_meV_per_A']:.0f} % or less) and the isotropic"
               f" polarizability error by {_pct(None if a is None else -a)} (the rule: -"
               f"{100 * PILOT_RULE['isotropic_median_relative_error']:.0f} % or less"
               f"{'; not compared' if a is None else ''})")
    if v["decision"] == "pending":
        return ("**Verdict: pending.** The rule needs both models' training, evaluation and"
                f" polarizabilities; not finished: {'; '.join(v['pending'])}.")
    if v["decision"] == "continue":
        return f"**Verdict: continue the campaign to its target**: {lowered}."
    return (f"**Verdict: stop the campaign** (neither criterion is met): {lowered}. Say so in"
            " the card and the note, and resolve issue 50 with this result.")


def pilot_markdown(result: dict) -> str:
    """pilot.md: the scratch and the pretrained model side by side on mini-eQM7's validation
    molecules, the changes in %, the rule's verdict (a section of the cheap set's card)."""
    b, s, p = result["setup"], result["scratch"], result["pretrained"]
    pre = p["pretrain"]
    frozen = (f"{pre['configurations']} configurations of {pre['molecules']} molecules"
              f" ({pre['n_shards']} shards, {pre['shards'][0]}-{pre['shards'][-1]}, frozen"
              f" {pre['frozen']})" if pre["shards"] else
              "its configurations (not frozen yet: the pretraining has not started)")
    lines = [
        "### Pilot table: pretrained + fine-tuned against from scratch, at equal CPU time", "",
        f"Generated by `examples/eqm7/bakeoff.py` on {result['generated']}, from the bake-off"
        f" of issue 51 (`examples/eqm7/bakeoff.md`). Two SchNet models of the same recipe"
        f" (seed {b['seed']}, {run_study.GROUP_LABEL[b['group']]}) for the same total of"
        f" {b['cpu_minutes']:g} CPU minutes: **{s['name']}** trained from scratch on"
        f" mini-eQM7's training split; **{p['name']}** pretrained for"
        f" {pre['cpu_budget_minutes']:.4g} CPU minutes on `{pre['data']}` ({frozen}, its own"
        " hydride references at its level), then fine-tuned from its"
        f" {pre['checkpoint']}.pt on mini-eQM7's training split (fresh optimizer, the paper"
        " level's hydride references) for the CPU time left. Judged on mini-eQM7's"
        f" {b['validation_molecules']} validation molecules (never its test ones): static"
        f" errors on {b['validation_configurations']} validation configurations, isotropic"
        f" polarizabilities against {b['references']} DFT references (PBE0/aug-cc-pVTZ).", "",
        "| model | CPU min | " + " | ".join(c[0] for c in PILOT_COLUMNS) + " |",
        "|---|---|" + "---|" * len(PILOT_COLUMNS)]
    for label, r in (("from scratch", s), ("pretrained + fine-tuned", p)):
        cells = []
        for _, sec, key, fmt, _ in PILOT_COLUMNS:
            stage = "evaluate" if sec == "validation" else "polarizability"
            cells.append(_cell(r[sec][key], stage, r, fmt))
        cpu = r["total_cpu_minutes"]
        if r.get("pretrain") and r["pretrain"]["cpu_minutes"] is not None:
            tuned = r["training"]["cpu_minutes"]
            cpu_text = (f"{r['pretrain']['cpu_minutes']:.1f} + "
                        f"{'pending' if tuned is None else f'{tuned:.1f}'}")
        else:
            cpu_text = "pending" if cpu is None else f"{cpu:.1f}"
        lines.append(f"| {label} ({r['name']}) | {cpu_text} | " + " | ".join(cells) + " |")
    changes = [_pct(None if g is None else -g) for g in result["changes"].values()]
    lines += [f"| change with pretraining | | {' | '.join(changes)} |", "",
              verdict_text(result["verdict"]), "",
              "CPU minutes: the training processes' CPU time over all resumes (pretraining +"
              " fine-tune). Change: (pretrained − scratch) / scratch, the pair-field slope's"
              " of its absolute value (0: pairs that respond to a field as the DFT centres"
              " do). α_iso: median over the validation molecules of |α_iso − α_iso,DFT| /"
              " α_iso,DFT. The rule (issue 50): continue the campaign to its target if"
              " pretraining lowers the validation core-force MAE by ≥ 15 % or the"
              " polarizability error by ≥ 25 %; otherwise stop."]
    return "\n".join(lines) + "\n"


def pilot(bake: dict, log=print, scratch: dict | None = None, pretrained: dict | None = None,
          setup_: dict | None = None) -> dict:
    """The pilot's table: ``pilot.scratch`` against ``pilot.pretrained`` (their rows,
    computed unless given), the changes and the rule's verdict (:func:`verdict`) ->
    ``pilot.results_dir``/pilot.json and pilot.md."""
    p = bake.get("pilot")
    if p is None:
        raise SystemExit("bakeoff: no pilot section in the bake-off's config")
    scratch = scratch or candidate_row(bake, p["scratch"])
    pretrained = pretrained or candidate_row(bake, p["pretrained"])
    changes = {}
    for _, sec, key, _, absolute in PILOT_COLUMNS:
        a, b = scratch[sec][key], pretrained[sec][key]
        if absolute and a is not None and b is not None:
            a, b = abs(a), abs(b)
        changes[key] = _gain(a, b)
    result = {"generated": _now(), "setup": setup_ or setup(bake, p["scratch"]),
              "scratch": scratch, "pretrained": pretrained, "changes": changes,
              "verdict": verdict(scratch, pretrained)}
    out = Path(p["results_dir"])
    run_study._write_json(out / "pilot.json", result)
    run_study._write_text(out / "pilot.md", pilot_markdown(result))
    log(f"bakeoff: {out / 'pilot.md'} (verdict: {result['verdict']['decision']})")
    return result


def commit(bake: dict, message: str) -> None:
    """Commit the tables (bakeoff.md/json, and the pilot's when configured)."""
    from emlpack.commits import git_commit

    out = Path(bake["results_dir"])
    paths = [out / "bakeoff.md", out / "bakeoff.json"]
    if bake.get("pilot"):
        paths += [Path(bake["pilot"]["results_dir"]) / n for n in ("pilot.md", "pilot.json")]
    git_commit([x for x in paths if x.exists()], message)


# ---------------------------------------------------------------------- run
def run(bake: dict, names: list[str], log=print, commit_table: bool = False) -> dict:
    """Each candidate in ``names``: its pretraining first when it has one
    (:func:`stage_pretrain`; a candidate whose pretraining data are not there yet is left for
    a later run), then run_study's stages (split val, its own workdir); the tables (every
    candidate's rows) after each; ``commit_table``: and commit them. Returns each
    candidate's work actually done (``Study.work``, and ``pretrain``)."""
    for name in names:
        check_candidate(bake, name)
    work = {}
    for name in names:
        did = {}
        if bake["candidates"][name].get("pretrain"):
            before = pretrain_record(bake, name) is not None
            if stage_pretrain(bake, name, log) is None:  # waiting for its data
                work[name] = {}
                continue
            if not before:
                did[PRETRAIN] = 1
        cfg = candidate_config(bake, name)  # the fine-tune's budget: what the pretraining left
        log(f"bakeoff: {name} ({', '.join(bake['candidates'][name]['overrides']) or 'train.yaml'}"
            f"; {finetune_minutes(bake, name):g} CPU min) in {cfg['workdir']}")
        study = run_study.run(list(STAGES), cfg, log=log)
        work[name] = {**did, **study.work}
        table(bake, list(bake["candidates"]), log=log)
        if commit_table:
            commit(bake, f"bake-off: {name} ({', '.join(STAGES)}), table")
    return work


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("action", choices=("run", "table", "pilot", "done"))
    p.add_argument("overrides", nargs="*", help="key=value overrides of bakeoff.yaml")
    p.add_argument("--only", nargs="+", metavar="NAME", help="these candidates only")
    p.add_argument("--config", default=str(HERE / "bakeoff.yaml"))
    p.add_argument("--commit", action="store_true", help="commit the tables as they change")
    args = p.parse_args(argv)
    bake = load_bakeoff(args.config, args.overrides)
    names = chosen(bake, args.only)

    def log(m: str) -> None:
        print(f"[{dt.datetime.now(dt.timezone.utc):%H:%M:%S}] {m}", flush=True)

    if args.action == "run":
        run(bake, names, log, commit_table=args.commit)
    elif args.action in ("table", "pilot"):
        if args.action == "table":
            table(bake, names, log)
        else:
            pilot(bake, log)
        if args.commit:
            commit(bake, f"bake-off: {args.action}")
    else:  # done: every candidate complete, or waiting for its pretraining data
        blocking = False
        for n in names:
            stages = pending_stages(run_study.Study(candidate_config(bake, n),
                                                    log=lambda m: None), bake, n)
            waiting = data_waiting(bake, n) if stages else None
            blocking |= bool(stages) and waiting is None
            print(f"{n}: " + ("complete" if not stages else f"waiting ({waiting})" if waiting
                              else "pending: " + ", ".join(stages)))
        return 1 if blocking else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
