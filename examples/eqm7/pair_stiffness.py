"""How stiff a model's electron pairs are, and why (the numbers of docs/pretrained.md).

    python examples/eqm7/pair_stiffness.py [MODEL] [DATA] [--every N]

For the first member of MODEL (default ``mini-eqm7``; a checkpoint path works too) on the
splits of the data-set folder DATA (default ``datasets/mini-eqm7``; every N-th configuration of
the training split, default 4) and on the authors' frames (``../shared/data/eqm7_pbe0_subset.xyz``
when present, every 5th), printed per set:

* ``slope``: :func:`emlpack.train.loss.field_response_slope` of the static pair-force error on
  the field force qE (0: the pairs respond to a field as the DFT centres do; 0.5: they move
  about twice as far);
* ``position error``: the model's equilibrium pairs (relaxed under each label's field) against
  the DFT centres, per Cartesian component (median, rms; Å), beside the rms displacement
  ``|qE| / K`` the field causes for a pair stiffness K of 50 eV/Å^2. A least-squares fit whose
  input errors are as large as its signal learns a diluted slope: position errors comparable
  with the field displacements leave the pairs too soft;
* ``augmentation fit``: on the training configurations (the DFT centres under the labels'
  fields), one pair each displaced by d = 0.01-0.12 Å along a random direction: the model's
  restoring force per Å (``(F(d) - F(0)) / d`` along -d, median; eV/Å^2) against the label the
  augmentation trains on at 0.06-0.12 Å, k = 54.4 eV/Å^2;
* at the DFT optimum of aziridine (``qm7-0011`` in DATA's references), the curvature
  ``2 dE / d^2`` of single-pair displacements of d = 0.01 and 0.1 Å (median over pairs and the
  six directions; eV/Å^2), against the augmentation's k = 2 Ha/Å^2 = 54.4 eV/Å^2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from emlpack.calculators.ensemble import as_ensemble
from emlpack.data.dataset import load_data
from emlpack.data.shards import read_shards
from emlpack.pairs.relax import relax_pairs
from emlpack.structure import PAIR_CHARGE, Structure
from emlpack.train.evaluate import static_errors
from emlpack.train.loss import field_response_slope
from emlpack.units import AUGMENTATION_K_EV_A2

ROOT = Path(__file__).resolve().parents[2]
SHARED_FRAMES = ROOT.parent / "shared/data/eqm7_pbe0_subset.xyz"


def report(member, name: str, structures: list[Structure]) -> None:
    """One line: field slope, pair position errors and field displacement of ``structures``."""
    a = static_errors(member.model, member.reference, structures)
    slope = field_response_slope(a["p_pred"] - a["p_true"], a["p_true"] - a["p_free"])
    results = relax_pairs(member.model, structures, fmax=1e-4)
    kept = [(r, s) for r, s in zip(results, structures, strict=True) if not r.reason]
    err = np.concatenate([(r.pairs - s.pairs).ravel() for r, s in kept])
    qe = np.concatenate([np.tile(PAIR_CHARGE * s.field, (s.n_pairs, 1)).ravel() for _, s in kept])
    print(f"{name:>12} ({len(structures)} configurations, {len(structures) - len(kept)} failed"
          f" relaxations): slope {slope:+.2f}; position error median"
          f" {np.median(np.abs(err)):.4f} Å, rms {np.sqrt(np.mean(err ** 2)):.4f} Å;"
          f" field displacement rms {np.sqrt(np.mean(qe ** 2)) / 50.0:.4f} Å (K = 50 eV/Å^2)")


def augmentation_fit(member, structures: list[Structure], seed: int = 0) -> None:
    """Median restoring stiffness (eV/Å^2) of single displaced pairs against the label's k."""
    rng = np.random.default_rng(seed)
    lengths = (0.01, 0.03, 0.06, 0.09, 0.12)
    secants: dict[float, list[float]] = {d: [] for d in lengths}
    for s in structures:
        i = int(rng.integers(s.n_pairs))
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)

        def restoring(d: float, s=s, i=i, u=u) -> float:
            p = s.pairs.copy()
            p[i] += d * u
            return -float(member.model.evaluate(s.copy(pairs=p))["pair_forces"][i] @ u)

        f0 = restoring(0.0)
        for d in lengths:
            secants[d].append((restoring(d) - f0) / d)
    print(f"augmentation fit ({len(structures)} training configurations, one pair each):"
          f" restoring force per Å (median, eV/Å^2) "
          + ", ".join(f"{np.median(v):.1f} at {d} Å" for d, v in secants.items())
          + f"; the augmentation's label k = {AUGMENTATION_K_EV_A2:.1f}")


def curvature(member, reference: Path) -> None:
    """Median single-pair curvature (eV/Å^2) at the model's pairs of a DFT optimum."""
    ref = json.loads(reference.read_text())
    numbers, positions, pairs = (np.array(ref[k]) for k in ("numbers", "positions", "pairs"))
    (r,) = relax_pairs(member.model, [Structure(numbers, positions, pairs)], fmax=1e-6)
    e0 = member.model.evaluate(Structure(numbers, positions, r.pairs))["energy"]
    out = []
    for d in (0.01, 0.1):
        ks = []
        for i in range(len(r.pairs)):
            for axis in range(3):
                for sign in (1.0, -1.0):
                    p = r.pairs.copy()
                    p[i, axis] += sign * d
                    e = member.model.evaluate(Structure(numbers, positions, p))["energy"]
                    ks.append(2.0 * (e - e0) / d**2)
        out.append(f"d = {d} Å: {np.median(ks):.1f}")
    print(f"single-pair curvature at {reference.stem}'s DFT optimum (median, eV/Å^2): "
          + "; ".join(out) + f" (augmentation k = {AUGMENTATION_K_EV_A2:.1f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", nargs="?", default="mini-eqm7")
    ap.add_argument("data", nargs="?", default=str(ROOT / "datasets/mini-eqm7"))
    ap.add_argument("--every", type=int, default=4, help="training split: every N-th")
    args = ap.parse_args()
    torch.set_num_threads(1)
    member = as_ensemble(args.model).members[0]
    data = read_shards(args.data)
    for name, idx in data.split_indices().items():
        idx = idx[:: args.every] if name == "train" else idx
        if len(idx):
            report(member, name, [data.structures[i] for i in idx])
    train = data.split_indices()["train"]
    augmentation_fit(member, [data.structures[i] for i in train[:: max(1, len(train) // 25)]])
    if SHARED_FRAMES.exists():
        report(member, "authors' 6", load_data(SHARED_FRAMES)[0][::5])
    aziridine = Path(args.data) / "references/pbe0_aug-cc-pvtz/qm7-0011.json"
    if aziridine.exists():
        curvature(member, aziridine)


if __name__ == "__main__":
    main()
