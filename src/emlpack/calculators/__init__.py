"""What users load and call: trained models and the calculators built on them.

* :mod:`emlpack.calculators.ensemble`: one checkpoint or an ensemble on the DFT energy scale;
* :mod:`emlpack.calculators.ase`: :class:`~emlpack.calculators.ase.EMLPCalculator`, the ASE
  calculator (relaxed pairs, uncertainty, warnings);
* :mod:`emlpack.calculators.labeler`: a model as a labeler (the protocol of the DFT labelers).
"""
