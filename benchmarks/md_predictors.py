"""MD pair predictors, offline: how close can a prediction of the relaxed pairs get before the
first evaluation of a step? (issue 14: one-evaluation steps need ~2e-4 eV/Å)

Along a tight reference trajectory (hexane, the ``benchmarks/md.py`` start, NVT 300 K, dt 0.5 fs,
``warm`` at fmax 1e-10 eV/Å) the exact pair-pair Hessian ``H_k`` and core-pair block ``C_k``
(forward differences, :func:`emlpack.pairs.solvers.difference_blocks`'s scheme) are computed at
every frame, with the exact linear response ``J_k = -H_k^-1 C_k^T`` (d pairs / d cores). Each
predictor of the pairs ``p_k`` at the cores ``c_k`` from the earlier frames is scored by its
linearised first residual ``max |H_k (p_pred - p_k)|`` (eV/Å; the largest pair-force component
the first evaluation would see). Exact blocks are an upper bound on what the carried models of
:class:`~emlpack.pairs.solvers.WarmStartSolver` (relative errors 1-25 %) can give.

Usage: OMP_NUM_THREADS=1 python benchmarks/md_predictors.py
       [--model benchmarks/fixtures/eqm7_small_trained.pt] [--steps 100] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, machine_info, write_json  # noqa: E402
from md import hexane  # noqa: E402

from emlpack.dynamics.md import TRAJECTORY, Watchdog, run_md  # noqa: E402
from emlpack.io import read_structures  # noqa: E402

#: polynomial extrapolation x(n+1) from x(n-k..n), oldest first
WEIGHTS = {1: [-1.0, 2.0], 2: [1.0, -3.0, 3.0], 3: [-1.0, 4.0, -6.0, 4.0],
           4: [1.0, -5.0, 10.0, -10.0, 5.0]}


def main() -> int:
    from emlpack.nn.checkpoint import load_model
    from emlpack.pairs.solvers import energy_gradient_function

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(ROOT / "benchmarks" / "fixtures"
                                           / "eqm7_small_trained.pt"))
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.model, torch.float64).double().eval()
    start = hexane(model)
    with tempfile.TemporaryDirectory() as tmp:
        run_md(args.model, start, args.steps, Path(tmp) / "r", dt_fs=0.5, temperature_K=300,
               relax="warm", seed=0, fmax=1e-10, watchdog=Watchdog(curvature_every=0),
               checkpoint_every=10 * args.steps)
        frames = read_structures(Path(tmp) / "r" / TRAJECTORY)
    cores = np.array([f.positions for f in frames])
    pairs = np.array([f.pairs for f in frames])
    h_pp, resp = [], []
    for f in frames:
        evaluate, _ = energy_gradient_function(model, start.copy(positions=f.positions,
                                                                 pairs=f.pairs))
        x = f.pairs.reshape(-1)
        g0 = evaluate(f.pairs)[1].reshape(-1)
        cols = np.empty((g0.size, x.size))
        for k in range(x.size):
            xk = x.copy()
            xk[k] += 1e-5
            cols[:, k] = (evaluate(xk.reshape(-1, 3))[1].reshape(-1) - g0) / 1e-5
        nc3 = 3 * f.n_cores
        h = 0.5 * (cols[nc3:] + cols[nc3:].T)
        h_pp.append(h)
        resp.append(-np.linalg.solve(h, cols[:nc3].T))  # J = -H^-1 C^T, (3P, 3N)

    def ex(arr, k, order):
        return sum(w * arr[k - order - 1 + i] for i, w in enumerate(WEIGHTS[order]))

    def move(j, dc):
        return (j @ dc.reshape(-1)).reshape(-1, 3)

    def extrapolated(order):  # the "corrected" predictor with the exact J of the last frame
        return lambda k: ex(pairs, k, order) + move(resp[k - 1], cores[k] - ex(cores, k, order))

    predictors = {f"extrapolation order {o} + response (J_k-1)": extrapolated(o)
                  for o in (1, 2, 3, 4)}
    predictors.update({
        "linear response from the last frame (J_k-1)":
            lambda k: pairs[k - 1] + move(resp[k - 1], cores[k] - cores[k - 1]),
        "midpoint, J extrapolated linearly (1.5 J_k-1 - 0.5 J_k-2)":
            lambda k: pairs[k - 1] + move(1.5 * resp[k - 1] - 0.5 * resp[k - 2],
                                          cores[k] - cores[k - 1]),
        "midpoint, J extrapolated quadratically":
            lambda k: pairs[k - 1] + move(2 * resp[k - 1] - 1.5 * resp[k - 2]
                                          + 0.5 * resp[k - 3], cores[k] - cores[k - 1]),
        "trapezoid with the exact J_k of the new frame (not available)":
            lambda k: pairs[k - 1] + move(0.5 * (resp[k - 1] + resp[k]),
                                          cores[k] - cores[k - 1]),
    })
    steps = range(8, len(frames))
    results = {}
    for name, predict in predictors.items():
        r = np.array([np.abs(h_pp[k] @ (predict(k) - pairs[k]).reshape(-1)).max()
                      for k in steps])
        results[name] = {"median": float(np.median(r)), "p90": float(np.percentile(r, 90)),
                         "max": float(r.max()), "fraction_below_2e-4": float(np.mean(r < 2e-4))}
        print(f"{name:62s} median {np.median(r):.2e}  p90 {np.percentile(r, 90):.2e}"
              f"  max {r.max():.2e}  <2e-4: {np.mean(r < 2e-4):.2f}")
    if args.json:
        write_json(args.json, {"benchmark": "md_predictors", "steps": args.steps,
                               "model": str(args.model), "results": results,
                               "machine": machine_info()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
