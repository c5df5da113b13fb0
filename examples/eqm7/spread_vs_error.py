"""Ensemble spread against the actual error of a pretrained ensemble.

    python examples/eqm7/spread_vs_error.py [DATA] [MODEL] [--static]

DATA: a data-set folder of the campaign (default ``datasets/mini-eqm7``; its validation and test
molecules are used) and, when present, the authors' six molecules (every 10th frame of
``../shared/data/eqm7_pbe0_subset.xyz``); MODEL: a pretrained name or ensemble folder (default
``mini-eqm7``). The pairs are relaxed from the DFT centres as the calculator does (``--static``:
kept at the DFT centres). Prints, per set, the medians of the energy spread and error per atom
(eV/atom) and of the largest force-component spread and error (eV/Å), their correlations, and
how often the ensemble's spread warnings fire (its calibrated thresholds when it carries them,
else the heuristic ones; :mod:`emlpack.calculators.calibration`), and the 95 % quantiles of the
spreads (what a calibration on that set would set).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from emlpack.calculators.calibration import spread_and_error, warned_fraction
from emlpack.calculators.ensemble import as_ensemble
from emlpack.data.shards import read_shards
from emlpack.io import read_structures

ROOT = Path(__file__).resolve().parents[2]


def main(argv: list[str]) -> None:
    static = "--static" in argv
    argv = [a for a in argv if a != "--static"]
    data = Path(argv[0]) if argv else ROOT / "datasets" / "mini-eqm7"
    ensemble = as_ensemble(argv[1] if len(argv) > 1 else "mini-eqm7")
    thresholds = ensemble.spread_thresholds
    print(f"thresholds: {thresholds.energy:.4f} eV/atom, {thresholds.forces:.3f} eV/Å"
          f" ({thresholds.basis})")
    shards = read_shards(data)
    split = shards.split_indices()
    sets = {name: [shards.structures[i] for i in split[name]] for name in ("val", "test")}
    six = ROOT.parent / "shared" / "data" / "eqm7_pbe0_subset.xyz"
    if six.exists():
        sets["authors' six"] = read_structures(six)[::10]
    for name, structures in sets.items():
        r = spread_and_error(ensemble, structures, relax_pairs=not static)
        warned = warned_fraction(r, thresholds)
        print(f"{name} ({len(structures)} configurations, {len(r['failed'])} failed): energy"
              f" spread/error median {np.median(r['energy_spread']):.3f}/"
              f"{np.median(r['energy_error']):.3f} eV/atom, correlation"
              f" {np.corrcoef(r['energy_spread'], r['energy_error'])[0, 1]:.2f}, warned"
              f" {warned['energy']:.0%}; largest force spread/error median"
              f" {np.median(r['force_spread']):.3f}/{np.median(r['force_error']):.3f} eV/Å,"
              f" correlation {np.corrcoef(r['force_spread'], r['force_error'])[0, 1]:.2f},"
              f" warned {warned['forces']:.0%}; 95 % quantiles of the spreads (the thresholds"
              f" a calibration on this set would give) {np.quantile(r['energy_spread'], 0.95):.4f}"
              f" eV/atom, {np.quantile(r['force_spread'], 0.95):.3f} eV/Å")


if __name__ == "__main__":
    main(sys.argv[1:])
