"""Properties of a model at a geometry: the extended Hessian and what is built on it.

* :mod:`emlpack.properties.hessian`: the extended Hessian (particles, cell, field);
* :mod:`emlpack.properties.response`: polarizability, Born-Oppenheimer blocks, crystal tensors;
* :mod:`emlpack.properties.ir`: harmonic IR spectra;
* :mod:`emlpack.properties.raman`: harmonic Raman spectra (Placzek);
* :mod:`emlpack.properties.spectra`, :mod:`emlpack.properties.spectrum_reference`: broadening,
  ensemble bands, spectrum plots and reference spectra;
* :mod:`emlpack.properties.optimize`: geometry optimisation (cores, pairs, cell);
* :mod:`emlpack.properties.fd_reference`: crystal tensors by finite differences with any labeler.
"""
