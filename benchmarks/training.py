"""Training step benchmark: CPU time per optimizer step of the mini-eQM7 study's model
(``examples/eqm7/train.yaml``: F=G=64, T=3, batch 16, float32, augmented), per short-range
family and per path of the force loss:

* ``double_backward``: forces by autograd in the positions with ``create_graph=True``, the
  loss differentiated again (the trainer before 2026-12-02; ``predict(parameters_only=False)``);
* ``parameters_only``: the electrostatics' forces computed without a graph (no parameters),
  the short range's through the edge vectors by autograd (``create_graph=True``);
* ``compiled``: the family's written-out gradient through ``torch.compile`` (compiled once
  before timing; one backward pass): SchNet's length gradient
  (:mod:`emlpack.nn.short_range.schnet_gradient`), PaiNN's vector gradient
  (:mod:`emlpack.nn.short_range.painn_gradient`); families with neither capability skip it.

The settings alternate block by block in one process (the machine is shared: only ratios
measured this way mean something); every block takes the same batches, inside
:func:`emlpack.heap.reused_heap` as the trainer runs. Before timing, one step's loss
gradients of every path are compared with the double backward's from the same state
(float32: relative 1e-5 of each parameter tensor's largest gradient). Also reported per
setting: aten operator calls per step and the fraction of the step's CPU time in matrix
products (``torch.profiler``, 5 steps; compiled kernels count in the step's time).

``--scale``: configurations per second of the fastest SchNet path at batch 16, 32 and 64, in
one process and in two 1-thread processes side by side (the study trains two models at once).

Usage: OMP_NUM_THREADS=1 python benchmarks/training.py --json training.json
       [--data datasets/mini-eqm7] [--steps 30] [--repeats 5] [--families schnet painn]
       [--scale]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, machine_info, write_json  # noqa: E402

PATHS = {"double_backward": {"parameters_only": False, "compiled": False},
         "parameters_only": {"parameters_only": True, "compiled": False},
         "compiled": {"parameters_only": True, "compiled": True}}
#: matrix products: aten's and oneDNN's (``mkldnn::_linear_pointwise``, the edge products of
#: :func:`emlpack.nn.short_range.common.edge_linear`)
MATMUL = ("aten::mm", "aten::addmm", "aten::bmm", "aten::matmul", "mkldnn", "aten::linear")


def make_trainer(data: Path, out: Path, family: str, batch_size: int = 16):
    from emlpack.train.config import load_config
    from emlpack.train.trainer import Trainer

    overrides = [f"data.path={data}", f"output.dir={out}", "augmentation.enabled=true",
                 f"training.batch_size={batch_size}"]
    if family != "schnet":  # the study's SchNet sizes; PaiNN's defaults (F=64, T=3)
        overrides.append(f"model.family={family}")
    return Trainer(load_config(ROOT / "examples" / "eqm7" / "train.yaml", overrides))


class Stepper:
    """One trainer and its optimizer step along one path of the force loss."""

    def __init__(self, trainer, parameters_only: bool, compiled: bool) -> None:
        self.trainer, self.parameters_only, self.compiled = trainer, parameters_only, compiled
        # the path before 2026-12-02 with its optimizer then (Adam's default loop, not fused)
        self.optimizer = trainer.optimizer if parameters_only else torch.optim.Adam(
            trainer.trained_parameters, lr=trainer.optimizer.defaults["lr"],
            eps=trainer.optimizer.defaults["eps"])

    def gradients(self, batch) -> list[torch.Tensor]:
        from emlpack.train.loss import combine, loss_terms, predict

        t = self.trainer
        pred = predict(t.model, batch, t.reference, compiled=self.compiled,
                       parameters_only=self.parameters_only)
        loss = combine(loss_terms(pred, batch), t.weights)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward(inputs=t.trained_parameters)
        return [p.grad for p in t.trained_parameters]

    def step(self, batch) -> None:
        self.gradients(batch)
        self.optimizer.step()


def gradient_error(exact: list[torch.Tensor], grads: list[torch.Tensor]) -> float:
    """Largest ``max|g - g_exact| / max(max|g_exact|, 1e-3 G)`` over the parameter tensors
    (``G``: the largest exact gradient of any tensor; the floor is for tensors whose gradient
    vanishes by a cancellation, e.g. the output bias under the live hydride reference)."""
    floor = 1e-3 * max(float(x.abs().max()) for x in exact)
    return max(float((g.double() - x).abs().max()) / max(float(x.abs().max()), floor)
               for x, g in zip(exact, grads, strict=True))


def exact_gradients(trainer, batch) -> list[torch.Tensor]:
    """The double backward's loss gradients in float64 (model and batch converted)."""
    import copy
    from dataclasses import fields, replace

    from emlpack.train.loss import combine, loss_terms, predict

    model = copy.deepcopy(trainer.model).double()
    names = {n for n, p in trainer.model.named_parameters()
             if any(p is q for q in trainer.trained_parameters)}
    params = [p for n, p in model.named_parameters() if n in names]
    values = {f.name: getattr(batch, f.name) for f in fields(batch)}
    values = {k: v.double() if isinstance(v, torch.Tensor) and v.is_floating_point() else v
              for k, v in values.items()}
    b64 = replace(batch, **{**values, "graph": batch.graph.to(torch.float64)})
    loss = combine(loss_terms(predict(model, b64, trainer.reference, parameters_only=False),
                              b64), trainer.weights)
    return list(torch.autograd.grad(loss, params))


