"""Was an MD run's largest jump the pair solver's or the model's?

    python examples/eqm7/md_jumps.py RUN MODEL

RUN: an MD output folder (``trajectory.xyz`` with every step recorded, ``analysis.json``);
MODEL: the checkpoint it ran with. Prints the per-step energy mismatch |dU + (F0+F1)/2 . dR| per
core (the MD watchdog's energy check, :meth:`emlpack.dynamics.md.Watchdog.energy_mismatch`):
median, 99th percentile, largest and the steps of the largest. Then, at the step of the
largest conserved-quantity jump, it relaxes the pairs from the previous step's pairs moved
rigidly with their nearest cores (:func:`emlpack.geometry.carry_pairs`) and compares: a minimum
far from the trajectory's pairs and lower in energy means the solver jumped (the watchdog now
redoes such steps); the same pairs mean the model's surface itself is discontinuous there.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from emlpack.dynamics.md import TRAJECTORY, Watchdog
from emlpack.geometry import carry_pairs
from emlpack.io import read_structures
from emlpack.nn.checkpoint import load_model
from emlpack.pairs.relax import RelaxOptions, relax_pairs


def main(argv: list[str]) -> None:
    run, model_path = Path(argv[0]), argv[1]
    frames = read_structures(run / TRAJECTORY)
    n = len(frames[0].numbers)
    mismatch = np.array([Watchdog.energy_mismatch(
        (float(a.info["potential_energy"]), a.forces, a.positions),
        (float(b.info["potential_energy"]), b.forces, b.positions))
        for a, b in zip(frames[:-1], frames[1:], strict=True)])
    top = np.argsort(mismatch)[-4:][::-1]
    print(f"{run.name}: {n} cores, energy mismatch per core median {np.median(mismatch):.2e},"
          f" 99th percentile {np.quantile(mismatch, 0.99):.2e}, largest {mismatch.max():.2e} eV;"
          " largest at steps "
          + ", ".join(f"{int(frames[i + 1].info['step'])} ({mismatch[i]:.2g})" for i in top))
    step = int(json.loads((run / "analysis.json").read_text())["analysis"]["max_jump_step"])
    by_step = {int(f.info["step"]): f for f in frames}
    if step not in by_step or step - 1 not in by_step:
        print(f"step {step} or the one before is not in the trajectory")
        return
    before, at = by_step[step - 1], by_step[step]
    model = load_model(model_path).double().eval()
    start = carry_pairs(before.pairs, before.positions, at.positions)
    result = relax_pairs(model, at.copy(pairs=start), RelaxOptions(fmax=1e-6))[0]
    e_traj = float(model.evaluate(at)["energy"])
    moved = np.linalg.norm(at.pairs - start, axis=1).max()
    apart = np.linalg.norm(result.pairs - at.pairs, axis=1).max()
    print(f"step {step} (largest conserved-quantity jump): the trajectory's pairs moved"
          f" {moved:.3f} Å from the rigidly carried ones; relaxing from those"
          f" {'converges' if result.converged else 'does NOT converge'} (smallest curvature"
          f" {result.min_curvature:.3g} eV/Å²) {apart:.3f} Å from the trajectory's pairs, at"
          f" {result.energy - e_traj:+.4f} eV: "
          + ("the solver left a minimum that still exists" if apart > 0.05
             and result.energy < e_traj - 1e-3 else "the same state: the model's surface"))


if __name__ == "__main__":
    main(sys.argv[1:])
