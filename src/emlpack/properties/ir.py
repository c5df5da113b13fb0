"""Harmonic IR spectra of molecules from the Born-Oppenheimer Hessian of the eMLP.

1. the extended Hessian (positions of cores and pairs, field) gives, with the pairs eliminated
   (Schur complement, :func:`emlpack.properties.response.born_oppenheimer_blocks`), the BO core
   Hessian ``K`` (eV/Å²) and the dipole derivatives ``Z_a,ib = dmu_a/dR_ib`` (e);
2. mass weighting ``K_mw = M^-1/2 K M^-1/2`` (masses: ``ase.data.atomic_masses``, amu) and
   projection on the complement of the rigid translations/rotations (``3N - 6`` modes, ``3N - 5``
   for linear molecules);
3. wavenumbers ``nu = sqrt(lambda) / (2 pi c)`` in cm^-1 (negative for imaginary modes);
4. intensities ``I_k = N_A/(12 eps0 c^2) |dmu/dQ_k|^2`` (km/mol) with
   ``dmu/dQ_k = sum_i Z_i L_ik / sqrt(m_i)``;
5. Lorentzian lines ``I_k (1/pi) (w/2) / ((nu - nu_k)^2 + (w/2)^2)`` of FWHM ``w`` (default
   10 cm^-1, the paper's), in km/mol per cm^-1 (:mod:`emlpack.properties.spectra`, which also
   draws the plot of ``emlp ir --plot``).

IR spectra from MD (the dipole autocorrelation) are in :mod:`emlpack.dynamics.ir_acf`; Raman
spectra in :mod:`emlpack.properties.raman`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ase.data import atomic_masses

from emlpack.geometry import normal_modes
from emlpack.nn.potential import EMLP
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.response import born_oppenheimer_blocks
from emlpack.properties.spectra import default_grid, lorentzian
from emlpack.structure import Structure
from emlpack.units import (
    IR_KM_PER_MOL_PER_E2_AMU,
    WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU,
)


@dataclass
class IRSpectrum:
    """Harmonic normal modes and IR intensities of a molecule.

    Attributes:
        frequencies: wavenumbers (cm^-1), ascending; imaginary modes negative.
        intensities: IR intensities (km/mol).
        modes: Cartesian displacement of each mode (n_modes, n_cores, 3), mass-weighted
            eigenvectors divided by sqrt(mass) and normalised.
        hessian: BO core Hessian (3Nc, 3Nc), eV/Å².
        dipole_derivatives: dmu_a/dR_ib (3, 3Nc), e.
        masses: amu.
    """

    frequencies: np.ndarray
    intensities: np.ndarray
    modes: np.ndarray
    hessian: np.ndarray
    dipole_derivatives: np.ndarray
    masses: np.ndarray

    def broadened(
        self, grid: np.ndarray | None = None, fwhm: float = 10.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """(wavenumbers cm^-1, absorbance km/mol/cm^-1) with Lorentzian lines of ``fwhm``."""
        if grid is None:
            grid = default_grid(self.frequencies)
        return grid, lorentzian(grid, self.frequencies, self.intensities, fwhm)

    def mode_table(self) -> dict:
        """The per-mode lists for JSON: wavenumbers (cm^-1) and intensities (km/mol)."""
        return {"frequencies_cm-1": self.frequencies.tolist(),
                "intensities_km_per_mol": self.intensities.tolist()}

    def as_dict(self, fwhm: float = 10.0) -> dict:
        """Plain dict for JSON: wavenumbers (cm^-1), intensities (km/mol), the spectrum broadened
        with Lorentzians of ``fwhm`` (cm^-1) and the masses (amu)."""
        grid, curve = self.broadened(fwhm=fwhm)
        return {
            **self.mode_table(),
            "fwhm_cm-1": fwhm,
            "spectrum_grid_cm-1": grid.tolist(),
            "spectrum_km_per_mol_per_cm-1": curve.tolist(),
            "masses_amu": self.masses.tolist(),
        }

    def text(self) -> str:
        """One line per mode: wavenumber (cm^-1) and intensity (km/mol)."""
        lines = ["mode  wavenumber (cm^-1)  intensity (km/mol)"]
        lines += [f"{k:4d}  {f:18.2f}  {i:18.3f}"
                  for k, (f, i) in enumerate(zip(self.frequencies, self.intensities, strict=True))]
        return "\n".join(lines)


def vibrational_modes(
    hessian: np.ndarray, positions: np.ndarray, masses: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal modes of a Cartesian core Hessian (3Nc, 3Nc; eV/Å²) at ``positions`` (Å) with
    ``masses`` (amu), rigid-body motions projected out.

    Returns ``(wavenumbers, vecs, cartesian)``: cm^-1 (ascending, imaginary negative), the
    mass-weighted orthonormal eigenvectors ``e_k`` (3Nc, n_modes) and the Cartesian
    displacement of each mode ``c_k = M^-1/2 e_k / |M^-1/2 e_k|`` (n_modes, Nc, 3), unit norm.
    """
    evals, vecs = normal_modes(hessian, positions, masses)
    freqs = np.sign(evals) * np.sqrt(np.abs(evals)) * WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU
    inv_sqrt_m = 1.0 / np.sqrt(np.repeat(masses, 3))
    cart = (vecs * inv_sqrt_m[:, None]).T.reshape(len(evals), -1, 3)
    cart /= np.linalg.norm(cart.reshape(len(evals), -1), axis=1)[:, None, None]
    return freqs, vecs, cart


def ir_intensities(dipole_derivatives: np.ndarray, vecs: np.ndarray,
                   masses: np.ndarray) -> np.ndarray:
    """IR intensities (km/mol) ``N_A/(12 eps0 c^2) |dmu/dQ_k|^2`` from the dipole derivatives
    dmu_a/dR_ib (3, 3Nc; e) and the mass-weighted modes ``vecs`` (3Nc, n_modes)."""
    inv_sqrt_m = 1.0 / np.sqrt(np.repeat(masses, 3))
    dmu_dq = dipole_derivatives @ (vecs * inv_sqrt_m[:, None])  # (3, n_modes), e/sqrt(amu)
    return IR_KM_PER_MOL_PER_E2_AMU * np.sum(dmu_dq**2, axis=0)


def ir_from_hessian(hessian: np.ndarray, structure: Structure) -> IRSpectrum:
    """:class:`IRSpectrum` from the molecular extended Hessian of ``structure``."""
    if structure.pbc:
        raise ValueError(f"{structure.source}: IR spectra are for molecules")
    k_bo, dmu_dr, _ = born_oppenheimer_blocks(hessian, structure)
    masses = atomic_masses[structure.numbers]
    freqs, vecs, cart = vibrational_modes(k_bo, structure.positions, masses)
    return IRSpectrum(freqs, ir_intensities(dmu_dr, vecs, masses), cart, k_bo, dmu_dr, masses)


def ir_spectrum(model: EMLP, structure: Structure) -> IRSpectrum:
    """Harmonic IR spectrum of ``structure`` (pairs relaxed, cores at a minimum: see
    :func:`emlpack.properties.optimize.optimize`)."""
    _, h = extended_hessian(model, structure)
    return ir_from_hessian(h.numpy(), structure)
