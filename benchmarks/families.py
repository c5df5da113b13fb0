"""Issue 48's cost table: what each short-range family costs in every path beyond training.

For each model given (trained checkpoints; default the two of
``examples/families/equal_cpu.sh``: SchNet F=G=64/T=3 and PaiNN F=64/T=3 trained for the same
CPU time on mini-eQM7), one thread, the models alternating section by section in one process
(CPU time of this process; on a shared machine only the ratios are meaningful):

* ``energy_forces``: 64 mini-eQM7 validation configurations in batches of 16, float32,
  ``model(graph, forces=True)`` on graphs built beforehand: ms per configuration;
* ``relax``: the same 64 configurations, every pair displaced by 0.05 Å (seeded), relaxed with
  ``relax_pairs`` (float64, the package's defaults, batches of 16): CPU ms per structure,
  iterations and energy+gradient evaluations per structure, failures;
* ``hessian_molecule``: butan-1-ol (15 atoms, RDKit, pairs guessed and relaxed by the model),
  ``extended_hessian`` (method ``fast``: SchNet's closed-form edge Hessian, PaiNN's reverse over
  reverse): CPU s, median of ``--repeats``;
* ``hessian_crystal``: beta-glycine's 20-atom cell (the paper's, at its Wannier centres: the
  molecular models cannot relax a crystal's pairs), the same;
* ``md``: hexane at the model's minimum (as ``benchmarks/md.py``), ``run_md`` NVT 300 K,
  dt 0.5 fs, ``--md-steps`` steps with the default solver: CPU ms per step, evaluations and
  Hessians per step.

Usage: OMP_NUM_THREADS=1 python benchmarks/families.py [--models NAME=PATH ...]
       [--json benchmarks/measured/families.json] [--repeats 3] [--md-steps 40]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, SHARED, CpuClock, benchmark_model, machine_info, write_json  # noqa: E402

DEFAULT_MODELS = (f"schnet={ROOT / 'runs/families/schnet/best.pt'}",
                  f"painn={ROOT / 'runs/families/painn/best.pt'}")


def validation_structures(n: int, seed: int = 0):
    from emlpack.data.shards import read_shards

    sharded = read_shards(ROOT / "datasets" / "mini-eqm7")
    val = sharded.split_indices()["val"]
    pick = np.random.default_rng(seed).choice(val, min(n, len(val)), replace=False)
    return [sharded.structures[k] for k in sorted(pick)]


def relaxed(model, s):
    """``s`` with its pairs relaxed by ``model`` (float64, the package's defaults)."""
    from emlpack.pairs.relax import relax_pairs

    r = relax_pairs(model, s)[0]
    if not r.converged:
        print(f"warning: {s.source}: the pair relaxation did not converge ({r.reason})")
    return s.copy(pairs=r.pairs)


def butanol(model):
    from ase import Atoms

    from emlpack.pairs.guess import guess_pairs
    from emlpack.qm.sampling import molecule_from_smiles
    from emlpack.structure import Structure

    mol = molecule_from_smiles("CCCCO", name="butan-1-ol", seed=0)
    s = Structure(mol.numbers, mol.positions, guess_pairs(Atoms(mol.numbers, mol.positions)),
                  source="butan-1-ol (RDKit)")
    return relaxed(model, s)


def beta_glycine():
    """The paper's cell at its Wannier centres, not relaxed: molecular models cannot relax the
    crystal's pairs (out of their training domain: pairs merge), and the Hessian's cost does
    not depend on where the pairs sit."""
    from emlpack.io import read_structures

    s = read_structures(SHARED / "data" / "beta_glycine_pbe_wannier.xyz")[0]
    return s.copy(field=np.zeros(3))


def timed(f, repeats: int) -> tuple[float, object]:
    """Median CPU seconds of ``repeats`` calls of ``f`` and the last result."""
    times, out = [], None
    for _ in range(repeats):
        clock = CpuClock()
        out = f()
        times.append(clock.elapsed())
    return statistics.median(times), out


def energy_forces(model32, structures, repeats: int) -> dict:
    batches = [structures[i:i + 16] for i in range(0, len(structures), 16)]
    graphs = [model32.graph(b, dtype=torch.float32) for b in batches]

    def run():
        for g in graphs:
            model32(g, forces=True, create_graph=False)["forces"].sum().item()

    run()  # warm-up
    t, _ = timed(run, repeats)
    return {"ms_per_configuration": 1e3 * t / len(structures)}


def relax(model, structures, repeats: int, seed: int = 0) -> dict:
    from emlpack.pairs.relax import relax_pairs

    rng = np.random.default_rng(seed)
    starts = []
    for s in structures:
        d = rng.normal(size=s.pairs.shape)
        d *= 0.05 / np.linalg.norm(d, axis=1, keepdims=True)
        starts.append(s.copy(pairs=s.pairs + d))
    batches = [starts[i:i + 16] for i in range(0, len(starts), 16)]

    def run():
        return [r for b in batches for r in relax_pairs(model, b)]

    relax_pairs(model, starts[:2])  # warm-up
    t, results = timed(run, repeats)
    return {"ms_per_structure": 1e3 * t / len(starts),
            "iterations_mean": float(np.mean([r.iterations for r in results])),
            "evaluations_mean": float(np.mean([r.n_evaluations for r in results])),
            "hessians_mean": float(np.mean([r.n_hessians for r in results])),
            "failed": int(sum(r.failed for r in results)), "n": len(results)}


def hessian(model, s, repeats: int) -> dict:
    from emlpack.properties.hessian import extended_hessian

    extended_hessian(model, s)  # warm-up
    t, (_, h) = timed(lambda: extended_hessian(model, s), repeats)
    return {"s": t, "n_cores": int(s.n_cores), "n_pairs": int(s.n_pairs),
            "size": int(h.shape[0])}


def md(model, steps: int) -> dict:
    from md import hexane

    from emlpack.dynamics.md import run_md

    start = hexane(model)
    with tempfile.TemporaryDirectory() as tmp:
        clock = CpuClock()
        r = run_md(model, start, steps, Path(tmp) / "md", temperature_K=300.0, seed=0,
                   resume=False)
        cpu = clock.elapsed()
    return {"steps": r.steps, "cpu_ms_per_step": 1e3 * cpu / max(1, r.steps),
            "evaluations_per_step": r.evaluations_per_step,
            "hessians_per_step": r.hessians_per_step, "watchdog_events": r.watchdog_events}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS), metavar="NAME=PATH")
    ap.add_argument("--json", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--n-structures", type=int, default=64)
    ap.add_argument("--md-steps", type=int, default=40)
    ap.add_argument("--sections", default="energy_forces,relax,hessian_molecule,"
                    "hessian_crystal,md")
    args = ap.parse_args()
    torch.set_num_threads(1)
    models = {}
    for spec in args.models:
        name, _, path = spec.partition("=")
        if not Path(path).exists():
            print(f"families.py: {path}: no such checkpoint (run examples/families/"
                  "equal_cpu.sh first, or give --models NAME=PATH)")
            return 2
        models[name] = (benchmark_model(path, torch.float64), benchmark_model(path, torch.float32))
    structures = validation_structures(args.n_structures)
    out: dict = {"machine": machine_info(), "models": dict(a.partition("=")[::2]
                                                            for a in args.models),
                 "n_structures": len(structures), "results": {n: {} for n in models}}
    for section in args.sections.split(","):
        for name, (m64, m32) in models.items():  # alternating, model by model
            if section == "energy_forces":
                r = energy_forces(m32, structures, args.repeats)
            elif section == "relax":
                r = relax(m64, structures, args.repeats)
            elif section == "hessian_molecule":
                r = hessian(m64, butanol(m64), args.repeats)
            elif section == "hessian_crystal":
                r = hessian(m64, beta_glycine(), args.repeats)
            elif section == "md":
                r = md(m64, args.md_steps)
            else:
                raise SystemExit(f"families.py: unknown section {section!r}")
            out["results"][name][section] = r
            print(f"{section} {name}: {r}", flush=True)
    names = list(models)
    if len(names) > 1:
        base = out["results"][names[0]]
        keys = {"energy_forces": "ms_per_configuration", "relax": "ms_per_structure",
                "hessian_molecule": "s", "hessian_crystal": "s", "md": "cpu_ms_per_step"}
        out["ratios_to_" + names[0]] = {
            n: {s: out["results"][n][s][k] / base[s][k] for s, k in keys.items() if s in base}
            for n in names[1:]}
        print(out["ratios_to_" + names[0]])
    if args.json:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
