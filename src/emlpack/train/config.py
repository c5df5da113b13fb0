"""Training configuration: YAML file + ``key=value`` overrides, resolved and validated.

Keys are nested sections (``data``, ``model``, ``augmentation``, ``loss``, ``training``,
``output``); an override names its key with dots, e.g. ``training.max_epochs=5`` or
``model.n_features=64``; values are parsed as YAML (``1e-3``, ``true``, ``[0.8, 0.1, 0.1]``).
Unknown keys are errors (a misspelt key never slips through silently).
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import torch
import yaml

from emlpack._files import write_text_atomic
from emlpack.data.augment import AugmentationConfig
from emlpack.errors import EmlpackError
from emlpack.nn.potential import ModelConfig
from emlpack.overrides import load_yaml, nested, parse_override
from emlpack.train.loss import LossWeights

DEFAULTS: dict = {
    "data": {
        "path": None,  # extxyz file, HDF5 store (.h5) or data-set folder of shards
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
        "max_time_minutes": None,
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
        # parameter-name prefixes kept fixed (e.g. [schnet.embedding] in a fine-tune)
        "freeze": [],
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
    """The resolved configuration: defaults <- YAML file <- overrides."""
    cfg = copy.deepcopy(DEFAULTS)
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
        cfg = merge(cfg, loaded)
    for text in overrides or []:
        cfg = merge(cfg, nested(*parse_override(text)))
    validate(cfg)
    return cfg


def validate(cfg: dict) -> None:
    """Refuse (:class:`ConfigError`) an unknown split or reference, a dtype other than float32 or
    float64, a batch size, epoch limit or patience that is not a positive integer, a negative
    learning rate, an Adam epsilon, decay period or time limit that is not a positive number, a
    decay factor outside (0, 1], a negative loss weight, a device PyTorch cannot use, and a bad
    model section."""
    d, t = cfg["data"], cfg["training"]
    if d["split"] not in ("auto", "molecule", "configuration", "card"):
        raise ConfigError(f"data.split must be auto, molecule, configuration or card, got"
                          f" {d['split']!r}")
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
    for key in ("adam_eps", "decay_epochs", "max_time_minutes"):
        if key == "max_time_minutes" and t[key] is None:  # no time limit
            continue
        if not (_number(t[key]) and t[key] > 0):
            raise ConfigError(f"training.{key} must be a positive number, got {t[key]!r}")
    if not (_number(t["decay_factor"]) and 0 < t["decay_factor"] <= 1):
        raise ConfigError(f"training.decay_factor must be in (0, 1], got {t['decay_factor']!r}")
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
