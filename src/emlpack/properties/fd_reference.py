"""Reference crystal tensors by finite differences with any labeler (DFT or a model).

A *labeler* is any callable ``labeler(structure, *, stress=False) -> Structure`` that returns
the structure labeled: ``energy`` (eV), ``forces`` (eV/Å), ``pairs`` = the electron pairs
(valence Wannier centres, Å) of the self-consistent state, ``stress`` (eV/Å³, ASE sign: only
for ``stress=True``, never together with a field) and the ``field`` (V/Å) it was run with
(:class:`emlpack.qm.cp2k.CP2KLabeler`, or :class:`emlpack.calculators.labeler.ModelLabeler`
for an eMLP). All tensors here are *ion-clamped*: the cores stay at their fractional
coordinates (only the electrons respond), unless a ``relax`` callable moves them first.

The finite differences (central, 2- or 4-point stencil, step ``h``):

* dielectric ``eps_ij = delta_ij + dP_i/dE_j / eps0`` from fields ``+-h e_j`` (V/Å) at the
  reference cell, ``P = sum_n q_n r_n / V`` (e/Å²) and ``eps0`` in e/(V·Å)
  (:data:`emlpack.units.EPSILON0_E_PER_V_A`); in Gaussian/atomic units this is
  ``delta_ij + 4 pi dP_i/dE_j``;
* stiffness ``C_ijkl = (1/V) d2E/(d eps_ij d eps_kl)`` (the definition of
  :mod:`emlpack.properties.response`) from strains ``A -> A (I + S_J B_J)`` (Voigt, engineering
  shear), positions strained with the cell: ``dsigma_ij/dS_J + tr(B_J) sigma0_ij - (B_J
  sigma0)_ij``. The last two terms vanish at a stress-free reference; they make the result exact at
  any reference stress ``sigma0`` (the 19th, unperturbed calculation provides it);
* proper piezoelectric tensor ``e~_iJ = (1/V) sum_a A_ai dp_a/dS_J`` (e/Å²) from the same
  strained calculations, where ``p_a = sum_n q_n s_na`` is the dipole in *fractional*
  coordinates ``s = r A^-1`` (the Berry-phase reduced polarization, Vanderbilt 2000). The
  improper ``dP/dS`` differs by ``delta_jk P_i - delta_ik P_j`` terms (see
  :func:`emlpack.properties.response.improper_piezo`);
* strain constants ``d = e : C^-1`` (Voigt: ``d_iJ = e_iK (C^-1)_KJ``, engineering shear).

Polarization quantum: the dipole of a periodic crystal is defined only modulo a lattice vector
times a charge, because any Wannier centre may be reported in any periodic image (and in any
order). Only *changes* are used: each perturbed centre is matched to a centre of the
unperturbed calculation (Hungarian assignment on minimum-image distances in fractional
coordinates), and its fractional displacement is wrapped into [-1/2, 1/2). Cores keep their
order and are wrapped the same way. The change ``dp = sum_n q_n ds_n`` is then continuous in the
perturbation; a displacement larger than ``max_centre_shift`` (Å) is refused as ambiguous.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from emlpack.errors import EmlpackError
from emlpack.geometry import (
    CENTRAL_DIFFERENCES,
    STRAIN_BASIS,
    VOIGT,
    VoigtViews,
    piezo_from_voigt,
    voigt_strain,
)
from emlpack.structure import PAIR_CHARGE, Structure
from emlpack.units import (
    A_PER_V_IN_PM_PER_V,
    E_PER_A2_IN_C_PER_M2,
    EPSILON0_E_PER_V_A,
    EV_PER_A3_IN_GPA,
    FIELD_AU_IN_V_PER_A,
)

Labeler = Callable[..., Structure]

_STENCILS = CENTRAL_DIFFERENCES
_AXES = "xyz"


class CrystalReferenceError(EmlpackError, RuntimeError):
    """Finite-difference reference tensors cannot be computed; the message says why."""


@dataclass(frozen=True)
class FDSettings:
    """Steps of the finite differences.

    Attributes:
        field_step: field step (V/Å); default 0.005 au, half the paper's largest training field.
        strain_step: Voigt strain step (dimensionless; engineering shear).
        points: 2 (central difference) or 4 (4th-order stencil).
        max_centre_shift: largest accepted displacement (Å) of a matched Wannier centre.
    """

    field_step: float = 0.005 * FIELD_AU_IN_V_PER_A
    strain_step: float = 0.01
    points: int = 2
    max_centre_shift: float = 0.5

    def __post_init__(self) -> None:
        if self.points not in _STENCILS:
            raise ValueError(f"FDSettings.points must be 2 or 4, got {self.points}")


@dataclass
class FDTask:
    """One labeling job of the finite differences: ``key``, input structure, stress flag."""

    key: str
    structure: Structure
    stress: bool
    kind: str  # "zero", "field" or "strain"
    index: int = -1  # field axis (0..2) or Voigt component (0..5)
    offset: float = 0.0  # stencil offset (multiples of the step)


def strain(structure: Structure, voigt_vector: np.ndarray) -> Structure:
    """Homogeneously strained copy: positions, pairs and cell times ``I + sum_J S_J B_J``."""
    deform = np.eye(3) + voigt_strain(voigt_vector)
    return structure.copy(positions=structure.positions @ deform,
                          pairs=structure.pairs @ deform, cell=structure.cell @ deform)


def _clean(structure: Structure) -> Structure:
    return structure.copy(energy=None, forces=None, pair_forces=None, stress=None,
                          field=np.zeros(3))


def reference_tasks(reference: Structure, settings: FDSettings = FDSettings(),
                    prefix: str = "ref", relax: Callable[[Structure], Structure] | None = None
                    ) -> list[FDTask]:
    """The calculations of :func:`reference_tensors`: the unperturbed structure (with stress),
    ``points`` fields along x, y, z (no stress) and ``points`` strains per Voigt component
    (with stress): 1 + 3p + 6p tasks (19 for p = 2).

    ``relax`` (optional) moves the cores of each perturbed structure (e.g. a DFT or model
    position relaxation at fixed cell/field) for relaxed-ion tensors; expensive with DFT.
    """
    if not reference.pbc:
        raise CrystalReferenceError(
            f"{reference.source}: reference tensors need a periodic structure")
    base = _clean(reference)
    offsets, _ = _STENCILS[settings.points]
    tasks = [FDTask(f"{prefix}/zero", base, True, "zero")]
    for j in range(3):
        for o in offsets:
            f = np.zeros(3)
            f[j] = o * settings.field_step
            s = base.copy(field=f)
            tasks.append(FDTask(f"{prefix}/field/{_AXES[j]}{o:+g}", relax(s) if relax else s,
                                False, "field", j, float(o)))
    for big in range(6):
        for o in offsets:
            vec = np.zeros(6)
            vec[big] = o * settings.strain_step
            s = strain(base, vec)
            tasks.append(FDTask(f"{prefix}/strain/{big + 1}{o:+g}", relax(s) if relax else s,
                                True, "strain", big, float(o)))
    return tasks


# ---------------------------------------------------------------------- polarization
def _wrap(frac: np.ndarray) -> np.ndarray:
    return frac - np.round(frac)


def fractional_dipole_change(reference: Structure, perturbed: Structure,
                             max_shift: float = 0.5) -> np.ndarray:
    """Change ``dp_a = sum_n q_n ds_na`` (e) of the fractional-coordinate dipole from
    ``reference`` to ``perturbed`` (each in its own cell), free of polarization quanta.

    Pairs are matched by a minimum-image assignment (their order and periodic image may
    change between calculations), cores by index; every fractional displacement is wrapped
    into [-1/2, 1/2). Raises :class:`CrystalReferenceError` when a matched particle moved farther
    than ``max_shift`` (Å): the mapping would then be ambiguous.
    """
    if perturbed.n_pairs != reference.n_pairs or perturbed.n_cores != reference.n_cores:
        raise CrystalReferenceError(
            f"{perturbed.source}: {perturbed.n_cores} cores/{perturbed.n_pairs} pairs, the"
            f" reference has {reference.n_cores}/{reference.n_pairs}")
    inv_ref = np.linalg.inv(reference.cell)
    inv_new = np.linalg.inv(perturbed.cell)
    s_ref = reference.pairs @ inv_ref
    s_new = perturbed.pairs @ inv_new
    diff = _wrap(s_new[:, None, :] - s_ref[None, :, :])  # [new, ref, 3]
    dist = np.linalg.norm(diff @ reference.cell, axis=-1)
    rows, cols = linear_sum_assignment(dist)
    ds_pairs = diff[rows, cols]
    ds_cores = _wrap(perturbed.positions @ inv_new - reference.positions @ inv_ref)
    shifts = np.concatenate([dist[rows, cols],
                             np.linalg.norm(ds_cores @ reference.cell, axis=-1)])
    if shifts.size and shifts.max() > max_shift:
        raise CrystalReferenceError(
            f"{perturbed.source}: a particle moved {shifts.max():.3f} Å from the reference"
            f" (> {max_shift} Å): polarization change ambiguous; use a smaller step")
    return PAIR_CHARGE * ds_pairs.sum(axis=0) + reference.core_charges @ ds_cores


# ---------------------------------------------------------------------- tensors
@dataclass
class ReferenceTensors(VoigtViews):
    """Finite-difference tensors (internal units: eV/Å³, e/Å², dimensionless).

    Attributes:
        volume: reference volume (Å³).
        dielectric: ion-clamped eps_ij (or relaxed, if the tasks relaxed the cores).
        stiffness: C_ijkl (eV/Å³), 3x3x3x3 (Voigt-symmetrised).
        piezo: proper e~_ijk (e/Å²), 3x3x3.
        stress0: stress of the unperturbed structure (eV/Å³).
        relaxed_ions: whether the perturbed structures had relaxed cores.
    """

    volume: float
    dielectric: np.ndarray
    stiffness: np.ndarray
    piezo: np.ndarray
    stress0: np.ndarray
    relaxed_ions: bool = False
    notes: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """Report units: GPa, C/m², pm/V."""
        return {
            "volume_A3": self.volume,
            "relaxed_ions": self.relaxed_ions,
            "dielectric": self.dielectric.tolist(),
            "stiffness_voigt_GPa": (self.stiffness_voigt * EV_PER_A3_IN_GPA).tolist(),
            "piezo_e_voigt_C_per_m2": (self.piezo_voigt * E_PER_A2_IN_C_PER_M2).tolist(),
            "piezo_d_voigt_pm_per_V": (
                self.strain_constants_voigt * A_PER_V_IN_PM_PER_V).tolist(),
            "stress0_GPa": (self.stress0 * EV_PER_A3_IN_GPA).tolist(),
            **self.notes,
        }


def reference_tensors(tasks: list[FDTask], labeled: dict[str, Structure],
                      settings: FDSettings = FDSettings()) -> ReferenceTensors:
    """Tensors from the labeled results (``labeled[task.key]``) of :func:`reference_tasks`."""
    missing = [t.key for t in tasks if t.key not in labeled]
    if missing:
        raise CrystalReferenceError(
            f"{len(missing)} finite-difference calculations missing: {missing}")
    zero_task = next(t for t in tasks if t.kind == "zero")
    ref = labeled[zero_task.key]
    if ref.stress is None:
        raise CrystalReferenceError(f"{ref.source}: the unperturbed calculation has no stress")
    offsets, weights = _STENCILS[settings.points]
    weight_of = dict(zip(offsets.tolist(), weights.tolist(), strict=True))
    cell, volume = ref.cell, ref.volume
    dp_dfield = np.zeros((3, 3))  # [a (fractional), j (field axis)]
    dsigma = np.zeros((3, 3, 6))  # [i, j, J]
    dp_dstrain = np.zeros((3, 6))  # [a, J]
    relaxed = False
    for t in tasks:
        if t.kind == "zero":
            continue
        out = labeled[t.key]
        w = weight_of[t.offset]
        dp = fractional_dipole_change(ref, out, settings.max_centre_shift)
        relaxed |= not np.allclose(t.structure.positions @ np.linalg.inv(t.structure.cell),
                                   ref.positions @ np.linalg.inv(cell), atol=1e-9)
        if t.kind == "field":
            dp_dfield[:, t.index] += w * dp / settings.field_step
        else:
            if out.stress is None:
                raise CrystalReferenceError(f"{t.key}: strained calculation without stress")
            dsigma[:, :, t.index] += w * out.stress / settings.strain_step
            dp_dstrain[:, t.index] += w * dp / settings.strain_step
    # dielectric: dP_i/dE_j = (1/V) sum_a A_ai dp_a/dE_j (fixed cell)
    dielectric = np.eye(3) + (cell.T @ dp_dfield) / (volume * EPSILON0_E_PER_V_A)
    # stiffness with the reference-stress terms (exact at sigma0 != 0), kl symmetric via B_J
    sigma0 = ref.stress
    c = np.zeros((3, 3, 3, 3))
    for big, (k, l) in enumerate(VOIGT):
        b = STRAIN_BASIS[big]
        x = dsigma[:, :, big] + np.trace(b) * sigma0 - b @ sigma0
        c[:, :, k, l] = c[:, :, l, k] = x
    piezo_voigt = (cell.T @ dp_dstrain) / volume
    return ReferenceTensors(
        volume=volume, dielectric=0.5 * (dielectric + dielectric.T),
        stiffness=c, piezo=piezo_from_voigt(piezo_voigt), stress0=sigma0.copy(),
        relaxed_ions=relaxed,
        notes={"field_step_V_per_A": settings.field_step, "strain_step": settings.strain_step,
               "stencil_points": settings.points,
               "dielectric_unsymmetrised": dielectric.tolist()},
    )


def compute_reference_tensors(labeler: Labeler, reference: Structure,
                              settings: FDSettings = FDSettings(),
                              relax: Callable[[Structure], Structure] | None = None,
                              ) -> ReferenceTensors:
    """Label every task of :func:`reference_tasks` in turn and return the tensors (for fast
    labelers; DFT runs label into a store instead, see ``examples/beta_glycine``)."""
    tasks = reference_tasks(reference, settings, relax=relax)
    labeled = {t.key: labeler(t.structure, stress=t.stress) for t in tasks}
    return reference_tensors(tasks, labeled, settings)
