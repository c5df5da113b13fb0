"""Molecular dynamics of the cores with relaxed electron pairs, and what is read from a run.

* :mod:`emlpack.dynamics.md`: the driver (NVE/NVT, watchdog, trajectory, resume);
* :mod:`emlpack.dynamics.analysis`: stability from the conserved quantity;
* :mod:`emlpack.dynamics.ir_acf`: IR spectra from the dipole autocorrelation.
"""
