"""The trainer: Adam with exponential decay, validation every epoch, best/last checkpoints,
early stopping, exact resume, CSV log, optional TensorBoard, data parallel with ``torchrun``.

Run directory (``output.dir``)::

    config.yaml   the resolved configuration      split.json   train/val/test indices
    log.csv       one row per epoch               best.pt      model with the best val. loss
    last.pt       model + training state (optimizer, scheduler, RNG, epoch, best metric)

Both ``.pt`` files load with :func:`emlpack.nn.checkpoint.load_model` (``weights_only=True``);
the training state sits in ``metadata["training"]``.

Determinism and resume: the order of the training set in epoch ``e`` is a permutation seeded
with ``(seed, e)``, and augmentation of configuration ``i`` uses ``(seed, e, i)``. A run killed
at any point restarts from the end of the last finished epoch (``last.pt`` is written
atomically) and continues exactly as an uninterrupted run would.

Snapshots (``output.snapshot_dir``): a run that outlives its machine (a training longer than a
session) copies ``last.pt``, ``best.pt`` and ``log.csv`` every ``output.snapshot_minutes`` and
when it stops (also on Ctrl-C, ``kill PID`` or an error) into a new folder
``snapshot_dir/step-NNNNNNNNN/`` (written under a temporary name, then renamed; the older
snapshot folders are removed), committed to git with ``output.snapshot_commit``. A run whose
``last.pt`` is missing or older than the newest snapshot starts from that snapshot, so the same
command on a fresh clone goes on exactly where the last snapshot stopped.

Learning rate: ``lr0 * decay_factor ** (step / (steps_per_epoch * decay_epochs))``, i.e.
halved every ``decay_epochs`` epochs with the paper's defaults, decayed smoothly per step; with
``decay_cpu_minutes`` instead ``lr0 * decay_factor ** (cpu_seconds / (60 decay_cpu_minutes))``
at every step, the run's CPU time counted over resumes (one process; a resume then continues
the schedule but is not bit-for-bit the uninterrupted run).

Data parallel: launched with ``torchrun --nproc_per_node K``, every process takes a slice of
each global batch (same global batches as one process); the loss terms are divided by the
global counts, so the gradients equal one process's with the same global batch.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np
import torch
import torch.distributed as dist

from emlpack._files import atomic_path, atomic_write, try_lock, write_text_atomic
from emlpack.commits import git_commit
from emlpack.data.augment import AugmentationConfig
from emlpack.data.dataset import (
    Collater,
    load_data,
    make_batch,
    molecule_id,
    split_indices,
    training_domain,
)
from emlpack.data.references import (
    ConstantReference,
    HydrideReference,
    HydrideReferenceError,
    load_hydrides,
)
from emlpack.data.shards import is_sharded, read_shards
from emlpack.heap import reused_heap
from emlpack.interrupts import terminate_as_interrupt
from emlpack.nn.checkpoint import read_checkpoint, save_model
from emlpack.nn.potential import EMLP, ModelConfig
from emlpack.optional import import_optional
from emlpack.train.config import DEFAULTS, ConfigError, dump_config, training_device
from emlpack.train.loss import (
    LossWeights,
    Metrics,
    combine,
    loss_terms,
    predict,
    predict_polarizability,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from torch.utils.tensorboard import SummaryWriter

    from emlpack.structure import Structure

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def build_reference(
    cfg: dict, structures: Sequence[Structure], train_idx: np.ndarray | Sequence[int],
    store_hydrides: dict | None,
) -> HydrideReference | ConstantReference:
    """The reference of the run: hydrides (live) or a constant (mean training energy)."""
    d = cfg["data"]
    kind = d["reference"]
    hydrides = None
    if d["hydrides"]:
        hydrides = load_hydrides(d["hydrides"])
    elif store_hydrides is not None:
        hydrides = (store_hydrides["structures"], store_hydrides["energies"])
    compositions = {tuple(sorted(structures[i].numbers.tolist())) for i in train_idx}
    if kind == "auto":
        kind = "hydrides" if hydrides is not None and len(compositions) > 1 else "constant"
    if kind == "hydrides":
        if hydrides is None:
            raise HydrideReferenceError("reference 'hydrides' needs data.hydrides (a folder) or a"
                                 " store with labelled hydrides")
        return HydrideReference(*hydrides)
    if len(compositions) > 1:
        raise HydrideReferenceError(
            f"{d['path']}: {len(compositions)} compositions need the hydride reference"
            " (set data.hydrides); a constant reference fits one composition only")
    return ConstantReference(float(np.mean([structures[i].energy for i in train_idx])))


class Trainer:
    """Trains one model from a resolved config (see :mod:`emlpack.train.config`)."""

    def __init__(self, cfg: dict) -> None:
        if cfg["output"]["tensorboard"]:  # refused before any work, not after an epoch
            import_optional("tensorboard", "output.tensorboard: true (TensorBoard logging)",
                            alternative="set output.tensorboard=false (log.csv only)")
        self.cfg = cfg
        t = cfg["training"]
        #: where the model and the batches live (``training.device``); batches are built on
        #: the CPU (neighbour lists, augmentation) and moved there
        self.device = training_device(t["device"])
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)
        self.dist = _init_distributed(self.device)
        self.rank = dist.get_rank() if self.dist else 0
        self.world = dist.get_world_size() if self.dist else 1
        if t["threads"]:
            torch.set_num_threads(int(t["threads"]))
        self.dtype = DTYPES[t["dtype"]]
        #: the training step through torch.compile (``training.compile``)
        self.compiled = bool(t.get("compile", False))
        self.run_dir = Path(cfg["output"]["dir"])
        self.weights = LossWeights(**cfg["loss"])
        d = cfg["data"]
        if not d["path"]:
            raise ValueError("data.path is not set (extxyz file or HDF5 store)")
        sharded = is_sharded(d["path"])
        if d["split"] == "card" and not sharded:
            raise ValueError(f"{d['path']}: data.split=card needs a data-set folder with a card")
        if d.get("shards") is not None and not sharded:
            raise ConfigError(f"{d['path']}: data.shards needs a data-set folder of shards")
        if sharded:
            shards = read_shards(d["path"], d.get("shards"))  # a missing shard: StoreError
            self.structures, store_hydrides = shards.structures, shards.hydrides
        else:
            self.structures, store_hydrides = load_data(d["path"])
        if d["split"] in ("auto", "card") and sharded:
            self.split = shards.split_indices()
        else:
            ids = [molecule_id(s) for s in self.structures]
            by = "molecule" if d["split"] == "auto" else d["split"]
            self.split = split_indices(ids, d["fractions"], by, d["split_seed"])
        for part, name in (("train", "training"), ("val", "validation")):
            if len(self.split[part]) == 0:  # no validation: no best model would be saved
                raise ConfigError(f"{d['path']}: the {name} split is empty ({d['split']}"
                                  f" split of {len(self.structures)} structures)")
        self.reference = build_reference(cfg, self.structures, self.split["train"],
                                          store_hydrides)
        self.model_config = ModelConfig.from_dict(cfg["model"])
        torch.manual_seed(t["seed"])
        self.model = EMLP(self.model_config).to(self.dtype).to(self.device)
        frozen = self._frozen_names(t.get("freeze") or [])
        # fused: one kernel for all parameters (the same update; 80 tensors of the study's
        # model's sizes, 1 thread: 0.8 against 3.8 ms a step for the default loop)
        self.optimizer = torch.optim.Adam(
            [p for n, p in self.model.named_parameters() if n not in frozen], lr=t["lr"],
            eps=t["adam_eps"], fused=self.device.type in ("cpu", "cuda"))
        #: what the loss is differentiated with respect to (:meth:`_train_epoch`)
        self.trained_parameters = [p for g in self.optimizer.param_groups for p in g["params"]]
        #: earlier stages of this model (:meth:`init_weights`), then this run (:meth:`metadata`)
        self.lineage: list[dict] = []
        self.batch_size = t["batch_size"]
        self.steps_per_epoch = len(self._epoch_batches(0))
        # CPU seconds of this process spent training, summed over resumes (max_cpu_minutes,
        # decay_cpu_minutes)
        self._cpu_base, self._cpu_start = 0.0, time.process_time()
        factor = float(t["decay_factor"])
        if t["decay_cpu_minutes"] is None:
            decay_steps = max(1e-12, self.steps_per_epoch * float(t["decay_epochs"]))
            self.scheduler = torch.optim.lr_scheduler.LambdaLR(
                self.optimizer, lambda step: factor ** (step / decay_steps))
        else:  # by the run's CPU time (over resumes): equal-CPU comparisons of families
            if self.world > 1:
                raise ValueError("training.decay_cpu_minutes: one process only (the CPU time"
                                 " differs between the processes of a data-parallel run)")
            decay_s = 60.0 * float(t["decay_cpu_minutes"])
            self.scheduler = torch.optim.lr_scheduler.LambdaLR(
                self.optimizer, lambda step: factor ** (self.cpu_seconds() / decay_s))
        self.ddp = self.model
        if self.dist:
            self.ddp = torch.nn.parallel.DistributedDataParallel(
                self.model, device_ids=[self.device] if self.device.type == "cuda" else None)
        aug = AugmentationConfig(**cfg["augmentation"])
        c = self.model_config
        self.collater = Collater(self.reference, c.cutoff, c.gcut, self.dtype,
                                 aug if aug.enabled else None, seed=t["seed"])
        self.epoch = 0
        self.step = 0
        self.best = math.inf
        self.best_epoch = -1
        self.bad_epochs = 0
        self._val_batches = None
        self._training_domain: dict | None = None

    # ------------------------------------------------------------------ data
    def _epoch_batches(self, epoch: int) -> list[np.ndarray]:
        """Global batches of epoch ``epoch``: a seeded permutation of the training set."""
        train = self.split["train"]
        rng = np.random.default_rng([self.cfg["training"]["seed"], epoch, 7])
        order = train[rng.permutation(len(train))]
        batches = [order[k:k + self.batch_size] for k in range(0, len(order), self.batch_size)]
        return [b for b in batches if len(b) >= self.world]

    def _local(self, batch: np.ndarray) -> np.ndarray:
        return batch[self.rank::self.world]

    def _loader(self, epoch: int):
        self.collater.epoch = epoch
        items = [[(int(i), self.structures[int(i)]) for i in self._local(b)]
                 for b in self._epoch_batches(epoch)]
        workers = int(self.cfg["data"]["num_workers"])
        if workers <= 0:
            return (self.collater(x) for x in items)
        return iter(torch.utils.data.DataLoader(
            items, batch_size=None, num_workers=workers, collate_fn=self.collater))

    def _validation_batches(self) -> list:
        if self._val_batches is None:
            val = self._local(self.split["val"])
            bs = int(self.cfg["training"]["eval_batch_size"])
            c = self.model_config
            self._val_batches = [
                make_batch([self.structures[int(i)] for i in val[k:k + bs]], self.reference,
                           c.cutoff, c.gcut, self.dtype, val[k:k + bs].tolist()).to(self.device)
                for k in range(0, len(val), bs)
            ]
        return self._val_batches

    # ------------------------------------------------------------------ state
    def _frozen_names(self, prefixes: list[str]) -> set[str]:
        """Names of the parameters that ``training.freeze`` keeps fixed (each prefix must match
        at least one parameter)."""
        names = [n for n, _ in self.model.named_parameters()]
        out = set()
        for prefix in prefixes:
            hit = {n for n in names if n == prefix or n.startswith(f"{prefix}.")}
            if not hit:
                raise ConfigError(f"training.freeze: {prefix!r} names no parameter (e.g."
                                  f" {', '.join(names[:3])})")
            out |= hit
        if len(out) == len(names):
            raise ConfigError("training.freeze: every parameter is frozen")
        return out

    def stage(self) -> dict:
        """This run as a lineage entry: data (path, the shards read when ``data.shards`` names
        them, configurations), its levels of theory, training size, reference, the starting
        checkpoint, frozen parameters, epoch and step."""
        levels = sorted({str(self.structures[int(i)].info.get("level", "")) or "unknown"
                         for i in self.split["train"]})
        t = self.cfg["training"]
        shards = self.cfg["data"].get("shards")
        return {"data_path": str(self.cfg["data"]["path"]), "levels": levels,
                "shards": list(shards) if shards is not None else None,
                "n_structures": len(self.structures),
                "n_train": int(len(self.split["train"])), "reference": self.reference.kind,
                "init_weights": str(t["init_weights"]) if t["init_weights"] else None,
                "freeze": list(t.get("freeze") or []), "epoch": self.epoch, "step": self.step}

    def metadata(self, **extra) -> dict:
        """Checkpoint metadata: reference, config, data path and size, split, training domain,
        epoch, lineage (the earlier stages, then this run) and ``extra`` (e.g. ``val`` metrics,
        ``training`` state)."""
        return {"reference": self.reference.to_metadata(), "config": self.cfg,
                "data_path": str(self.cfg["data"]["path"]),
                "n_structures": len(self.structures),
                "split": {k: v.tolist() for k, v in self.split.items()},
                **self._domain(), "epoch": self.epoch,
                "lineage": [*self.lineage, self.stage()], **extra}

    def _domain(self) -> dict:
        """Elements and largest molecule of the training split (computed once)."""
        if self._training_domain is None:
            self._training_domain = training_domain(
                [self.structures[i] for i in self.split["train"]])
        return self._training_domain

    def training_state(self) -> dict:
        """What resuming needs (saved in last.pt): optimizer and scheduler states, counters, best
        validation loss, torch RNG state and world size."""
        return {
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "epoch": self.epoch, "step": self.step, "best": self.best,
            "best_epoch": self.best_epoch, "bad_epochs": self.bad_epochs,
            "torch_rng": torch.get_rng_state(), "world_size": self.world,
            "cpu_seconds": self.cpu_seconds(),
        }

    def cpu_seconds(self) -> float:
        """CPU seconds (user + system, all threads) this run's training took, resumed parts
        included (``training.max_cpu_minutes``)."""
        return self._cpu_base + time.process_time() - self._cpu_start

    def resume(self, path: Path) -> None:
        """Continue from the checkpoint ``path`` (last.pt): weights, optimizer, scheduler, counters
        and RNG state; a different model or data config or data size raises ``ValueError``."""
        payload = read_checkpoint(path)
        saved = payload["metadata"].get("config", {})
        for section in ("model", "data"):
            if not self._same_section(section, saved.get(section)):
                raise ValueError(
                    f"{path}: the run was started with a different '{section}' config; resume"
                    " with the same config, or start afresh (--restart / another output.dir)")
        saved_n = payload["metadata"].get("n_structures")
        if saved_n is not None and int(saved_n) != len(self.structures):
            raise ValueError(
                f"{path}: the run was started on {saved_n} structures, {self.cfg['data']['path']}"
                f" now holds {len(self.structures)}; resume on the same data (e.g. a fixed set of"
                " shards), or start afresh (--restart / another output.dir)")
        state = payload["metadata"]["training"]
        self.lineage = list(payload["metadata"].get("lineage", [])[:-1])  # without this run
        self.model.load_state_dict(payload["state_dict"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.epoch, self.step = int(state["epoch"]), int(state["step"])
        self.best, self.best_epoch = float(state["best"]), int(state["best_epoch"])
        self.bad_epochs = int(state["bad_epochs"])
        self._cpu_base = float(state.get("cpu_seconds", 0.0))  # absent before 2026-12-02
        self._cpu_start = time.process_time()
        torch.set_rng_state(state["torch_rng"])

    def _same_section(self, section: str, saved: dict | None) -> bool:
        """Whether the config ``section`` saved in a checkpoint equals this run's (a key the
        saved one lacks, added to the config since, counts as its default); ``model``
        compared normalised (:meth:`ModelConfig.from_dict`: a run started before the
        short-range families saved the version-1 flat spelling)."""
        if section != "model" or saved is None:
            if saved is not None and section in DEFAULTS:  # a key added since: its default
                saved = {**{k: v for k, v in DEFAULTS[section].items() if k not in saved},
                         **saved}
            return saved == self.cfg[section]
        try:
            return ModelConfig.from_dict(saved) == self.model_config
        except (TypeError, ValueError):
            return False

    def init_weights(self, path: str | Path) -> None:
        """Start from the weights of the checkpoint ``path`` (its model config must equal this
        run's); optimizer, schedule and counters start afresh (a fine-tune: this run's data and
        reference, e.g. the paper's level after pretraining at a cheap one); the checkpoint's
        lineage becomes this run's history."""
        payload = read_checkpoint(path)
        meta = payload.get("metadata") or {}
        self.lineage = list(meta.get("lineage") or [
            {"data_path": meta.get("data_path"), "levels": ["unknown"],
             "n_train": len((meta.get("split") or {}).get("train", [])),
             "epoch": meta.get("epoch"), "note": "written before lineage was recorded"}])
        saved = ModelConfig.from_dict(payload["config"])
        if saved != self.model_config:
            mine, theirs = _flat(self.model_config.to_dict()), _flat(saved.to_dict())
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            raise ConfigError(f"training.init_weights={path}: its model differs from this run's"
                              f" model config in {', '.join(diff)}")
        self.model.load_state_dict(payload["state_dict"])

    # ------------------------------------------------------------------ loop
    def train(self, resume: bool = True) -> Path:
        """Train until ``max_epochs``, early stopping or the time limit; returns best.pt."""
        out = self.run_dir
        lock = None
        if self.rank == 0:  # one training per run folder (two would overwrite each other)
            lock = try_lock(out / "train.lock")
            if lock is None:
                raise ConfigError(f"{out}: another training is running in this folder (its"
                                  " train.lock is held); wait for it or use another output.dir")
        try:
            # the double backward's edge-sized buffers are freed and allocated again at every
            # step: reused from the heap instead of page-faulted in (emlpack.heap)
            with reused_heap():
                return self._train(resume)
        finally:
            if lock is not None:
                os.close(lock)

    def _train(self, resume: bool) -> Path:
        t = self.cfg["training"]
        out = self.run_dir
        last = out / "last.pt"
        if self.rank == 0:
            self._restore_snapshot(resume)
        if self.dist:
            dist.barrier()
        if resume and last.exists():
            self.resume(last)
            self._print(f"resumed from {last} at epoch {self.epoch}")
        elif t["init_weights"]:
            self.init_weights(t["init_weights"])
            self._print(f"weights from {t['init_weights']}")
        if self.rank == 0:
            out.mkdir(parents=True, exist_ok=True)
            dump_config(self.cfg, out / "config.yaml")
            log.info("settings (also in %s): %s", out / "config.yaml",
                     json.dumps(self.cfg, default=str))
            write_text_atomic(out / "split.json",
                              json.dumps({k: v.tolist() for k, v in self.split.items()}))
            self._trim_log(out / "log.csv")
        self._print(
            f"{len(self.structures)} structures: train {len(self.split['train'])}, val"
            f" {len(self.split['val'])}, test {len(self.split['test'])} (by"
            f" {self.cfg['data']['split']}); reference {self.reference.kind};"
            f" {self.model.n_parameters()} parameters; {self.world} process(es) on"
            f" {self.device}")
        writer = self._tensorboard()
        t_start = self._snapshot_time = time.monotonic()
        self._saved_step = self._snapshot_step = self.step
        limit, cpu_limit = t["max_time_minutes"], t["max_cpu_minutes"]
        stop_reason = "max_epochs"
        with terminate_as_interrupt():  # ``kill PID`` stops as Ctrl-C does, with a snapshot
            try:
                while self.epoch < t["max_epochs"]:
                    if t["patience"] is not None and self.bad_epochs >= int(t["patience"]):
                        # checked first: a run resumed after it stopped early trains no more
                        stop_reason = (f"early stopping ({self.bad_epochs} epochs without"
                                       " improvement)")
                        break
                    if cpu_limit is not None and self.cpu_seconds() > 60.0 * float(cpu_limit):
                        # checked first too: an epoch starts only while the budget lasts
                        stop_reason = f"CPU time limit ({cpu_limit} CPU min over all resumes)"
                        break
                    self._epoch(writer)
                    if self.dist:
                        dist.barrier()
                    if limit is not None and time.monotonic() - t_start > 60.0 * float(limit):
                        stop_reason = f"time limit ({limit} min; resume to continue)"
                        break
            finally:  # also on Ctrl-C, SIGTERM or an error: the state of the last finished epoch
                if (self.rank == 0 and self.cfg["output"]["snapshot_dir"]
                        and self._saved_step != self._snapshot_step):
                    self._snapshot()
        self._print(f"stopped: {stop_reason}; best epoch {self.best_epoch}"
                    f" (val loss {self.best:.4g})")
        if writer is not None:
            writer.close()
        return out / "best.pt"

    def _epoch(self, writer: SummaryWriter | None) -> None:
        """One epoch: train, validate, then (rank 0) best.pt, last.pt, the log row, a snapshot
        when one is due, TensorBoard and the progress line."""
        out = self.run_dir
        t0 = time.monotonic()
        train_stats = self._train_epoch()
        val = self.validate()
        self.epoch += 1
        improved = val["loss"] < self.best
        if improved:
            self.best, self.best_epoch, self.bad_epochs = val["loss"], self.epoch, 0
        else:
            self.bad_epochs += 1
        row = {"epoch": self.epoch, "step": self.step,
               "lr": self.optimizer.param_groups[0]["lr"], **train_stats,
               **{f"val_{k}": v for k, v in val.items()},
               "best_epoch": self.best_epoch, "epoch_time": time.monotonic() - t0}
        if self.rank == 0:
            if improved:
                save_model(self.model, out / "best.pt", self.metadata(val=val))
            save_model(self.model, out / "last.pt", self.metadata(training=self.training_state()))
            self._saved_step = self.step
            self._log(out / "log.csv", row)
            if self._snapshot_due():
                self._snapshot()
            if writer is not None:
                for k, v in row.items():
                    writer.add_scalar(k, v, self.epoch)
            self._print(
                f"epoch {self.epoch}: loss {train_stats['train_loss']:.4g}, val loss"
                f" {val['loss']:.4g}, val F MAE {val.get('forces_mae', float('nan')):.4f}"
                f" eV/Å, E MAE {1000 * val.get('energy_mae', float('nan')):.2f} meV/atom"
                + (" *" if improved else ""))

    def _train_epoch(self) -> dict:
        from emlpack.progress import progress as progress_bar

        self.model.train()
        names = self.weights.terms()
        sums = torch.zeros(len(names) + 3, dtype=torch.float64)
        batches = self._loader(self.epoch)
        progress = self.cfg["output"]["progress"] and self.rank == 0
        # off a terminal the epoch's own log line is its progress
        bar = progress_bar(batches, total=self.steps_per_epoch, desc=f"epoch {self.epoch + 1}",
                           unit="batch", enabled=progress, leave=False, lines=False)
        for batch in bar:
            batch = batch.to(self.device)
            pred = predict(self.ddp, batch, self.reference, compiled=self.compiled)
            if "polarizability" in names:  # the plain model: the term adds its own graph
                pred.update(predict_polarizability(self.model, batch))
            terms = loss_terms(pred, batch)
            counts = torch.stack([terms[k][1] for k in names]).double()
            if self.dist:
                self._all_reduce(counts)
            gcounts = dict(zip(names, counts.to(pred["forces"].dtype), strict=True))
            loss = combine(terms, self.weights, gcounts) * self.world
            self.optimizer.zero_grad(set_to_none=True)
            # the parameters only: a plain backward() also differentiates the loss with respect
            # to the positions (a leaf of the force computation), the second derivatives of the
            # whole energy, electrostatics included, that nothing uses (identical gradients;
            # benchmarks/training.py, the study's model, 1 thread: 1-5 % less CPU per step)
            loss.backward(inputs=self.trained_parameters)
            self.optimizer.step()
            # the fused step does not count as an in-place change of the parameters (torch
            # 2.13): bump their versions, which the caches keyed on them (folded weights,
            # the polarizability term's Hessian weights) compare
            torch.autograd.graph.increment_version(self.trained_parameters)
            self.scheduler.step()
            self.step += 1
            # per-term mean squared errors of this global batch, for the log
            parts = torch.tensor([float(terms[k][0].detach()) / max(float(counts[n]), 1.0)
                                  for n, k in enumerate(names)], dtype=torch.float64)
            stats = torch.cat([parts, torch.tensor(
                [batch.n_augmented, batch.n_singular, 0.0], dtype=torch.float64)])
            if self.dist:
                self._all_reduce(stats)
            stats[-1] = sum(getattr(self.weights, k) * stats[n] for n, k in enumerate(names))
            sums += stats
            bar.set_postfix(loss=f"{float(stats[-1]):.4g}")
        n = max(self.steps_per_epoch, 1)
        out = {f"train_{k}_mse": float(sums[i]) / n for i, k in enumerate(names)}
        out["train_loss"] = float(sums[-1]) / n
        out["n_augmented"], out["n_singular"] = int(sums[len(names)]), int(sums[len(names) + 1])
        return out

    def validate(self) -> dict:
        """Metrics on the validation split, summed over ranks (:meth:`Metrics.result`), and ``loss``
        (inf when there is nothing to validate)."""
        self.model.eval()
        metrics = Metrics()
        for batch in self._validation_batches():
            pred = predict(self.model, batch, self.reference, create_graph=False)
            metrics.update(pred, batch)
        tensor = metrics.tensor()
        if self.dist:
            self._all_reduce(tensor)
            metrics.load_tensor(tensor)
        out = metrics.result()
        out["loss"] = metrics.loss(self.weights) if out else math.inf
        return out

    def _all_reduce(self, tensor: torch.Tensor) -> None:
        """Sum the CPU ``tensor`` over the processes, in place (through the GPU under NCCL)."""
        if self.device.type == "cuda":
            on_device = tensor.to(self.device)
            dist.all_reduce(on_device)
            tensor.copy_(on_device.cpu())
        else:
            dist.all_reduce(tensor)

    # ------------------------------------------------------------------ snapshots
    SNAPSHOT_FILES = ("last.pt", "best.pt", "log.csv")

    def _snapshots(self) -> list[Path]:
        """The snapshot folders of ``output.snapshot_dir``, oldest first."""
        folder = self.cfg["output"]["snapshot_dir"]
        if not folder or not Path(folder).is_dir():
            return []
        return sorted(p for p in Path(folder).glob("step-*") if p.is_dir())

    def _snapshot_due(self) -> bool:
        o = self.cfg["output"]
        return bool(o["snapshot_dir"]) and (
            time.monotonic() - self._snapshot_time >= 60.0 * float(o["snapshot_minutes"]))

    def _snapshot(self) -> Path:
        """Copy the run's state into a new ``step-NNNNNNNNN`` folder; remove the older ones (a
        newer one, from another machine, stays); commit with ``output.snapshot_commit``."""
        o = self.cfg["output"]
        root = Path(o["snapshot_dir"])
        final = root / f"step-{self._saved_step:09d}"  # the step of last.pt
        # only the older ones go: a newer snapshot came from elsewhere (another machine went
        # further, e.g. a GPU) and is what the next start of this run should take
        snaps = self._snapshots()
        older = [p for p in snaps if _snapshot_step(p) < self._saved_step]
        newer = [p.name for p in snaps if _snapshot_step(p) > self._saved_step]
        if newer:
            log.warning("%s holds newer snapshots than this run's step %d (%s): kept; the"
                        " run resumes from the newest when started again", root,
                        self._saved_step, ", ".join(newer))
        tmp = root / f".{final.name}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for name in self.SNAPSHOT_FILES:
            if (self.run_dir / name).exists():
                shutil.copyfile(self.run_dir / name, tmp / name)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        for p in older:
            shutil.rmtree(p)
        self._snapshot_time = time.monotonic()
        self._snapshot_step = self._saved_step
        self._print(f"snapshot {final}")
        if o["snapshot_commit"]:
            git_commit([root], f"training snapshot {root}: step {self._saved_step}")
        return final

    def _restore_snapshot(self, resume: bool) -> None:
        """Copy the newest snapshot into the run folder when the run's ``last.pt`` is missing
        or older; with ``resume=False`` (start afresh) the old snapshots are removed."""
        snaps = self._snapshots()
        if not snaps:
            return
        if not resume:
            log.warning("starting afresh: removing the old snapshots %s", snaps)
            for p in snaps:
                shutil.rmtree(p)
            return
        newest = snaps[-1]
        last = self.run_dir / "last.pt"
        run_step = (int(read_checkpoint(last)["metadata"]["training"]["step"])
                    if last.exists() else -1)
        if _snapshot_step(newest) <= run_step:
            return
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for name in self.SNAPSHOT_FILES:
            if (newest / name).exists():
                with atomic_path(self.run_dir / name) as tmp:
                    shutil.copyfile(newest / name, tmp)
        self._print(f"restored {self.run_dir} from the snapshot {newest}")

    # ------------------------------------------------------------------ output
    def _print(self, text: str) -> None:
        if self.rank == 0:
            log.info(text)

    def _trim_log(self, path: Path) -> None:
        """Drop rows of epochs after the resumed one (a killed run may have logged them)."""
        if not path.exists():
            return
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        keep = [r for r in rows if int(r["epoch"]) <= self.epoch]
        if len(keep) != len(rows):
            def write(fh: TextIO) -> None:
                w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(keep)

            atomic_write(path, write)

    def _log(self, path: Path, row: dict) -> None:
        new = not path.exists()
        with open(path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(row), extrasaction="ignore", restval="")
            if new:
                w.writeheader()
            w.writerow({k: (f"{v:.10g}" if isinstance(v, float) else v) for k, v in row.items()})
            fh.flush()
            os.fsync(fh.fileno())

    def _tensorboard(self):
        if not self.cfg["output"]["tensorboard"] or self.rank != 0:
            return None
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(str(self.run_dir / "tensorboard"))


def _snapshot_step(folder: Path) -> int:
    """The training step of a snapshot folder ``step-NNNNNNNNN``."""
    return int(folder.name.split("-")[1])


def _init_distributed(device: torch.device) -> bool:
    """Join the ``torchrun`` process group (NCCL on GPUs, else Gloo); False without one."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return False
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return True


def train(cfg: dict, resume: bool = True) -> Path:
    """Train one model; returns the path of ``best.pt``."""
    trainer = Trainer(cfg)
    try:
        return trainer.train(resume=resume)
    finally:
        if trainer.dist and dist.is_initialized():
            dist.destroy_process_group()


def train_ensemble(cfg: dict, seeds: list[int], resume: bool = True) -> list[Path]:
    """Train one model per seed in ``<output.dir>/seed<k>``; returns their best.pt paths."""
    import copy

    paths = []
    for seed in seeds:
        c = copy.deepcopy(cfg)
        c["training"]["seed"] = int(seed)
        c["output"]["dir"] = str(Path(cfg["output"]["dir"]) / f"seed{seed}")
        paths.append(Trainer(c).train(resume=resume))
    return paths


def _flat(d: dict, where: str = "") -> dict:
    """A nested dict as ``{"a.b": value}`` (for naming the keys that differ)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{where}{k}."))
        else:
            out[where + k] = v
    return out
