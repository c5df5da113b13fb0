"""When is an ensemble's spread large? Thresholds calibrated on molecules the models did not
train on, and the spread set against the actual error.

:func:`calibrate_spread` evaluates an ensemble the way users do (:class:`EMLPCalculator`, every
member relaxing its own electron pairs unless ``relax_pairs=False``) on labeled configurations
held out from training (the validation molecules of a data set) and sets each warning threshold
at a quantile of their spreads: with the default 0.95 a warning says "this spread is larger than
on 95 % of the configurations of molecules that are in the models' domain", the usual
out-of-distribution reading of an ensemble (no distribution is assumed). The returned record is
what :func:`emlpack.pretrained.export_pretrained` stores in every member
(``spread_calibration``) and what :func:`emlpack.calculators.ensemble.spread_thresholds` reads.
It also records how much larger the error typically is than the spread (``error_over_spread``,
ratio of medians), since a quiet spread is no proof of accuracy.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from ase.calculators.calculator import CalculationFailed

from emlpack.calculators.ase import EMLPCalculator
from emlpack.calculators.ensemble import ModelEnsemble, SpreadThresholds
from emlpack.io.ase_convert import structure_to_atoms
from emlpack.structure import Structure

#: the quantities of :func:`spread_and_error`, per configuration
SPREAD_KEYS = ("energy_spread", "energy_error", "force_spread", "force_error")


def result_spread(results: dict, n_atoms: int) -> dict[str, float]:
    """The spread measures of one :class:`EMLPCalculator` ensemble result (its ``*_std``
    entries, population std over the members): ``energy_spread`` (eV/atom), ``force_spread``
    (largest spread of a core-force component, eV/Å) and ``pair_spread`` (largest spread of an
    electron-pair coordinate, Å; NaN without ``electron_pairs_std``): the measures the
    warnings, the calibration and active learning's selection read."""
    pairs = results.get("electron_pairs_std")
    return {"energy_spread": float(results["energy_std"]) / max(int(n_atoms), 1),
            "force_spread": float(np.max(results["forces_std"], initial=0.0)),
            "pair_spread": float("nan") if pairs is None else float(np.max(pairs, initial=0.0))}


def spread_and_error(ensemble: ModelEnsemble, structures: Sequence[Structure],
                     relax_pairs: bool = True) -> dict:
    """Per configuration: the ensemble's energy spread and absolute error per atom (eV/atom),
    and its largest force-component spread and largest force-component error (eV/Å), as
    arrays; ``failed``: the indices whose pair relaxation failed (left out of the arrays).
    The pairs start from the labeled centres (relaxed from there unless ``relax_pairs`` is
    False); the errors are against each configuration's labels, on the DFT scale."""
    out: dict[str, list] = {key: [] for key in SPREAD_KEYS}
    failed = []
    calculator_log = logging.getLogger("emlpack.calculators.ase")
    level = calculator_log.level
    calculator_log.setLevel(logging.ERROR)  # the calculator's warnings: not for this loop
    try:
        for k, s in enumerate(structures):
            atoms = structure_to_atoms(s)
            atoms.calc = EMLPCalculator(ensemble, relax_pairs=relax_pairs, check_bonding=False)
            try:
                energy = atoms.get_potential_energy()
            except CalculationFailed:
                failed.append(k)
                continue
            n = len(atoms)
            spread = result_spread(atoms.calc.results, n)
            out["energy_spread"].append(spread["energy_spread"])
            out["energy_error"].append(abs(energy - s.energy) / n)
            out["force_spread"].append(spread["force_spread"])
            out["force_error"].append(float(np.max(np.abs(atoms.get_forces() - s.forces))))
    finally:
        calculator_log.setLevel(level)
    result: dict = {key: np.asarray(value, float) for key, value in out.items()}
    result["failed"] = failed
    return result


def calibrate_spread(ensemble: ModelEnsemble, structures: Sequence[Structure], set_name: str,
                     quantile: float = 0.95, relax_pairs: bool = True,
                     min_configurations: int = 20) -> dict:
    """Spread thresholds at ``quantile`` of the spreads on ``structures`` (labeled
    configurations of molecules held out from training), as the JSON-able record
    ``export_pretrained(..., spread_calibration=)`` stores: ``energy_eV_per_atom``,
    ``forces_eV_per_A``, ``quantile``, ``set`` (``set_name``, how the card and the warnings
    name the configurations), ``configurations`` (evaluated), ``failed`` (pair relaxations
    that failed), ``members``, ``pairs`` ("relaxed" or "labeled centres"), and the medians of
    spread and error with their ratio ``error_over_spread``. Raises ValueError below
    ``min_configurations`` evaluated configurations (too few to place the quantile)."""
    if len(ensemble) < 2:
        raise ValueError("a spread needs an ensemble of at least two models")
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"quantile must lie between 0 and 1, got {quantile}")
    r = spread_and_error(ensemble, structures, relax_pairs)
    if len(r["energy_spread"]) < min_configurations:
        raise ValueError(f"{len(r['energy_spread'])} configurations of {set_name} evaluated"
                         f" ({len(r['failed'])} failed): fewer than {min_configurations}, too"
                         " few to place the quantile")
    median = {key: float(np.median(r[key])) for key in SPREAD_KEYS}
    return {
        "energy_eV_per_atom": float(np.quantile(r["energy_spread"], quantile)),
        "forces_eV_per_A": float(np.quantile(r["force_spread"], quantile)),
        "quantile": float(quantile),
        "set": set_name,
        "configurations": int(len(r["energy_spread"])),
        "failed": len(r["failed"]),
        "members": len(ensemble),
        "pairs": "relaxed" if relax_pairs else "labeled centres",
        "median": median,
        "error_over_spread": {
            "energy": median["energy_error"] / max(median["energy_spread"], 1e-300),
            "forces": median["force_error"] / max(median["force_spread"], 1e-300)},
    }


def warned_fraction(r: dict, thresholds: SpreadThresholds) -> dict[str, float]:
    """How often ``thresholds`` warn on the configurations of a :func:`spread_and_error`
    result: by energy spread, by force spread, by either."""
    e = r["energy_spread"] > thresholds.energy
    f = r["force_spread"] > thresholds.forces
    n = max(len(e), 1)
    return {"energy": float(e.sum() / n), "forces": float(f.sum() / n),
            "either": float((e | f).sum() / n)}
