"""Training configuration: YAML file + ``key=value`` overrides, resolved and validated.

Keys are nested sections (``data``, ``model``, ``augmentation``, ``loss``, ``training``,
``output``); an override names its key with dots, e.g. ``training.max_epochs=5`` or
``model.short_range.n_features=64``; values are parsed as YAML (``1e-3``, ``true``,
``[0.8, 0.1, 0.1]``). Unknown keys are errors (a misspelt key never slips through silently).

The ``model`` section (:class:`emlpack.nn.potential.ModelConfig`): ``family`` (the
short-range family, ``schnet`` by default), ``short_range`` (that family's parameters), the
cutoff and the electrostatics. Short-range parameters belong to the family they were written
for: the family is resolved first (defaults <- file <- overrides), its parameters start from
its defaults, then the file's (when the file is for the same family; an override
``model.family=painn`` on a SchNet config file leaves the file's SchNet parameters out, with a
warning) and the ``model.short_range.KEY=VALUE`` overrides. The version-1 spelling, SchNet's
parameters directly in ``model`` (``model.n_features: 64``, ``model.n_features=64``), still
means SchNet's ``short_range``.
"""

from __future__ import annotations

import copy
import logging
import os
from pathlib import Path
from typing import Any

import torch
import yaml

from emlpack._files import write_text_atomic
from emlpack.data.augment import AugmentationConfig
from emlpack.errors import EmlpackError
from emlpack.nn.potential import DEFAULT_FAMILY, ModelConfig, nest_flat_keys
from emlpack.nn.short_range import families
from emlpack.overrides import load_yaml, nested, parse_override
from emlpack.train.loss import LossWeights

log = logging.getLogger(__name__)

DEFAULTS: dict = {
    "data": {
        "path": None,  # extxyz file, HDF5 store (.h5) or data-set folder of shards
        # a data-set folder's shards to read (file names, e.g. [0000.h5, 0001.h5]): a list
        # frozen when a run starts on a set that is still growing (its resume needs the same
        # data); None: every shard
        "shards": None,
        "hydrides": None,  # folder with H2.xyz, CH4.xyz, ... and energies_*_hartree.txt
        "reference": "auto",  # auto | hydrides | constant
        "split": "auto",  # auto (card of a data-set folder, else molecule) | molecule |
        # configuration | card
        "fractions": [0.9, 0.05, 0.05],
        "split_seed": 0,
        "num_workers": 0,
    },
    "model": ModelConfig().to_dict(),
    "augmentation": AugmentationConfig().to_dict(),
    "loss": LossWeights().to_dict(),
    "training": {
        "seed": 0,
        "dtype": "float32",
        "batch_size": 64,
        "lr": 3.0e-4,
        "adam_eps": 1.0e-7,
        "decay_factor": 0.5,
        "decay_epochs": 30.0,
        "max_epochs": 1000,
        "max_time_minutes": None,  # wall minutes per call (a resume gets them again)
        # CPU minutes of the training process over all resumes (equal-CPU comparisons on a
        # shared machine): the run stops after the epoch that passes them; None: no limit
        "max_cpu_minutes": None,
        # the learning rate decays by decay_factor every this many CPU minutes of the run
        # (over resumes) instead of every decay_epochs; None: by epochs
        "decay_cpu_minutes": None,
        "patience": None,  # early stopping: epochs without improvement (None: off)
        "threads": None,
        # where the model trains: auto (the first CUDA GPU when PyTorch sees one, else the CPU),
        # cpu, cuda or cuda:N; batches are built on the CPU and moved there
        "device": "auto",
        "eval_batch_size": 64,
        # a checkpoint (best.pt / last.pt of an earlier run) whose weights start a fresh run
        # (fine-tuning, e.g. on a data set that grew): same model config; new optimizer and
        # schedule; ignored when the run resumes from its own last.pt. The checkpoint's lineage
        # (what it was trained on) is carried into this run's checkpoints
        "init_weights": None,
        # parameter-name prefixes kept fixed (e.g. [short_range.embedding] in a fine-tune)
        "freeze": [],
        # the training step through torch.compile (families with a written-out length
        # gradient, SchNet): 1.6x fewer CPU seconds a step after a one-off compilation of
        # about a minute (docs/performance.md); needs a C++ compiler, falls back with a warning
        "compile": False,
    },
    "output": {
        "dir": "runs/emlp",
        "progress": True,
        "tensorboard": False,
        # snapshots: copies of the run's state that outlive the machine (trainer.py)
        "snapshot_dir": None,  # folder for step-NNNNNNNN/ snapshots (None: none)
        "snapshot_minutes": 30.0,  # a snapshot after the first epoch that ends this much later
        "snapshot_commit": False,  # git-commit every snapshot (the folder must be in a repo)
    },
}


