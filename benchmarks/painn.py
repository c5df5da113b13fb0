"""PaiNN against SchNet on one training-size graph: energy+forces and a training-like step.

The graph: 16 configurations of the mini-eQM7 training split drawn with ``--seed`` (about 500
particles and 5,600 half-list edges at the 4 Å cutoff, one training batch). Timed per model:

* ``energy_forces``: atomic energies summed, forces ``-dE/dR`` by autograd (no graph kept);
* ``train_step``: energy and force loss (MSE against fixed random targets), forces with
  ``create_graph=True``, the loss differentiated to the parameters (a double backward), as the
  trainer's step without the electrostatics.

Models: PaiNN F=64/T=3 and F=128/T=3 (n_rbf 20) and SchNet F=G=64/T=3 (n_rbf 32, as
``examples/eqm7/train.yaml``), default initialisation, seed 0. Each timing is the median of
``--repeats`` blocks of ``--steps`` calls (CPU time of this process), the models alternating
block by block (the machine is shared, so ratios are the meaningful numbers), inside
:func:`emlpack.heap.reused_heap` as the trainer runs (``--plain-heap``: glibc's defaults).

Usage: OMP_NUM_THREADS=1 python benchmarks/painn.py --json painn.json
       [--data datasets/mini-eqm7] [--dtype float32] [--steps 10] [--repeats 5]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, CpuClock, machine_info, write_json  # noqa: E402


def training_graph(data: Path, seed: int, n_structures: int = 16, cutoff: float = 4.0):
    """``(numbers, positions, i, j, shifts @ cell)`` of ``n_structures`` training configurations."""
    from emlpack.data.shards import read_shards
    from emlpack.nn.graph import collate

    sharded = read_shards(data)
    train = sharded.split_indices()["train"]
    pick = np.random.default_rng(seed).choice(train, n_structures, replace=False)
    g = collate([sharded.structures[k] for k in pick], cutoff, 1.0)
    offsets = torch.einsum("ek,ekl->el", g.edge_shift, g.cell[g.batch[g.edge_i]])
    return g.numbers, g.positions, g.edge_i, g.edge_j, offsets


def build(family: str, **params) -> torch.nn.Module:
    from emlpack.nn.short_range.painn import PaiNN
    from emlpack.nn.short_range.schnet import SchNet

    torch.manual_seed(0)
    return {"painn": PaiNN, "schnet": SchNet}[family](**params)


def runners(model: torch.nn.Module, family: str, graph, dtype: torch.dtype):
    numbers, positions, i, j, offsets = graph
    positions, offsets = positions.to(dtype), offsets.to(dtype)
    model = model.to(dtype)
    params = [p for p in model.parameters() if p.requires_grad]
    gen = torch.Generator().manual_seed(1)
    target_e = torch.randn((), generator=gen, dtype=dtype)
    target_f = torch.randn(positions.shape, generator=gen, dtype=dtype)

    def energy(pos: torch.Tensor) -> torch.Tensor:
        d = pos.index_select(0, j) - pos.index_select(0, i) + offsets
        return model(numbers, d, i, j).sum()  # both families take the edge vectors

    def energy_forces() -> None:
        pos = positions.clone().requires_grad_(True)
        e = energy(pos)
        (g,) = torch.autograd.grad(e, pos)

    def train_step() -> None:
        pos = positions.clone().requires_grad_(True)
        e = energy(pos)
        (g,) = torch.autograd.grad(e, pos, create_graph=True)
        loss = (e - target_e) ** 2 + ((-g - target_f) ** 2).mean()
        grads = torch.autograd.grad(loss, params)
        assert all(torch.isfinite(x).all() for x in grads)

    return {"energy_forces": energy_forces, "train_step": train_step}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "datasets" / "mini-eqm7"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--steps", type=int, default=10, help="calls per timed block")
    ap.add_argument("--repeats", type=int, default=5, help="blocks per model and task")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    ap.add_argument("--plain-heap", action="store_true",
                    help="glibc's default heap instead of emlpack.heap.reused_heap")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from emlpack.heap import reused_heap

    with contextlib.nullcontext() if args.plain_heap else reused_heap():
        out = measure(args)
    if args.json:
        write_json(args.json, out)


def measure(args: argparse.Namespace) -> dict:
    """Time every model on the graph; the JSON document."""
    dtype = getattr(torch, args.dtype)
    graph = training_graph(Path(args.data), args.seed)
    models = {
        "painn_F64_T3": ("painn", {"n_features": 64, "n_interactions": 3, "n_rbf": 20}),
        "painn_F128_T3": ("painn", {"n_features": 128, "n_interactions": 3, "n_rbf": 20}),
        "schnet_F64_G64_T3": ("schnet", {"n_features": 64, "n_filters": 64, "n_rbf": 32,
                                         "n_interactions": 3}),
    }
    runs, info = {}, {}
    for name, (family, params) in models.items():
        model = build(family, **params)
        runs[name] = runners(model, family, graph, dtype)
        info[name] = {"family": family, "params": params,
                      "n_parameters": sum(p.numel() for p in model.parameters())}
        for fn in runs[name].values():  # warm-up
            fn()
    times = {name: {task: [] for task in r} for name, r in runs.items()}
    for _ in range(args.repeats):
        for task in ("energy_forces", "train_step"):
            for name, r in runs.items():
                clock = CpuClock()
                for _ in range(args.steps):
                    r[task]()
                times[name][task].append(clock.elapsed() / args.steps)
    out = {
        "benchmark": "painn",
        "graph": {"n_particles": int(graph[0].shape[0]), "n_edges": int(graph[2].shape[0]),
                  "n_structures": 16, "seed": args.seed, "data": str(args.data)},
        "dtype": args.dtype,
        "heap": "glibc default" if args.plain_heap else "emlpack.heap.reused_heap",
        "steps": args.steps,
        "repeats": args.repeats,
        "machine": machine_info(),
        "models": {},
    }
    base = times["schnet_F64_G64_T3"]
    for name in runs:
        med = {task: statistics.median(t) for task, t in times[name].items()}
        out["models"][name] = {
            **info[name],
            **{f"{task}_ms": 1e3 * m for task, m in med.items()},
            **{f"{task}_ms_all": [1e3 * x for x in t] for task, t in times[name].items()},
            **{f"{task}_vs_schnet": m / statistics.median(base[task]) for task, m in med.items()},
        }
        print(f"{name:20s} {info[name]['n_parameters']:8d} params  "
              + "  ".join(f"{task} {1e3 * m:7.1f} ms" for task, m in med.items()))
    return out


if __name__ == "__main__":
    main()
