"""Relaxation benchmark: emlpack's batched pair relaxation vs SciPy BFGS, float64.

Start geometries: shared eqm7 configurations (1s core centres removed), a subset spread evenly
over the 6 molecules (``--limit``, default 64), with every electron pair displaced by a random
vector of length 0.05 Å (seeded). ``--model fixture``: paper-size model with the fixture
(random) weights; ``--model trained``: the small trained model in ``benchmarks/fixtures``.

* emlpack: ``relax_pairs(model, batch, fmax=..., initial_hessian=--method)`` on batches of
  ``--batch-size`` structures;
  time per structure = batch wall time / batch size.
* SciPy: ``scipy.optimize.minimize(method='BFGS', jac=True, options={'gtol': tol})`` one
  structure at a time, energy and gradient from the same model (float64, graph built once per
  structure, only the pair positions change).

Convergence criterion, the same for both: the largest |pair-force component| < ``--tol``
(eV/Å; SciPy's gtol is the infinity norm of the gradient). emlpack's own criterion is the
per-pair force norm, so it is given ``fmax = tol`` and its result is re-checked with the
component criterion. A structure fails when it does not converge or when two pairs merged
(closer than 0.1 Å; with these random weights some pairs merge, see the fixtures README).

Warm-up (not timed): two iterations of the first batch, a small relaxation and one exact
pair Hessian, so that one-off costs of the process (the first ``torch.func`` transform imports
``torch._dynamo``: ~1.3 s CPU; the SchNet filter table of a large batch: ~0.15 s; measured)
fall outside both timings.

Default path (``default_path``): the same batches relaxed with ``relax_pairs``' defaults, i.e.
with the curvature check at the result (smallest pair-Hessian eigenvalue by Davidson) that
the comparison above leaves out (SciPy has none); what the calculator and ``emlp evaluate``
pay. Wall and CPU time per structure, the same repeats.

Hexane (``hexane_lewis``): RDKit hexane (seed 0) with the Lewis-structure pair guess, relaxed
alone with the default method at ``fmax = --tol``, wall and CPU time (best of 3).

Usage: python benchmarks/relax.py --json benchmarks/results/relax.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import scipy.optimize
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    CpuClock,
    benchmark_model,
    load_structures,
    machine_info,
    write_json,
)

from emlpack.pairs.relax import pair_hessian, relax_pairs  # noqa: E402

MERGE_DISTANCE = 0.1  # Å


def select(structures, limit: int) -> list[int]:
    """``limit`` frame indices spread evenly over the molecules (blocks of equal formula)."""
    blocks: dict[str, list[int]] = {}
    for k, s in enumerate(structures):
        blocks.setdefault(str(sorted(s.numbers.tolist())), []).append(k)
    groups = list(blocks.values())
    per = [limit // len(groups) + (g < limit % len(groups)) for g in range(len(groups))]
    out = []
    for idx, m in zip(groups, per, strict=False):
        out += [idx[int(t)] for t in np.linspace(0, len(idx) - 1, m)] if m else []
    return sorted(out)


def displaced(s, rng, amount: float):
    v = rng.normal(size=s.pairs.shape)
    v *= amount / np.linalg.norm(v, axis=1, keepdims=True)
    return s.copy(pairs=s.pairs + v)


def min_pair_distance(pairs: np.ndarray) -> float:
    if len(pairs) < 2:
        return np.inf
    d = np.linalg.norm(pairs[:, None] - pairs[None], axis=-1)
    d[np.diag_indices(len(pairs))] = np.inf
    return float(d.min())


def scipy_relax(model, s, tol: float, max_iter: int) -> dict:
    t0 = time.perf_counter()
    g = model.graph(s, dtype=torch.float64)
    pair_idx = torch.nonzero(g.is_pair).squeeze(1)
    n_eval = 0

    def fun(x):
        nonlocal n_eval
        n_eval += 1
        xt = torch.tensor(x.reshape(-1, 3), dtype=torch.float64, requires_grad=True)
        e = model.energy(g, g.positions.index_put((pair_idx,), xt)).sum()
        (grad,) = torch.autograd.grad(e, xt)
        return float(e.detach()), grad.numpy().reshape(-1).copy()

    res = scipy.optimize.minimize(
        fun, s.pairs.reshape(-1), method="BFGS", jac=True,
        options={"gtol": tol, "maxiter": max_iter},
    )
    wall = time.perf_counter() - t0
    _, grad = fun(res.x)  # not counted: re-check the criterion at the returned point
    n_eval -= 1
    pairs = res.x.reshape(-1, 3)
    gmax = float(np.abs(grad).max())
    merged = min_pair_distance(pairs) < MERGE_DISTANCE
    return {
        "time": wall, "evaluations": n_eval, "iterations": int(res.nit),
        "converged": bool(gmax < tol), "merged": merged, "energy": float(res.fun),
        "max_grad_component": gmax, "message": str(res.message),
    }


def ours_relax(model, batch, tol: float, max_iter: int, method: str) -> tuple[float, list[dict]]:
    t0 = time.perf_counter()
    clock = CpuClock()
    results = relax_pairs(
        model, batch, fmax=tol, max_iterations=max_iter, initial_hessian=method,
        check_curvature=False,
    )
    wall = time.perf_counter() - t0
    cpu = clock.elapsed()
    out = []
    for r in results:
        gmax = float(np.abs(r.pair_forces).max()) if len(r.pair_forces) else 0.0
        out.append({
            "evaluations": r.n_evaluations, "hessians": r.n_hessians, "iterations": r.iterations,
            "converged": gmax < tol,
            "merged": min_pair_distance(r.pairs) < MERGE_DISTANCE, "energy": r.energy,
            "max_grad_component": gmax, "reason": r.reason,
        })
    return wall, cpu, out


def hexane_lewis(model, tol: float, method: str, repeats: int = 3) -> dict:
    """Relax the pairs of RDKit hexane from the Lewis guess alone (best of ``repeats``)."""
    from ase import Atoms

    from emlpack.pairs.guess import guess_pairs
    from emlpack.qm.sampling import molecule_from_smiles
    from emlpack.structure import Structure

    mol = molecule_from_smiles("CCCCCC", name="hexane", seed=0)
    pairs = guess_pairs(Atoms(mol.numbers, mol.positions), method="lewis")
    s = Structure(mol.numbers, mol.positions, pairs, source="hexane (RDKit, Lewis pairs)")
    walls, cpus = [], []
    for _ in range(repeats):
        t0, clock = time.perf_counter(), CpuClock()
        (r,) = relax_pairs(model, [s], fmax=tol, initial_hessian=method)
        walls.append(time.perf_counter() - t0)
        cpus.append(clock.elapsed())
    return {"wall_s": min(walls), "cpu_s": min(cpus), "evaluations": r.n_evaluations,
            "iterations": r.iterations, "hessians": r.n_hessians, "reason": r.reason,
            "energy": r.energy, "max_force": r.max_force}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the results to this file (atomically)")
    ap.add_argument("--limit", type=int, default=64, help="number of structures")
    ap.add_argument("--batch-size", type=int, default=64, help="emlpack batch size")
    ap.add_argument("--repeats", type=int, default=1, help="timed repeats of each method")
    ap.add_argument("--tol", type=float, default=1e-4, help="max |gradient component|, eV/Å")
    ap.add_argument("--displacement", type=float, default=0.05, help="pair displacement, Å")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-iterations", type=int, default=1000, help="SciPy maxiter")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    ap.add_argument("--method", choices=["coulomb", "bfgs", "exact"], default="coulomb",
                    help="emlpack relax_pairs initial_hessian (coulomb: analytic electrostatic"
                    " pair Hessian + SR1 short-range model, the default; exact: Newton with exact"
                    " pair Hessians, slower here)")
    ap.add_argument("--model", default="fixture",
                    help="'fixture' (paper size, random fixture weights), 'trained' (the small"
                    " trained model benchmarks/fixtures/eqm7_small_trained.pt) or a checkpoint")
    ap.add_argument("--max-our-iterations", type=int, default=200)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    everything = load_structures()
    frames = select(everything, args.limit)
    rng = np.random.default_rng(args.seed)
    starts = [displaced(everything[k], rng, args.displacement) for k in frames]
    model = benchmark_model(args.model)
    batches = [starts[k : k + args.batch_size] for k in range(0, len(starts), args.batch_size)]

    # warm-up (builds the filter table of a large batch once, as any long-lived process)
    relax_pairs(model, batches[0], fmax=args.tol, initial_hessian=args.method, max_iterations=2,
                check_curvature=False)
    relax_pairs(model, starts[:2], fmax=args.tol, initial_hessian=args.method)
    pair_hessian(model, starts[0])  # warm-up of torch.func (imports torch._dynamo once)
    ours_times, scipy_runs = [], []
    ours_cpu = scipy_cpu = 0.0
    for rep in range(args.repeats):
        # alternate: our batches, then SciPy structure by structure
        per_structure, ours = [], []
        for b in batches:
            wall, cpu, res = ours_relax(model, b, args.tol, args.max_our_iterations, args.method)
            per_structure += [wall / len(b)] * len(b)
            ours_cpu += cpu
            ours += res
        ours_times.append(per_structure)
        clock = CpuClock()
        scipy_runs.append([scipy_relax(model, s, args.tol, args.max_iterations) for s in starts])
        scipy_cpu += clock.elapsed()
        print(f"repeat {rep + 1}: ours {statistics.median(per_structure):.4f} s/structure,"
              f" SciPy {statistics.median(r['time'] for r in scipy_runs[-1]):.4f} s/structure",
              flush=True)
    default_wall, default_cpu, default_failed = [], 0.0, 0
    for _ in range(args.repeats):
        for b in batches:
            t0, clock = time.perf_counter(), CpuClock()
            res = relax_pairs(model, b, fmax=args.tol, max_iterations=args.max_our_iterations,
                              initial_hessian=args.method)
            default_wall.append((time.perf_counter() - t0) / len(b))
            default_cpu += clock.elapsed()
            default_failed += sum(r.failed for r in res)
    ours_t = [statistics.median(t) for t in zip(*ours_times, strict=False)]
    scipy_t = [statistics.median(r["time"] for r in rs) for rs in zip(*scipy_runs, strict=False)]
    sp = scipy_runs[-1]

    def failures(rs):
        return {
            "non_converged": sum(not r["converged"] for r in rs),
            "merged_pairs": sum(r["merged"] for r in rs),
            "failed": sum((not r["converged"]) or r["merged"] for r in rs),
        }

    ours_med = statistics.median(ours_t)
    scipy_med = statistics.median(scipy_t)
    out = {
        "benchmark": "relax",
        "n_structures": len(starts),
        "frames": frames,
        "displacement_A": args.displacement,
        "seed": args.seed,
        "dtype": "float64",
        "convergence": f"max |dE/dr| over pair components < {args.tol:g} eV/Å for both"
        f" (SciPy gtol={args.tol:g}, infinity norm; emlpack fmax={args.tol:g} on per-pair"
        " norms, which implies it)",
        "merge_distance_A": MERGE_DISTANCE,
        "emlpack": {
            "method": f"relax_pairs(initial_hessian={args.method!r}, check_curvature=False)",
            "batch_sizes": [len(b) for b in batches],
            "median_time_per_structure_s": ours_med,
            "time_per_structure_s": ours_t,
            "median_evaluations": statistics.median(r["evaluations"] for r in ours),
            "mean_evaluations": statistics.fmean(r["evaluations"] for r in ours),
            "median_hessians": statistics.median(r["hessians"] for r in ours),
            "failures": failures(ours),
            "per_structure": ours,
        },
        "scipy": {
            "version": scipy.__version__,
            "method": "BFGS",
            "median_time_per_structure_s": scipy_med,
            "median_evaluations": statistics.median(r["evaluations"] for r in sp),
            "mean_evaluations": statistics.fmean(r["evaluations"] for r in sp),
            "failures": failures(sp),
            "per_structure": sp,
        },
        "speedup_vs_scipy": scipy_med / ours_med,
        "speedup_vs_scipy_total_wall": sum(scipy_t) / sum(ours_t),
        "speedup_vs_scipy_cpu": scipy_cpu / max(ours_cpu, 1e-12),
        "cpu_time_s": {"emlpack": ours_cpu, "scipy": scipy_cpu},
        "default_path": {
            "method": f"relax_pairs(initial_hessian={args.method!r}) with its curvature check",
            "median_time_per_structure_s": statistics.median(default_wall),
            "cpu_time_per_structure_s": default_cpu / (args.repeats * len(starts)),
            "failed": default_failed // args.repeats,
        },
        "hexane_lewis": hexane_lewis(model, args.tol, args.method),
        "model": args.model,
        "repeats": args.repeats,
        "machine": machine_info(),
    }
    if args.json:
        write_json(args.json, out)
    print(f"ours {ours_med:.4f} s/structure, {out['emlpack']['median_evaluations']} evaluations,"
          f" failures {out['emlpack']['failures']}")
    print(f"SciPy {scipy_med:.4f} s/structure, {out['scipy']['median_evaluations']} evaluations,"
          f" failures {out['scipy']['failures']}")
    dp = out["default_path"]
    print(f"default path (with the curvature check): {dp['median_time_per_structure_s']:.4f}"
          f" s/structure wall, {dp['cpu_time_per_structure_s']:.4f} s CPU, failed {dp['failed']}")
    hx = out["hexane_lewis"]
    print(f"hexane from the Lewis guess: {hx['wall_s']:.3f} s wall, {hx['cpu_s']:.3f} s CPU,"
          f" {hx['evaluations']} evaluations {hx['reason']}")
    print(f"speedup_vs_scipy {out['speedup_vs_scipy']:.1f} (total wall"
          f" {out['speedup_vs_scipy_total_wall']:.1f}, CPU {out['speedup_vs_scipy_cpu']:.1f})")
    return out


if __name__ == "__main__":
    main()