class ConfigError(EmlpackError, ValueError):
    """An invalid configuration file or override."""


def merge(base: dict, update: dict, where: str = "") -> dict:
    """``base`` updated recursively with ``update``; unknown keys raise :class:`ConfigError`."""
    out = copy.deepcopy(base)
    for key, value in (update or {}).items():
        if key not in out:
            raise ConfigError(f"unknown config key {where + key!r} (known: {sorted(out)})")
        if isinstance(out[key], dict):
            if not isinstance(value, dict):
                raise ConfigError(f"config key {where + key!r} must be a mapping")
            out[key] = merge(out[key], value, where + key + ".")
        else:
            out[key] = value
    return out


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """The resolved configuration: defaults <- YAML file <- overrides (the ``model`` section
    as described in the module docstring)."""
    cfg = copy.deepcopy(DEFAULTS)
    file_model = None
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: no such config file")
        try:
            loaded = load_yaml(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {exc}") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"{path}: the top level must be a mapping")
        loaded = dict(loaded)
        file_model = loaded.pop("model", None)
        cfg = merge(cfg, loaded)
    model_overrides = []
    for text in overrides or []:
        keys, value = parse_override(text)
        if keys[0] == "model":
            model_overrides.append((keys[1:], value, text))
        else:
            cfg = merge(cfg, nested(keys, value))
    cfg["model"] = resolve_model_section(file_model, model_overrides)
    validate(cfg)
    return cfg


def resolve_model_section(
    section: Any = None, overrides: list[tuple[list[str], Any, str]] | None = None
) -> dict:
    """The ``model`` section from a config file's ``section`` (None: none) and the model
    overrides ``(keys below model, value, text)``: family first, then its parameters (module
    docstring); every parameter of the family present. Bad keys raise :class:`ConfigError`."""
    if section is None:
        section = {}
    if not isinstance(section, dict):
        raise ConfigError("config key 'model' must be a mapping")
    try:
        section = nest_flat_keys(section)
    except ValueError as exc:
        raise ConfigError(f"model: {exc}") from None
    # an override of the whole section (model={...}) counts as one override per key
    expanded: list[tuple[list[str], Any, str]] = []
    for keys, value, text in overrides or []:
        if not keys:
            if not isinstance(value, dict):
                raise ConfigError(f"override {text!r}: config key 'model' must be a mapping")
            expanded.extend(([k], v, text) for k, v in value.items())
        else:
            expanded.append((keys, value, text))
    file_family = section.get("family", DEFAULT_FAMILY)
    family = file_family
    for keys, value, _ in expanded:
        if keys == ["family"]:
            family = value
    if not isinstance(family, str) or family not in families():
        raise ConfigError(f"model.family must be one of {', '.join(families())}, got"
                          f" {family!r}")
    out = ModelConfig(family=family).to_dict()
    for key, value in section.items():
        if key not in ("family", "short_range"):
            out[key] = value
    file_params = section.get("short_range") or {}
    if not isinstance(file_params, dict):
        raise ConfigError("config key 'model.short_range' must be a mapping")
    if family == file_family:
        out["short_range"].update(file_params)
    elif file_params:
        log.warning("model.family=%s replaces the config file's family %s: its short_range"
                    " parameters (%s) are not used; %s's defaults apply unless overridden"
                    " (model.short_range.KEY=VALUE)", family, file_family,
                    ", ".join(sorted(file_params)), family)
    schnet_params = set(ModelConfig(family=DEFAULT_FAMILY).short_range)
    for keys, value, text in expanded:
        head = keys[0]
        if keys == ["family"]:
            continue
        if head == "short_range":
            if len(keys) == 1:
                if not isinstance(value, dict):
                    raise ConfigError(f"override {text!r}: config key 'model.short_range'"
                                      " must be a mapping")
                updates = value
            elif len(keys) == 2:
                updates = {keys[1]: value}
            else:
                raise ConfigError(f"override {text!r}: 'model.short_range.{keys[1]}' is not"
                                  " a mapping")
            unknown = sorted(set(updates) - set(out["short_range"]))
            if unknown:
                raise ConfigError(f"override {text!r}: short-range family {family!r} has no"
                                  f" parameter(s) {unknown} (its parameters:"
                                  f" {sorted(out['short_range'])})")
            out["short_range"].update(updates)
        elif head in out:
            if len(keys) > 1:
                raise ConfigError(f"override {text!r}: 'model.{head}' is not a mapping")
            out[head] = value
        elif head in schnet_params and len(keys) == 1:  # version-1 spelling: SchNet's
            if family != DEFAULT_FAMILY:
                raise ConfigError(f"override {text!r}: model.{head} beside the others is a"
                                  f" SchNet parameter (version-1 spelling); family {family!r}"
                                  f" takes model.short_range.{head}=...")
            out["short_range"][head] = value
        else:
            raise ConfigError(f"unknown config key {'model.' + '.'.join(keys)!r} (known:"
                              f" {sorted(out)})")
    return out


def validate(cfg: dict) -> None:
    """Refuse (:class:`ConfigError`) an unknown split or reference, a shard list that is not a
    list of names, a dtype other than float32 or float64, a batch size, epoch limit or
    patience that is not a positive integer, a negative learning rate, an Adam epsilon, decay
    period or time limit that is not a positive number, a decay factor outside (0, 1], a
    negative loss weight, a device PyTorch cannot use, and a bad model section."""
    d, t = cfg["data"], cfg["training"]
    if d["split"] not in ("auto", "molecule", "configuration", "card"):
        raise ConfigError(f"data.split must be auto, molecule, configuration or card, got"
                          f" {d['split']!r}")
    shards = d.get("shards")
    if shards is not None and not (isinstance(shards, list) and shards and all(
            isinstance(x, str) and x for x in shards)):
        raise ConfigError(f"data.shards must be null or a non-empty list of shard file names"
                          f" (e.g. [0000.h5, 0001.h5]), got {shards!r}")
    if d["reference"] not in ("auto", "hydrides", "constant"):
        raise ConfigError(f"data.reference must be auto, hydrides or constant, got"
                          f" {d['reference']!r}")
    if t["dtype"] not in ("float32", "float64"):
        raise ConfigError(f"training.dtype must be float32 or float64, got {t['dtype']!r}")
    training_device(t["device"])
    for key in ("batch_size", "max_epochs"):
        if not isinstance(t[key], int) or t[key] < 1:
            raise ConfigError(f"training.{key} must be a positive integer, got {t[key]!r}")
    if not (_number(t["lr"]) and t["lr"] >= 0):
        raise ConfigError(f"training.lr must be a number >= 0, got {t['lr']!r}")
    for key in ("adam_eps", "decay_epochs", "max_time_minutes", "max_cpu_minutes",
                "decay_cpu_minutes"):
        if key in ("max_time_minutes", "max_cpu_minutes", "decay_cpu_minutes") \
                and t[key] is None:  # no limit / by epochs
            continue
        if not (_number(t[key]) and t[key] > 0):
            raise ConfigError(f"training.{key} must be a positive number, got {t[key]!r}")
    if not (_number(t["decay_factor"]) and 0 < t["decay_factor"] <= 1):
        raise ConfigError(f"training.decay_factor must be in (0, 1], got {t['decay_factor']!r}")
    if not isinstance(t.get("compile", False), bool):
        raise ConfigError(f"training.compile must be true or false, got {t['compile']!r}")
    if t["patience"] is not None and (not isinstance(t["patience"], int) or t["patience"] < 1):
        raise ConfigError(f"training.patience must be a positive integer or null, got"
                          f" {t['patience']!r}")
    for key, value in cfg["loss"].items():
        if not (_number(value) and value >= 0):
            raise ConfigError(f"loss.{key} must be a number >= 0, got {value!r}")
    try:
        ModelConfig.from_dict(cfg["model"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"model: {exc}") from None


def training_device(name: str) -> torch.device:
    """The device of ``training.device`` for this process. ``auto``: a CUDA GPU when PyTorch
    sees one for every process of the node (``torchrun``'s LOCAL_WORLD_SIZE), else the CPU;
    ``cuda``: the GPU of the process's LOCAL_RANK; ``cuda:N``, ``cpu`` as named. A GPU that is
    not there raises :class:`ConfigError`."""
    name = str(name)
    rank = int(os.environ.get("LOCAL_RANK", "0"))
    per_node = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    if name == "auto":
        gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
        return torch.device("cuda", rank) if gpus >= per_node else torch.device("cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"training.device must be auto, cpu, cuda or cuda:N, got {name!r}")\
            from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"training.device must be auto, cpu, cuda or cuda:N, got {name!r}")
    if device.type == "cpu":
        return device
    if not torch.cuda.is_available():
        raise ConfigError(f"training.device={name}: PyTorch sees no CUDA GPU here"
                          " (training.device=cpu, or auto)")
    if device.index is None:
        if per_node > torch.cuda.device_count():
            raise ConfigError(
                f"training.device={name}: {per_node} processes on this node and"
                f" {torch.cuda.device_count()} GPU(s); one GPU per process (or"
                " training.device=cpu)")
        device = torch.device("cuda", rank)
    return device


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def dump_config(cfg: dict, path: str | Path) -> None:
    """Write ``cfg`` to ``path`` as YAML (atomically)."""
    write_text_atomic(path, yaml.safe_dump(cfg, sort_keys=False))