def loader_cost(trainer, n_batches: int) -> float:
    """CPU ms per batch of the trainer's loader (augmentation, neighbour lists, graph)."""
    c0 = time.process_time()
    for k, _ in enumerate(trainer._loader(0)):
        if k + 1 == n_batches:
            break
    return 1e3 * (time.process_time() - c0) / n_batches


def profile_step(stepper: Stepper, batches) -> dict:
    """Aten operator calls per step and the matrix products' share of the step's CPU time."""
    from torch.profiler import profile

    with profile() as prof:
        for b in batches:
            stepper.step(b)
    events = prof.key_averages()
    ops = [e for e in events if e.key.startswith("aten::")]
    # self times add up to the profiled CPU time, compiled kernels included
    total = sum(e.self_cpu_time_total for e in events)
    mm = sum(e.self_cpu_time_total for e in events if e.key.startswith(MATMUL))
    return {"operator_calls_per_step": sum(e.count for e in ops) / len(batches),
            "matmul_fraction": mm / total if total else float("nan")}


def bench_steps(args) -> dict:
    from emlpack.heap import reused_heap
    from emlpack.nn.short_range import LengthGradient, VectorGradient

    result: dict = {"families": {}}
    with tempfile.TemporaryDirectory() as tmp:
        steppers: dict[str, Stepper] = {}
        batches = None
        for family in args.families:
            trainer = make_trainer(Path(args.data), Path(tmp) / family, family)
            if batches is None:
                batches = list(trainer._loader(0))[: args.steps + 5]
            start = {k: v.clone() for k, v in trainer.model.state_dict().items()}
            written_out = isinstance(trainer.model.short_range, LengthGradient | VectorGradient)
            paths = [p for p in PATHS if p != "compiled" or written_out]
            exact = exact_gradients(trainer, batches[0])
            for name in paths:
                s = Stepper(trainer, **PATHS[name])
                c0 = time.process_time()
                grads = [g.clone() for g in s.gradients(batches[0])]
                first = time.process_time() - c0
                key = f"{family}/{name}"
                steppers[key] = s
                result["families"].setdefault(family, {})[name] = {
                    "gradient_error": gradient_error(exact, grads), "first_call_cpu_s": first}
            if family == args.families[0]:
                result["loader_ms_per_batch"] = loader_cost(trainer, 40)
            trainer.model.load_state_dict(start)
        timed = batches[5:]
        with reused_heap():
            for s in steppers.values():
                for b in batches[:5]:  # warm-up
                    s.step(b)
            runs: dict[str, list[float]] = {k: [] for k in steppers}
            for _ in range(args.repeats):
                for key, s in steppers.items():
                    c0 = time.process_time()
                    for b in timed:
                        s.step(b)
                    runs[key].append((time.process_time() - c0) / len(timed))
            profiles = {key: profile_step(s, timed[:5]) for key, s in steppers.items()}
    for key, rows in runs.items():
        family, name = key.split("/")
        ms = 1e3 * statistics.median(rows)
        entry = result["families"][family][name]
        entry.update(ms_per_step=ms, configurations_per_s=16 / (ms / 1e3), runs_ms=[
            1e3 * r for r in rows], **profiles[key])
        entry["ratio_to_double_backward"] = ms / (
            1e3 * statistics.median(runs[f"{family}/double_backward"]))
        # the same gradients: as close to float64's as the double backward's, or within 1e-5
        entry["same_gradients"] = entry["gradient_error"] <= max(
            1e-5, 2 * result["families"][family]["double_backward"]["gradient_error"])
    result["particles_per_batch"] = statistics.mean(b.graph.positions.shape[0] for b in timed)
    result["edges_per_batch"] = statistics.mean(b.graph.edge_i.shape[0] for b in timed)
    return result


