"""Configurations of a crystal for labeling: the field set and the stress set (paper, beta-glycine).

Two sets, because a Berry-phase field and the stress cannot be computed together (CP2K 2023.1,
Quantum ESPRESSO): the *field set* gets a random homogeneous field (uniform in the ball of
radius ``max_field_au`` = 0.01 au, :func:`emlpack.qm.sampling.random_field`) and no stress;
the *stress set* has no field and is labeled with stress.

Two generators of geometries around a reference crystal:

* :func:`random_displacement_sample` (round 0 of the active-learning loop, no Hessian needed):
  Gaussian displacements of the cores (``sigma`` Å) and, for the stress set, a random symmetric
  strain (components uniform in +-``max_strain``);
* :func:`hessian_sample`: the cell-extended normal-mode sample at ``T`` (600 K in the paper) of
  :func:`emlpack.qm.sampling.cell_normal_mode_sample`, from an extended Hessian in (Cartesian
  core positions, 9 cell elements) or a callable returning it: finite differences of DFT, or the
  Born-Oppenheimer Hessian of a trained eMLP (:func:`emlpack.calculators.labeler.bo_cell_hessian`).

Every sample is reproducible from ``(seed, round, set, index)`` alone, so a resumed run
regenerates exactly the configurations whose keys are not yet in the store. The electron pairs
of a sample are the reference pairs carried along (same offset from their nearest core); they
are only a starting guess, the labeler computes the real ones.

The loop (label random displacements -> train -> sample from the model's Hessian -> label more)
is driven by ``examples/beta_glycine/run_study.py``; this module is torch-free.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from emlpack.geometry import carry_pairs
from emlpack.qm.sampling import cell_normal_mode_sample, random_field
from emlpack.structure import Structure

#: the two sets; stress is labeled on the stress set only
SETS = ("field", "stress")

HessianLike = np.ndarray | Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class LabelTask:
    """A configuration to label: store ``key``, input ``structure``, whether to compute stress."""

    key: str
    structure: Structure
    stress: bool


def sample_rng(seed: int, round_index: int, set_name: str, index: int) -> np.random.Generator:
    """The generator of one sample: depends only on its identity (resumable generation)."""
    return np.random.default_rng([int(seed), int(round_index), SETS.index(set_name), int(index)])


def carry_reference_pairs(reference: Structure, positions: np.ndarray,
                          cell: np.ndarray) -> np.ndarray:
    """Reference pairs moved with the cell (same fractional coordinates) and then with their
    nearest core's displacement (minimum image)."""
    return carry_pairs(reference.pairs, reference.positions, positions, reference.cell, cell,
                       reference.pbc)


def random_strain(rng: np.random.Generator, max_strain: float) -> np.ndarray:
    """Symmetric strain tensor (3, 3) with components uniform in +-``max_strain``."""
    e = rng.uniform(-max_strain, max_strain, size=(3, 3))
    return 0.5 * (e + e.T)


def random_displacement_sample(reference: Structure, rng: np.random.Generator,
                               sigma: float = 0.05, max_strain: float = 0.0) -> Structure:
    """Cores displaced by N(0, sigma^2) per component (Å); cell and positions strained by a
    random symmetric strain when ``max_strain`` > 0. No field; labels removed."""
    deform = np.eye(3) + (random_strain(rng, max_strain) if max_strain > 0 else 0.0)
    cell = reference.cell @ deform
    positions = (reference.positions + rng.normal(scale=sigma, size=reference.positions.shape))
    positions = positions @ np.linalg.inv(reference.cell) @ cell
    return _unlabeled(reference, positions, cell)


def hessian_sample(reference: Structure, hessian: HessianLike, rng: np.random.Generator,
                   temperature: float = 600.0, min_eigenvalue: float | None = None
                   ) -> Structure:
    """Cell-extended normal-mode sample at ``temperature`` (K) around ``reference`` from an
    extended Hessian (eV/Å²) in (core positions, cell elements) or a callable returning it.
    ``min_eigenvalue`` (eV/Å²) floors the internal eigenvalues (a model Hessian away from the
    model's own minimum may have soft or negative directions)."""
    positions, cell = cell_normal_mode_sample(
        reference.numbers, reference.positions, reference.cell, hessian, temperature, rng,
        min_eigenvalue=min_eigenvalue)
    return _unlabeled(reference, positions, cell)


def _unlabeled(reference: Structure, positions: np.ndarray, cell: np.ndarray) -> Structure:
    return reference.copy(positions=positions, cell=cell,
                          pairs=carry_reference_pairs(reference, positions, cell),
                          field=np.zeros(3), energy=None, forces=None, pair_forces=None,
                          stress=None, info={})


def with_set(structure: Structure, set_name: str, rng: np.random.Generator,
             max_field_au: float = 0.01) -> tuple[Structure, bool]:
    """The structure prepared for its set: a random field (V/Å, <= ``max_field_au`` au) on
    the field set; zero field and ``stress=True`` on the stress set."""
    if set_name == "field":
        return structure.copy(field=random_field(rng, max_field_au)), False
    if set_name == "stress":
        return structure.copy(field=np.zeros(3)), True
    raise ValueError(f"unknown set {set_name!r} (field, stress)")


def crystal_tasks(reference: Structure, counts: dict[str, int], *, seed: int = 0,
                  round_index: int = 0, hessian: HessianLike | None = None,
                  temperature: float = 600.0, sigma: float = 0.05, max_strain: float = 0.02,
                  max_field_au: float = 0.01, min_eigenvalue: float | None = None,
                  prefix: str = "", molecule_id: str = "crystal") -> list[LabelTask]:
    """Labeling tasks of one round: ``counts[set]`` samples per set, keys
    ``{prefix}r{round}/{set}/{index:04d}``.

    Without ``hessian``: random displacements (``sigma``; strain up to ``max_strain`` on the
    stress set). With ``hessian``: cell-extended normal-mode samples at ``temperature``; the
    field set then keeps the reference cell (its strain is not labeled anyway) by sampling the
    full distribution and restoring the cell with the fractional coordinates kept.
    """
    if hessian is not None and callable(hessian):
        h = hessian(reference.positions, reference.cell)  # evaluate once for all samples
    else:
        h = hessian
    tasks = []
    for set_name in SETS:
        for i in range(int(counts.get(set_name, 0))):
            rng = sample_rng(seed, round_index, set_name, i)
            if h is None:
                s = random_displacement_sample(
                    reference, rng, sigma, max_strain if set_name == "stress" else 0.0)
            else:
                s = hessian_sample(reference, h, rng, temperature, min_eigenvalue)
                if set_name == "field":
                    frac = s.positions @ np.linalg.inv(s.cell)
                    s = _unlabeled(reference, frac @ reference.cell, reference.cell)
            s, stress = with_set(s, set_name, rng, max_field_au)
            key = f"{prefix}r{round_index}/{set_name}/{i:04d}"
            s.info = {"key": key, "molecule_id": molecule_id, "kind": f"{set_name}-r{round_index}"}
            s.source = key
            tasks.append(LabelTask(key, s, stress))
    return tasks
