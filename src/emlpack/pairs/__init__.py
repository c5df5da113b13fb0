"""Electron pairs: starting guesses, relaxation solvers and the one check of the result.

* :mod:`emlpack.pairs.guess`: starting pairs for bare structures (Boys, Lewis; no torch).
* :mod:`emlpack.pairs.relax`: the batched Born-Oppenheimer relaxation
  (:func:`~emlpack.pairs.relax.relax_pairs`: default quasi-Newton, exact Newton, damped BFGS).
* :mod:`emlpack.pairs.solvers`: the solvers as strategies behind one interface
  (:class:`~emlpack.pairs.solvers.PairSolver`): :class:`~emlpack.pairs.solvers.BatchedSolver`
  (``relax_pairs``), MD's :class:`~emlpack.pairs.solvers.WarmStartSolver` (extrapolation +
  carried-Hessian quasi-Newton) and the paper's :class:`~emlpack.pairs.solvers.BoxedLBFGSB`;
  :class:`emlpack.calculators.ase.EMLPCalculator` takes any of them.
* :mod:`emlpack.pairs.checks`: :func:`~emlpack.pairs.checks.check_pairs` (merged or stray
  pairs, convergence, curvature; minimum image).

Moving pairs with their cores (the warm start after the cores moved) is
:func:`emlpack.geometry.carry_pairs`.
"""