def scale_worker(data: str, batch_size: int, seconds: float) -> dict:
    """Configurations per second of the compiled SchNet step at ``batch_size`` (one thread)."""
    from emlpack.heap import reused_heap

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(Path(data), Path(tmp), "schnet", batch_size)
        s = Stepper(trainer, parameters_only=True, compiled=True)
        batches = list(trainer._loader(0))
        with reused_heap():
            for b in batches[:3]:
                s.step(b)
            n, c0, w0 = 0, time.process_time(), time.perf_counter()
            while time.perf_counter() - w0 < seconds:
                b = batches[3 + n % (len(batches) - 3)]
                s.step(b)
                n += b.n_structures
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return {"batch_size": batch_size, "configurations_per_cpu_s": n / cpu,
            "configurations_per_wall_s": n / wall}


def bench_scale(args) -> dict:
    """``scale_worker`` at 16, 32, 64 configurations: one process, then two side by side."""
    cmd = [sys.executable, __file__, "--data", args.data, "--worker-seconds",
           str(args.worker_seconds)]
    out: dict = {"one_process": [], "two_processes": []}
    for bs in (16, 32, 64):
        one = subprocess.run([*cmd, "--worker", str(bs)], capture_output=True, text=True,
                             check=True)
        out["one_process"].append(json.loads(one.stdout.strip().splitlines()[-1]))
        procs = [subprocess.Popen([*cmd, "--worker", str(bs)], stdout=subprocess.PIPE,
                                  text=True) for _ in range(2)]
        rows = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
        out["two_processes"].append({"batch_size": bs, "per_process": rows,
                                     "configurations_per_wall_s": sum(
                                         r["configurations_per_wall_s"] for r in rows)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "datasets" / "mini-eqm7"))
    ap.add_argument("--steps", type=int, default=30, help="steps per timed block")
    ap.add_argument("--repeats", type=int, default=5, help="blocks per setting")
    ap.add_argument("--families", nargs="+", default=["schnet", "painn"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--scale", action="store_true", help="also the batch-size scaling")
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--worker-seconds", type=float, default=60.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.worker is not None:
        print(json.dumps(scale_worker(args.data, args.worker, args.worker_seconds)))
        return
    result = {"benchmark": "training step", "data": args.data, **bench_steps(args)}
    for family, paths in result["families"].items():
        for name, e in paths.items():
            print(f"{family:7s} {name:16s} {e['ms_per_step']:7.1f} ms/step"
                  f" ({e['ratio_to_double_backward']:.3f}x), {e['operator_calls_per_step']:.0f}"
                  f" ops/step, matmul {100 * e['matmul_fraction']:.0f} %, gradient error"
                  f" {e['gradient_error']:.1e}")
    print(f"loader: {result['loader_ms_per_batch']:.1f} ms/batch")
    if args.scale:
        result["scale"] = bench_scale(args)
        for row in result["scale"]["one_process"]:
            print(f"batch {row['batch_size']}: {row['configurations_per_cpu_s']:.0f}"
                  " configurations per CPU second (one process)")
        for row in result["scale"]["two_processes"]:
            print(f"batch {row['batch_size']}: {row['configurations_per_wall_s']:.0f}"
                  " configurations per second (two processes)")
    result["machine"] = machine_info()
    if args.json:
        write_json(args.json, result)


if __name__ == "__main__":
    main()
