"""Every physical constant and unit conversion of emlpack, in one place.

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
#: harmonic spring constant of the data augmentation, Ha/Å^2 -> eV/Å^2
AUGMENTATION_K_EV_A2 = 2.0 * HARTREE

#: Gaussian width parameter sigma of the reference (Å); gamma = 1/(2 sigma) = 0.39284 / Å
REFERENCE_SIGMA = 1.2727922061357857
REFERENCE_GAMMA = 1.0 / (2.0 * REFERENCE_SIGMA)
#: reciprocal-space cutoff of the reference Ewald sum, |k|/(2 pi) <= gcut, in 1/bohr
REFERENCE_GCUT_PER_BOHR = 0.25

SQRT_PI = math.sqrt(math.pi)
