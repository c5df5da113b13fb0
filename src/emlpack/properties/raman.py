"""Harmonic Raman spectra of molecules from the eMLP (Placzek approximation, static
polarizability).

1. Normal modes and wavenumbers as for IR (:mod:`emlpack.properties.ir`): the
   Born-Oppenheimer core Hessian from the extended Hessian, mass weighted, rigid-body motions
   projected out; ``c_k`` is mode k's Cartesian displacement (unit norm, Å) and
   ``Q_k = s |M^1/2 c_k|`` the normal coordinate (Å·amu^1/2) of a displacement ``s c_k``.
2. Polarizability derivatives ``alpha'_k = d alpha / d Q_k`` (Å²/amu^1/2, alpha in Å³ =
   e·Å²/V times ``k_e``) by **central differences of the model's analytic polarizability
   along each mode** (:func:`polarizability_derivatives`): the clamped-core polarizability
   ``alpha = H_Fp H_pp^-1 H_pF`` (pairs relaxed, cores clamped: the electronic polarizability
   that Raman scattering sees; :func:`~emlpack.properties.response.polarizability_from_hessian`)
   at the geometries ``x0 + o h c_k`` (4-point stencil, ``o = -2, -1, 1, 2``), the electron
   pairs moved along their linear Born-Oppenheimer response ``p0 + o h dp/dx c_k`` with
   ``dp/dx = -H_pp^-1 H_pc`` from the extended Hessian at ``x0``. That path has the tangent of
   the relaxed pairs' path, so its derivative at ``x0`` is the Born-Oppenheimer derivative
   exactly, without a pair relaxation at any displaced geometry (whose tolerance would be
   noise in the differences); the stencil's error is O(h^4).

   Why not analytic: the extended Hessian holds the energy's second derivatives, and
   ``alpha'`` needs third ones (the change of ``H_pp`` along the mode and the pairs'
   response), which no closed form here provides; the differences of the exact ``alpha`` cost
   4 extended Hessians per mode (aziridine, mini-eqm7: 72 Hessians, ~2 s per model) and are
   tested against finite differences of the fully relaxed ``alpha`` (ASE's ``PlaczekStatic``
   with Cartesian displacements) and a 2-point variant of themselves.
3. Raman invariants (D. A. Long, *The Raman Effect*, 2002), for each mode:
   ``a'^2 = (tr alpha'/3)^2`` and ``gamma'^2 = 1/2 [(a'_xx - a'_yy)^2 + (a'_yy - a'_zz)^2 +
   (a'_zz - a'_xx)^2] + 3 (a'_xy^2 + a'_yz^2 + a'_zx^2)``; the Raman activity
   ``S = 45 a'^2 + 7 gamma'^2`` (Å⁴/amu), the "Raman activity" of quantum chemistry codes and
   ASE's ``Raman.get_absolute_intensities()`` (``delta=0``: same invariants and units; matched
   rather than used, since ASE's ``PlaczekStatic`` differences 6N Cartesian displacements;
   tested); the depolarisation ratios ``rho_p = 3 gamma'^2 / (45 a'^2 + 4 gamma'^2)``
   (plane-polarised incident light, 90° scattering; 0 to 3/4, 3/4 = depolarised) and
   ``rho_n = 6 gamma'^2 / (45 a'^2 + 7 gamma'^2)`` (natural light; 0 to 6/7). A mode without
   activity (below :data:`INACTIVE` of the largest) has no ratio (NaN; ``None`` in JSON).
4. The broadened spectrum: Lorentzians of FWHM ``w`` (default 10 cm^-1, as ``emlp ir``) with
   the activities as areas, Å⁴/amu per cm^-1 (:func:`emlpack.properties.spectra.lorentzian`).
   Activities are not scattered intensities: those add the laser's ``(nu_0 - nu_k)^4`` and the
   Boltzmann factor, which depend on the experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from emlpack.geometry import CENTRAL_DIFFERENCES
from emlpack.nn.potential import EMLP
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.ir import ir_from_hessian
from emlpack.properties.response import polarizability_from_hessian
from emlpack.properties.spectra import default_grid, lorentzian, nan_as_none
from emlpack.structure import Structure
from emlpack.units import COULOMB_EV_A

#: default Cartesian step (Å, norm of the whole displacement) of the mode differences
STEP = 2e-3
#: a mode whose activity is below this fraction of the largest one has no depolarisation ratio
INACTIVE = 1e-10
#: how the derivatives are computed (recorded in the JSON output)
METHOD = ("central differences ({points} points, step {step:g} Å along each mode's Cartesian"
          " displacement) of the model's analytic clamped-core polarizability, the electron"
          " pairs moved along their linear Born-Oppenheimer response")


def raman_invariants(derivatives: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(a'^2, gamma'^2)`` (Å⁴/amu) of polarizability derivatives (n_modes, 3, 3; Å²/amu^1/2):
    the squared mean and the anisotropy of each mode's (symmetrised) tensor, as ASE's
    ``RamanData._invariants``."""
    d = 0.5 * (derivatives + np.swapaxes(derivatives, -1, -2))
    xx, yy, zz = d[..., 0, 0], d[..., 1, 1], d[..., 2, 2]
    mean_sq = ((xx + yy + zz) / 3.0) ** 2
    aniso_sq = (0.5 * ((xx - yy) ** 2 + (yy - zz) ** 2 + (zz - xx) ** 2)
                + 3.0 * (d[..., 0, 1] ** 2 + d[..., 1, 2] ** 2 + d[..., 0, 2] ** 2))
    return mean_sq, aniso_sq


