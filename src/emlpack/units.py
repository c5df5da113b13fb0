"""Every physical constant and unit conversion of emlpack, in one place (plus the few fixed
constants of the paper's method, in their own section; no tunable hyperparameters).

emlpack works in eV, Å, e, eV/Å, V/Å (field) and eV/Å^3 (stress, ASE sign) at every public
interface. The constants are those of molmod (CODATA-1998 based), the unit system of the
authors' TensorFlow reference and of the paper's data; they differ from CODATA-2018 in the
seventh digit, which matters for reproducing the reference to 1e-8.
"""

from __future__ import annotations

import math

#: bohr per Å (molmod ``angstrom``)
ANGSTROM_IN_BOHR = 1.889726133921252
#: Å per bohr
BOHR = 1.0 / ANGSTROM_IN_BOHR
#: Hartree per eV (molmod ``electronvolt``)
EV_IN_HARTREE = 0.036749325919680595
#: eV per Hartree
HARTREE = 1.0 / EV_IN_HARTREE
#: Coulomb constant e^2/(4 pi eps0) in eV·Å: 1/(angstrom*electronvolt) = 14.3996...
COULOMB_EV_A = 1.0 / (ANGSTROM_IN_BOHR * EV_IN_HARTREE)
#: one atomic unit of electric field (Hartree/(e·bohr)) in V/Å: 51.422...
FIELD_AU_IN_V_PER_A = ANGSTROM_IN_BOHR / EV_IN_HARTREE
#: molmod ``pascal``: atomic units of pressure per Pa
PASCAL_IN_AU = 3.3989315827578425e-14
#: eV/Å^3 -> GPa: 160.2176...
EV_PER_A3_IN_GPA = EV_IN_HARTREE / ANGSTROM_IN_BOHR**3 / (1e9 * PASCAL_IN_AU)
#: a.u. of time per fs (molmod ``femtosecond``)
FEMTOSECOND_IN_AU = 41.341373336646825
#: Boltzmann constant in eV/K (molmod ``boltzmann`` = 3.1668154051341965e-06 Ha/K)
BOLTZMANN_EV_K = 3.1668154051341965e-06 * HARTREE
#: e·Å -> Debye (1 D = 0.20819434 e·Å)
E_A_IN_DEBYE = 1.0 / 0.20819434

SQRT_PI = math.sqrt(math.pi)

# ------------------------------------------------------------- method constants of the paper
# Not tunable hyperparameters but fixed constants of the published method, given in the
# paper's units (Ha, bohr) and converted here; tests/test_units.py checks them against
# docs/conventions.md. The tunable defaults that start from them live with their configuration:
# ``nn.potential.ModelConfig.gcut`` / ``gamma`` and ``data.augment.AugmentationConfig.k``.

#: harmonic spring constant of the data augmentation (2 Ha/Å^2 in the paper), in eV/Å^2
AUGMENTATION_K_EV_A2 = 2.0 * HARTREE
#: Gaussian width parameter sigma of the reference (Å); gamma = 1/(2 sigma) = 0.39284 / Å
REFERENCE_SIGMA = 1.2727922061357857
REFERENCE_GAMMA = 1.0 / (2.0 * REFERENCE_SIGMA)
#: reciprocal-space cutoff of the reference Ewald sum, |k|/(2 pi) <= gcut, in 1/bohr
REFERENCE_GCUT_PER_BOHR = 0.25

# ---------------------------------------------------------------- response and spectroscopy
# SI constants (CODATA 2018, exact where defined) for report units; the model's own constants
# above stay molmod's.
#: elementary charge (C)
ELEMENTARY_CHARGE_C = 1.602176634e-19
#: atomic mass unit (kg)
AMU_KG = 1.66053906660e-27
#: speed of light (m/s)
SPEED_OF_LIGHT_M_S = 299792458.0
#: Avogadro constant (1/mol)
AVOGADRO = 6.02214076e23
#: vacuum permittivity (F/m)
EPSILON0_SI = 8.8541878128e-12
#: vacuum permittivity in e/(V·Å), consistent with the model's Coulomb constant:
#: eps0 = 1/(4 pi k_e), k_e = COULOMB_EV_A (eV·Å/e² = V·Å/e)
EPSILON0_E_PER_V_A = 1.0 / (4.0 * math.pi * COULOMB_EV_A)
#: polarization/piezo: e/Å² -> C/m² (16.02...)
E_PER_A2_IN_C_PER_M2 = ELEMENTARY_CHARGE_C / 1e-20
#: piezoelectric strain constant: Å/V -> pm/V
A_PER_V_IN_PM_PER_V = 100.0
#: polarizability volume: Å³ -> bohr³ (alpha[Å³] = alpha[e·Å²/V] * COULOMB_EV_A)
POLARIZABILITY_A3_IN_BOHR3 = ANGSTROM_IN_BOHR**3
#: harmonic wavenumber: sqrt(eV/(Å² amu)) -> cm^-1 (521.47...)
WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU = (
    math.sqrt(ELEMENTARY_CHARGE_C / (1e-20 * AMU_KG)) / (2.0 * math.pi * SPEED_OF_LIGHT_M_S * 100.0)
)
#: IR intensity N_A/(12 eps0 c²) |dmu/dQ|²: (e/sqrt(amu))² -> km/mol (974.86...)
IR_KM_PER_MOL_PER_E2_AMU = (
    AVOGADRO / (12.0 * EPSILON0_SI * SPEED_OF_LIGHT_M_S**2)
    * ELEMENTARY_CHARGE_C**2 / AMU_KG / 1000.0
)
#: Planck constant (J·s, exact)
PLANCK_J_S = 6.62607015e-34
#: speed of light in cm/fs (wavenumber cm^-1 = frequency 1/fs / this)
SPEED_OF_LIGHT_CM_PER_FS = SPEED_OF_LIGHT_M_S * 100.0 * 1e-15
#: h c in eV·cm (photon energy of 1 cm^-1: 1.2398e-4 eV)
PLANCK_C_EV_CM = PLANCK_J_S * SPEED_OF_LIGHT_M_S * 100.0 / ELEMENTARY_CHARGE_C
#: 1 eV in amu·Å²/fs² (kinetic energies from velocities in Å/fs: 0.0096485)
EV_IN_AMU_A2_PER_FS2 = ELEMENTARY_CHARGE_C / (AMU_KG * 1e-20 / 1e-30)
