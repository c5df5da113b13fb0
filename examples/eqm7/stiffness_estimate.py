"""The electron pairs' stiffness that DFT's polarizabilities imply, against the shipped model's
and the augmentation's label k = 2 Ha/Å² (issue 51, item 2c; the numbers of docs/stiffness.md).

    OMP_NUM_THREADS=1 python examples/eqm7/stiffness_estimate.py [MODEL] [--json OUT]

Molecules: the training molecules of mini-eQM7 with a paper-level (PBE0/aug-cc-pVTZ + DF)
finite-field polarizability in ``examples/qm7_cheap/level_choice/paper/*-alpha.json`` (their
prepared GFN2-xTB optima, zero field). Per molecule, with ``q = 2 e`` and ``N`` its valence
pairs, all stiffnesses in eV/Å²:

* ``k_DFT = q² N / alpha_DFT``: the stiffness of ``N`` independent isotropic harmonic pairs
  (each displaced by ``q F / k``, ``alpha = sum q²/k``) whose polarizability is DFT's
  isotropic one (``alpha`` in e·Å²/V; the cores clamped);
* for every member of MODEL (default ``mini-eqm7``) at the same cores, pairs guessed
  (Foster-Boys at HF/STO-3G) and relaxed: ``alpha_model`` (clamped cores, the response code)
  and ``k_model = q² N / alpha_model`` the same way;
* ``k1_model``: the member's single-pair curvature at its pairs (the mean of the traces / 3 of
  the 3x3 diagonal blocks of its pair Hessian, short range + electrostatics): the stiffness
  one displaced pair meets with the others held, which is what the augmentation's label
  ``k`` prescribes; ``k1_model / k_model`` measures how much the pairs' collective
  relaxation (and their coupling) softens the response beyond independent pairs;
* ``k1_DFT = k1_model * alpha_model / alpha_DFT``: the single-pair curvature that DFT's
  polarizability implies if the member's pair Hessian were scaled as a whole until its
  polarizability is DFT's (``alpha`` is inversely proportional to a uniform scale).

The last line compares the medians with the augmentation's ``k`` and with the training
data's pair-field slope (``field_response_slope``: ``c ~ 1 - K_model / K_DFT``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from ase import Atoms

from emlpack._files import write_text_atomic
from emlpack.calculators.ensemble import as_ensemble
from emlpack.data.shards import read_molecule_table
from emlpack.pairs.guess import guess_pairs
from emlpack.pairs.relax import relax_pairs
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.response import pair_minimum_problem, polarizability_from_hessian
from emlpack.structure import PAIR_CHARGE, Structure
from emlpack.units import AUGMENTATION_K_EV_A2, COULOMB_EV_A, POLARIZABILITY_A3_IN_BOHR3

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "datasets" / "mini-eqm7"
PAPER_ALPHA = ROOT / "examples" / "qm7_cheap" / "level_choice" / "paper"
TO_BOHR3 = COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3
Q2 = PAIR_CHARGE**2


def molecule(name: str) -> Structure:
    """The prepared optimum of ``name`` with guessed pairs."""
    with np.load(DATA / "prepared" / f"{name}.npz") as prep:
        numbers, positions = prep["numbers"], prep["positions"]
    pairs = guess_pairs(Atoms(numbers=numbers, positions=positions))
    return Structure(numbers, positions, pairs, source=f"{name} (prepared optimum)")


def member_numbers(model, s: Structure) -> dict:
    """alpha (bohr³), k_model and k1_model (eV/Å²) of one member at its relaxed pairs."""
    (r,) = relax_pairs(model, [s], fmax=1e-6)
    at = s.copy(pairs=r.pairs)
    _, h = extended_hessian(model, at)
    h = h.numpy()
    problem = pair_minimum_problem(h, at) or r.reason
    alpha = polarizability_from_hessian(h, at)
    nc, n = at.n_cores, at.n_cores + at.n_pairs
    blocks = [h[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(nc, n)]
    iso = float(np.trace(alpha) / 3)
    return {"alpha_iso_bohr3": iso * TO_BOHR3, "alpha_bohr3": (alpha * TO_BOHR3).tolist(),
            "k_model": Q2 * at.n_pairs / iso,
            "k1_model": float(np.mean([np.trace(b) / 3 for b in blocks])),
            "problem": problem}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", nargs="?", default="mini-eqm7")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    split = {m["name"]: m["split"] for m in read_molecule_table(DATA)}
    members = as_ensemble(args.model).members
    rows = []
    for path in sorted(PAPER_ALPHA.glob("*-alpha.json")):
        ref = json.loads(path.read_text())
        name = ref["molecule"]
        if not ref.get("ok") or split.get(name) != "train":
            continue
        s = molecule(name)
        alpha_dft = ref["alpha_iso_bohr3"] / TO_BOHR3  # e·Å²/V
        row = {"molecule": name, "n_heavy": ref["n_heavy"], "n_pairs": s.n_pairs,
               "alpha_dft_iso_bohr3": ref["alpha_iso_bohr3"],
               "k_dft": Q2 * s.n_pairs / alpha_dft, "members": []}
        for member in members:
            m = member_numbers(member.model, s)
            m["k1_dft"] = m["k1_model"] * m["alpha_iso_bohr3"] / ref["alpha_iso_bohr3"]
            diff = np.array(m["alpha_bohr3"]) - np.array(ref["alpha_bohr3"])
            m["alpha_component_mse_bohr6"] = float(np.mean(diff**2))
            row["members"].append(m)
        rows.append(row)
        ok = [m for m in row["members"] if not m["problem"]]
        print(f"{name} ({row['n_heavy']} heavy, {row['n_pairs']} pairs): alpha DFT"
              f" {row['alpha_dft_iso_bohr3']:.1f} bohr³, model"
              f" {np.mean([m['alpha_iso_bohr3'] for m in ok]):.1f}"
              f" ({np.mean([m['alpha_iso_bohr3'] for m in ok]) / row['alpha_dft_iso_bohr3']:.2f}"
              f"x); k_DFT {row['k_dft']:.1f}, k_model {np.mean([m['k_model'] for m in ok]):.1f};"
              f" k1_model {np.mean([m['k1_model'] for m in ok]):.1f},"
              f" k1_DFT {np.mean([m['k1_dft'] for m in ok]):.1f}"
              f" ({len(members) - len(ok)} members left out)", flush=True)
    ok = [(r, m) for r in rows for m in r["members"] if not m["problem"]]
    summary = {
        "k_dft_median": float(np.median([r["k_dft"] for r in rows])),
        "k_model_median": float(np.median([m["k_model"] for _, m in ok])),
        "k1_model_median": float(np.median([m["k1_model"] for _, m in ok])),
        "k1_dft_median": float(np.median([m["k1_dft"] for _, m in ok])),
        "alpha_ratio_median": float(np.median([m["alpha_iso_bohr3"] / r["alpha_dft_iso_bohr3"]
                                               for r, m in ok])),
        "collective_factor_median": float(np.median([m["k1_model"] / m["k_model"]
                                                     for _, m in ok])),
        "alpha_component_mse_bohr6": float(np.mean([m["alpha_component_mse_bohr6"]
                                                    for _, m in ok])),
        "augmentation_k": AUGMENTATION_K_EV_A2, "n_molecules": len(rows),
        "n_member_results": len(ok)}
    print("medians (eV/Å²): k_DFT {k_dft_median:.1f}, k_model {k_model_median:.1f},"
          " k1_model {k1_model_median:.1f}, k1_DFT {k1_dft_median:.1f}; alpha model/DFT"
          " {alpha_ratio_median:.2f} (component MSE {alpha_component_mse_bohr6:.0f} bohr^6);"
          " k1/k_eff {collective_factor_median:.2f};"
          " augmentation k {augmentation_k:.1f}".format(**summary))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.json, json.dumps({"model": args.model, "summary": summary,
                                                 "molecules": rows}, indent=1))


if __name__ == "__main__":
    main()