def raman_activities(derivatives: np.ndarray) -> np.ndarray:
    """Raman activities ``45 a'^2 + 7 gamma'^2`` (Å⁴/amu)."""
    mean_sq, aniso_sq = raman_invariants(derivatives)
    return 45.0 * mean_sq + 7.0 * aniso_sq


def depolarization_ratios(derivatives: np.ndarray, natural: bool = False) -> np.ndarray:
    """``3 gamma'^2 / (45 a'^2 + 4 gamma'^2)`` (plane-polarised light) or, ``natural``,
    ``6 gamma'^2 / (45 a'^2 + 7 gamma'^2)``; NaN for a mode without activity (:data:`INACTIVE`)."""
    mean_sq, aniso_sq = raman_invariants(derivatives)
    num, den = (6.0 * aniso_sq, 45.0 * mean_sq + 7.0 * aniso_sq) if natural else (
        3.0 * aniso_sq, 45.0 * mean_sq + 4.0 * aniso_sq)
    active = 45.0 * mean_sq + 7.0 * aniso_sq > INACTIVE * np.max(
        45.0 * mean_sq + 7.0 * aniso_sq, initial=0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(active, num / np.where(active, den, 1.0), np.nan)


def normal_coordinate_per_step(modes: np.ndarray, masses: np.ndarray) -> np.ndarray:
    """``|M^1/2 c_k|`` (amu^1/2): the normal coordinate (Å·amu^1/2) of a 1 Å step along each
    unit Cartesian mode ``c_k`` (n_modes, Nc, 3)."""
    sqrt_m = np.sqrt(np.asarray(masses, float))[None, :, None]
    return np.linalg.norm((modes * sqrt_m).reshape(len(modes), -1), axis=1)


def derivatives_from_differences(alphas: np.ndarray, step: float, modes: np.ndarray,
                                 masses: np.ndarray) -> np.ndarray:
    """``d alpha / d Q_k`` (Å²/amu^1/2) from polarizabilities (n_modes, n_points, 3, 3; Å³) at
    the displacements ``o step c_k`` of a central stencil of :data:`CENTRAL_DIFFERENCES`
    (``n_points`` 2 or 4, offsets ascending), ``step`` in Å."""
    alphas = np.asarray(alphas, float)
    _, weights = CENTRAL_DIFFERENCES[alphas.shape[1]]
    d_ds = np.einsum("kpij,p->kij", alphas, weights) / step  # Å³/Å
    return d_ds / normal_coordinate_per_step(modes, masses)[:, None, None]


@dataclass
class RamanSpectrum:
    """Harmonic normal modes, Raman activities and depolarisation ratios of a molecule.

    Attributes:
        frequencies: wavenumbers (cm^-1), ascending; imaginary modes negative.
        polarizability_derivatives: ``d alpha / d Q_k`` (n_modes, 3, 3), Å²/amu^1/2.
        ir_intensities: IR intensities of the same modes (km/mol).
        modes: Cartesian displacement of each mode (n_modes, n_cores, 3), unit norm.
        masses: amu.
        polarizability: clamped-core polarizability at the geometry (3, 3), e·Å²/V.
        method: how the derivatives were computed.
    """

    frequencies: np.ndarray
    polarizability_derivatives: np.ndarray
    ir_intensities: np.ndarray
    modes: np.ndarray
    masses: np.ndarray
    polarizability: np.ndarray
    method: str = ""

    @property
    def activities(self) -> np.ndarray:
        """Raman activities ``45 a'^2 + 7 gamma'^2`` (Å⁴/amu)."""
        return raman_activities(self.polarizability_derivatives)

    @property
    def depolarization_ratios(self) -> np.ndarray:
        """Depolarisation ratios for plane-polarised incident light (NaN: inactive mode)."""
        return depolarization_ratios(self.polarizability_derivatives)

    @property
    def depolarization_ratios_natural(self) -> np.ndarray:
        """Depolarisation ratios for natural (unpolarised) incident light."""
        return depolarization_ratios(self.polarizability_derivatives, natural=True)

    def broadened(
        self, grid: np.ndarray | None = None, fwhm: float = 10.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """(wavenumbers cm^-1, activity Å⁴/amu per cm^-1) with Lorentzian lines of ``fwhm``."""
        if grid is None:
            grid = default_grid(self.frequencies)
        return grid, lorentzian(grid, self.frequencies, self.activities, fwhm)

    def mode_table(self) -> dict:
        """The per-mode lists for JSON: wavenumbers (cm^-1), activities and invariants
        (Å⁴/amu), depolarisation ratios (``None``: inactive mode), IR intensities (km/mol) and
        the derivatives (Å²/amu^1/2; their sign follows the mode's, which is arbitrary)."""
        mean_sq, aniso_sq = raman_invariants(self.polarizability_derivatives)
        return {
            "frequencies_cm-1": self.frequencies.tolist(),
            "activities_A4_per_amu": self.activities.tolist(),
            "depolarization_ratios": nan_as_none(self.depolarization_ratios),
            "depolarization_ratios_natural": nan_as_none(self.depolarization_ratios_natural),
            "mean_polarizability_derivative_sq_A4_per_amu": mean_sq.tolist(),
            "anisotropy_sq_A4_per_amu": aniso_sq.tolist(),
            "intensities_km_per_mol": self.ir_intensities.tolist(),
            "polarizability_derivatives_A2_per_sqrt_amu":
                self.polarizability_derivatives.tolist(),
        }

    def as_dict(self, fwhm: float = 10.0) -> dict:
        """Plain dict for JSON: :meth:`mode_table`, the clamped-core polarizability
        (e·Å²/V), the broadened spectrum (Å⁴/amu per cm^-1), the masses and the method."""
        grid, curve = self.broadened(fwhm=fwhm)
        return {
            **self.mode_table(),
            "polarizability_e_A2_per_V": self.polarizability.tolist(),
            "fwhm_cm-1": fwhm,
            "spectrum_grid_cm-1": grid.tolist(),
            "spectrum_A4_per_amu_per_cm-1": curve.tolist(),
            "masses_amu": self.masses.tolist(),
            "method": self.method,
        }

    def text(self) -> str:
        """One line per mode: wavenumber, Raman activity, depolarisation ratio, IR intensity."""
        lines = ["mode  wavenumber (cm^-1)  activity (Å^4/amu)  depolarization  IR (km/mol)"]
        for k, (f, s, r, i) in enumerate(zip(self.frequencies, self.activities,
                                             self.depolarization_ratios, self.ir_intensities,
                                             strict=True)):
            ratio = f"{r:14.3f}" if np.isfinite(r) else f"{'-':>14}"
            lines.append(f"{k:4d}  {f:18.2f}  {s:18.3f}  {ratio}  {i:11.3f}")
        return "\n".join(lines)


def polarizability_derivatives(
    model: EMLP, structure: Structure, hessian: np.ndarray, modes: np.ndarray,
    masses: np.ndarray, step: float = STEP, points: int = 4,
) -> np.ndarray:
    """``d alpha / d Q_k`` (n_modes, 3, 3; Å²/amu^1/2) by central differences of the model's
    clamped-core polarizability along each unit Cartesian mode ``modes[k]`` (Nc, 3), the pairs
    moved along their linear response (module docstring); ``hessian``: the molecular extended
    Hessian at ``structure`` (pairs relaxed), ``step`` in Å, ``points`` 2 or 4."""
    if points not in CENTRAL_DIFFERENCES:
        raise ValueError(f"points: one of {sorted(CENTRAL_DIFFERENCES)}, got {points}")
    h = 0.5 * (hessian + hessian.T)
    nc, n = structure.n_cores, structure.n_cores + structure.n_pairs
    cores, pairs = np.arange(3 * nc), np.arange(3 * nc, 3 * n)
    dp_dx = -np.linalg.solve(h[np.ix_(pairs, pairs)], h[np.ix_(pairs, cores)])  # (3Np, 3Nc)
    offsets, _ = CENTRAL_DIFFERENCES[points]
    alphas = np.zeros((len(modes), len(offsets), 3, 3))
    for k, mode in enumerate(modes):
        dx = step * mode.reshape(-1)
        dp = dp_dx @ dx
        for j, o in enumerate(offsets):
            moved = structure.copy(positions=structure.positions + o * dx.reshape(nc, 3),
                                   pairs=structure.pairs + o * dp.reshape(-1, 3))
            _, hd = extended_hessian(model, moved)
            alphas[k, j] = polarizability_from_hessian(hd.numpy(), moved) * COULOMB_EV_A
    return derivatives_from_differences(alphas, step, modes, masses)


def raman_spectrum(model: EMLP, structure: Structure, step: float = STEP,
                   points: int = 4) -> RamanSpectrum:
    """Harmonic Raman spectrum of ``structure`` (pairs relaxed, cores at a minimum: see
    :func:`emlpack.properties.optimize.optimize`); ``step`` (Å) and ``points`` of the
    polarizability differences (:func:`polarizability_derivatives`)."""
    if structure.pbc:
        raise ValueError(f"{structure.source}: Raman spectra are for molecules")
    _, h = extended_hessian(model, structure)
    h = h.numpy()
    ir = ir_from_hessian(h, structure)
    derivs = polarizability_derivatives(model, structure, h, ir.modes, ir.masses, step, points)
    return RamanSpectrum(ir.frequencies, derivs, ir.intensities, ir.modes, ir.masses,
                         polarizability_from_hessian(h, structure),
                         METHOD.format(points=points, step=step))
