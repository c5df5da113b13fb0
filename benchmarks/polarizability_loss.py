"""Training step cost of the loss's polarizability term (issue 51, item 2a): CPU and wall time
per optimizer step of the mini-eQM7 study's model (``examples/eqm7/train.yaml``: F=G=64, T=3,
batch 16, float32, augmented) on mini-eQM7 batches, without the term and with it on 4 labelled
configurations of each batch of 16.

The weights start from the shipped ``mini-eqm7`` member 0 (same architecture): a fresh
model's pair Hessian is indefinite at most DFT centres, so the term would leave its labels
out and cost nothing. The labels (made up: 0.6 times the model's own polarizability at the
start, their values do not change the cost) go on 4 configurations of each batch whose pair
Hessian is positive definite there (so that all 4 enter the term). Settings alternate block
by block in one process on the same batches (the machine is shared: only the ratios mean
something), the weights held (each step's loss and backward; no optimizer update, which costs
the same in every setting and would change which labels enter); ``value only``: the term's
polarizabilities without their graph (the exact pair Hessians and the solves), to split its
cost.

Usage: OMP_NUM_THREADS=1 python benchmarks/polarizability_loss.py --json polarizability_loss.json
       [--data datasets/mini-eqm7] [--steps 10] [--repeats 4] [--labelled 4]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, machine_info, write_json  # noqa: E402


def make_trainer(data: Path, out: Path):
    from emlpack.pretrained import resolve_model
    from emlpack.train.config import load_config
    from emlpack.train.trainer import Trainer

    member = resolve_model("mini-eqm7")[0][0]
    cfg = load_config(ROOT / "examples" / "eqm7" / "train.yaml",
                      [f"data.path={data}", f"output.dir={out}", "augmentation.enabled=true",
                       "loss.polarizability=1e-3"])
    trainer = Trainer(cfg)
    trainer.init_weights(member)
    return trainer


def label(batches: list, model, n_labelled: int) -> list[int]:
    """Put labels on ``n_labelled`` configurations of each batch whose pair Hessian at the DFT
    centres is positive definite (in place); returns how many each batch got."""
    from emlpack.properties.response import clamped_polarizabilities

    counts = []
    for batch in batches:
        b = batch.n_structures
        keep = torch.arange(batch.graph.n_structures) < b
        res = clamped_polarizabilities(model, batch.graph.subgraph(keep))
        ok = [k for k in range(b) if not res.problems[k]][:n_labelled]
        batch.has_polarizability = torch.zeros(b, dtype=torch.bool)
        batch.has_polarizability[ok] = True
        batch.polarizability = 0.6 * res.alpha.detach()
        counts.append(len(ok))
    return counts


def main() -> None:
    from emlpack.heap import reused_heap
    from emlpack.train.loss import combine, loss_terms, predict, predict_polarizability

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "datasets" / "mini-eqm7"))
    ap.add_argument("--steps", type=int, default=10, help="steps per timed block")
    ap.add_argument("--repeats", type=int, default=4, help="blocks per setting")
    ap.add_argument("--labelled", type=int, default=4, help="labelled configurations per batch")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp, reused_heap():
        trainer = make_trainer(Path(args.data), Path(tmp))
        model = trainer.model
        batches = [b for b in list(trainer._loader(0)) if b.n_structures == 16]
        batches = batches[: args.steps + 2]
        model.train()
        counts = label(batches, model, args.labelled)

        def step(batch, setting: str) -> None:
            pred = predict(model, batch, trainer.reference)
            if setting == "with term":
                pred.update(predict_polarizability(model, batch))
            elif setting == "value only":
                pred.update(predict_polarizability(model, batch, create_graph=False))
            loss = combine(loss_terms(pred, batch), trainer.weights)
            trainer.optimizer.zero_grad(set_to_none=True)
            loss.backward(inputs=trainer.trained_parameters)

        for b in batches[:2]:  # warm-up
            step(b, "with term")
        timed = batches[2:]
        runs: dict[str, list[dict]] = {"without term": [], "with term": [], "value only": []}
        for _ in range(args.repeats):
            for name in runs:
                c0, w0 = time.process_time(), time.perf_counter()
                for b in timed:
                    step(b, name)
                c1, w1 = time.process_time(), time.perf_counter()
                runs[name].append({"cpu_s_per_step": (c1 - c0) / len(timed),
                                   "wall_s_per_step": (w1 - w0) / len(timed)})

    summary = {name: {k: statistics.median(r[k] for r in rows) for k in rows[0]}
               for name, rows in runs.items()}
    ratios = {name: {k: summary[name][k] / summary["without term"][k]
                     for k in ("cpu_s_per_step", "wall_s_per_step")}
              for name in ("with term", "value only")}
    result = {"benchmark": "training step with the polarizability term", "data": args.data,
              "batch_size": 16, "labelled_per_batch": counts[2:],
              "pairs_per_labelled": statistics.mean(
                  float(b.graph.n_pairs[: b.n_structures][b.has_polarizability].float().mean())
                  for b in timed),
              "particles_per_batch": statistics.mean(b.graph.positions.shape[0] for b in timed),
              "median": summary, "ratio_over_without": ratios, "runs": runs,
              "machine": machine_info()}
    for name, s in summary.items():
        print(f"{name:13s} CPU {s['cpu_s_per_step']:.4f} s/step,"
              f" wall {s['wall_s_per_step']:.4f} s/step")
    for name, r in ratios.items():
        print(f"{name} / without: CPU {r['cpu_s_per_step']:.2f}, wall {r['wall_s_per_step']:.2f}")
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
