"""Training step benchmark: CPU and wall time per optimizer step of the mini-eQM7 study's model
(``examples/eqm7/train.yaml``: F=G=64, T=3, batch 16, float32, augmented), with the freed
memory kept in the heap (``emlpack.heap.reused_heap``, what ``Trainer.train`` does) and
without (glibc's defaults).

The settings alternate block by block in one process (the machine is shared, so only
ratios measured this way are meaningful); each block takes the same batches. Before timing,
one step's loss gradients are computed under every setting from the same state and compared
(they must be identical: the setting only changes where memory comes from).

The third setting, the kept heap with the plain ``backward()`` (the loss also differentiated
in the positions, as before 2026-11-28), measures the parameters-only backward.

Usage: OMP_NUM_THREADS=1 python benchmarks/training.py --json training.json
       [--data datasets/mini-eqm7] [--steps 40] [--repeats 6]
"""

from __future__ import annotations

import argparse
import contextlib
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, machine_info, write_json  # noqa: E402


def make_trainer(data: Path, out: Path):
    from emlpack.train.config import load_config
    from emlpack.train.trainer import Trainer

    cfg = load_config(ROOT / "examples" / "eqm7" / "train.yaml",
                      [f"data.path={data}", f"output.dir={out}", "augmentation.enabled=true"])
    return Trainer(cfg)


def main() -> None:
    from emlpack.heap import reused_heap
    from emlpack.train.loss import combine, loss_terms, predict

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "datasets" / "mini-eqm7"))
    ap.add_argument("--steps", type=int, default=40, help="steps per timed block")
    ap.add_argument("--repeats", type=int, default=6, help="blocks per setting")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(Path(args.data), Path(tmp))
        batches = list(trainer._loader(0))[: args.steps + 5]
        model = trainer.model
        model.train()

        def gradients(batch, every_leaf: bool = False) -> list[torch.Tensor]:
            loss = combine(loss_terms(predict(model, batch, trainer.reference), batch),
                           trainer.weights)
            trainer.optimizer.zero_grad(set_to_none=True)
            # as Trainer._train_epoch; every_leaf: the plain backward() used before 2026-11-28
            loss.backward(inputs=None if every_leaf else trainer.trained_parameters)
            return [p.grad.clone() for p in model.parameters()]

        plain = gradients(batches[0])
        with reused_heap():
            reused = gradients(batches[0])
            leaves = gradients(batches[0], every_leaf=True)
        identical = all(torch.equal(a, b) and torch.equal(a, c)
                        for a, b, c in zip(plain, reused, leaves, strict=True))

        def step(batch, every_leaf: bool = False) -> None:
            gradients(batch, every_leaf)
            trainer.optimizer.step()

        for b in batches[:5]:  # warm-up
            step(b)
        timed = batches[5:]
        # "reused_heap_every_leaf": the kept heap with the plain backward() (the gradient in
        # the positions too), to measure the parameters-only backward
        runs: dict[str, list[dict]] = {"plain": [], "reused_heap": [],
                                       "reused_heap_every_leaf": []}
        for _ in range(args.repeats):
            for name in runs:
                ctx = reused_heap() if name != "plain" else contextlib.nullcontext()
                with ctx:
                    r0 = resource.getrusage(resource.RUSAGE_SELF)
                    c0, w0 = time.process_time(), time.perf_counter()
                    for b in timed:
                        step(b, every_leaf=name == "reused_heap_every_leaf")
                    c1, w1 = time.process_time(), time.perf_counter()
                    r1 = resource.getrusage(resource.RUSAGE_SELF)
                n = len(timed)
                runs[name].append({"cpu_s_per_step": (c1 - c0) / n,
                                   "wall_s_per_step": (w1 - w0) / n,
                                   "minor_faults_per_step": (r1.ru_minflt - r0.ru_minflt) / n})

    summary = {name: {k: statistics.median(r[k] for r in rows) for k in rows[0]}
               for name, rows in runs.items()}
    ratio = {k: summary["reused_heap"][k] / summary["plain"][k]
             for k in ("cpu_s_per_step", "wall_s_per_step")}
    ratio_leaves = {k: summary["reused_heap"][k] / summary["reused_heap_every_leaf"][k]
                    for k in ("cpu_s_per_step", "wall_s_per_step")}
    result = {"benchmark": "training step", "data": args.data,
              "particles_per_batch": statistics.mean(b.graph.positions.shape[0] for b in timed),
              "edges_per_batch": statistics.mean(b.graph.edge_i.shape[0] for b in timed),
              "identical_gradients": identical, "median": summary,
              "ratio_reused_over_plain": ratio,
              "ratio_parameters_only_over_every_leaf": ratio_leaves, "runs": runs,
              "machine": machine_info()}
    for name, s in summary.items():
        print(f"{name:12s} CPU {s['cpu_s_per_step']:.4f} s/step, wall {s['wall_s_per_step']:.4f}"
              f" s/step, {s['minor_faults_per_step']:.0f} minor faults/step")
    print(f"reused/plain: CPU {ratio['cpu_s_per_step']:.3f}, wall {ratio['wall_s_per_step']:.3f};"
          f" identical gradients: {identical}")
    print(f"parameters-only/every-leaf backward: CPU {ratio_leaves['cpu_s_per_step']:.3f},"
          f" wall {ratio_leaves['wall_s_per_step']:.3f}")
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
