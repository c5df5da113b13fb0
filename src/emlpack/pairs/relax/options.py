"""Settings (:class:`RelaxOptions`) and outcome (:class:`RelaxResult`) of the pair
relaxation (:func:`emlpack.pairs.relax.relax_pairs`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from emlpack.pairs.checks import (
    COLLAPSE_DISTANCE,
    FLAT_CURVATURE,
    MAX_CORE_DISTANCE,
    MIN_PAIR_DISTANCE,
)

if TYPE_CHECKING:
    #: per structure None or the (lower, upper) box of its pairs, (P, 3) each (Å)
    Bounds = Sequence[tuple[np.ndarray, np.ndarray] | None] | None


@dataclass
class RelaxResult:
    """Outcome of relaxing the electron pairs of one structure (Å, eV, eV/Å, eV/Å^2)."""

    pairs: np.ndarray
    energy: float
    converged: bool
    iterations: int
    n_evaluations: int
    n_hessians: int
    max_force: float
    min_curvature: float
    reason: str = ""
    pair_forces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: forces on the cores (eV/Å) at the result when the solver computed them (MD's warm-start
    #: solvers), so that the caller needs no further evaluation; None otherwise
    forces: np.ndarray | None = None
    #: how the start pairs were made ("given"; MD's solvers: "warm", "paper", "rigid", "guess")
    start: str = "given"

    @property
    def failed(self) -> bool:
        """True when ``reason`` names a failure."""
        return bool(self.reason)


@dataclass
class RelaxOptions:
    """Settings of :func:`relax_pairs` (lengths Å, forces eV/Å)."""

    fmax: float = 1e-4
    max_iterations: int = 100
    max_step: float = 0.3
    #: exact Hessian refresh every this many accepted steps (0: never)
    hessian_every: int = 5
    #: "coulomb" (default): quasi-Newton whose model is the exact analytic electrostatic pair
    #: Hessian at every iterate plus an SR1 model of the short-range remainder (one
    #: energy+gradient per iteration, no autograd Hessians); "exact": start from the exact
    #: pair Hessian and refresh it when the model goes stale
    #: (few iterations; a Hessian costs about 2.5 x 3P gradient evaluations); "bfgs": start
    #: from an identity model (``initial_curvature``) and use damped BFGS
    #: updates only, halving rejected steps (more iterations, each one gradient evaluation)
    initial_hessian: str = "coulomb"
    #: ``"bfgs"``: curvature (eV/Å^2) of the identity start model, as SciPy's BFGS (1: H0 = I);
    #: <= 0: Shanno-Phua scaling from the first step instead (measured: about 2x more
    #: iterations on the eqm7 relaxation benchmark, the scaled model is too stiff)
    initial_curvature: float = 1.0
    #: "coulomb": start model of the short-range remainder: "lumped" (three forward
    #: differences of the gradient, counted as evaluations: per pair the row sum of its
    #: short-range 3x3 couplings; on a trained model the short range is ~93 % of the pair
    #: Hessian, measured) or "zero"
    short_range_start: str = "lumped"
    #: "coulomb": structures not converged after this many quasi-Newton iterations finish
    #: with the exact-Hessian Newton method (0: never)
    newton_after: int = 50
    #: "coulomb": structures whose largest pair force is above this (or ``fmax`` when larger;
    #: eV/Å) are evaluated in float32 (start, lumped start and iterations; Armijo test with a
    #: 1e-6 |E| allowance for the float32 energy, and steps whose predicted decrease is below
    #: that allowance accepted on a lower pair-gradient norm), then finished in float64 (first
    #: step: accepted on a lower gradient norm); the minima are float64 minima (0: float64
    #: throughout; the float32 gradient is within ~1.3e-5 eV/Å of float64, measured)
    float32_above: float = 3e-4
    #: ... only in batches of at least this many pairs (measured on the trained model: float32
    #: energy+gradient 2.5x cheaper for 432 pairs, equal for 32, 1.5x dearer for 4); when the
    #: structures still in float32 hold fewer pairs than this, they all go on in float64
    float32_min_pairs: int = 128
    #: "coulomb": the smallest curvature at the result (``check_curvature``) by Davidson
    #: iterations preconditioned by the quasi-Newton model, at most this many exact
    #: Hessian-vector products (0: the full exact pair Hessian instead)
    curvature_steps: int = 20
    #: energies and gradients with the SchNet filters of the pair edges from a cubic Hermite
    #: table of this spacing (Å; :class:`emlpack.nn.short_range.schnet.FilterTable`; families
    #: with the capability :class:`~emlpack.nn.short_range.protocol.TabulatesEdges`) instead
    #: of the filter network (Hessian-vector products and exact Hessians keep the network).
    #: Measured on the trained benchmark model, 64 structures: energies within 3e-11 eV, pair
    #: gradients within 2.5e-8 eV/Å, an energy+gradient 1.5x cheaper in float64 and float32,
    #: the relaxation benchmark 1.27x; batches of at least ``TABLE_MIN_EDGES`` pair edges;
    #: 0: off)
    filter_table: float = 1e-3
    #: failure thresholds of :func:`emlpack.pairs.checks.check_pairs` (Å)
    min_pair_distance: float = MIN_PAIR_DISTANCE
    max_core_distance: float = MAX_CORE_DISTANCE
    check_curvature: bool = True
    #: (method "coulomb", molecules) steps in cylindrical coordinates about the axis through
    #: each pair's two nearest cores (:class:`BondRotations`) instead of straight ones
    #: (measured on the 64-structure benchmark: acetylene's slowest 58 -> 40 evaluations)
    bond_rotations: bool = True
    #: (method "coulomb", with ``bond_rotations``) a structure with a group of at least
    #: ``rotation_probe_pairs`` pairs about one bond (a double or triple bond's pairs) takes
    #: one step that turns each group together by this arc (Å, downhill) instead of a Newton
    #: step, when its largest pair force first falls below ``rotation_probe_below`` (eV/Å; the
    #: mode is soft near the minimum only); its secant puts that rotation's curvature into
    #: the model (measured on the relaxation benchmark: shipped member 0 CPU -16 %, slowest
    #: 53 -> 36 evaluations; docs/relaxation.md; 0: off). ``rotation_floor``: the Newton
    #: step's curvature floor (eV/Å^2) for a probed structure (a lower one, 3e-3, was faster
    #: on the benchmark but failed more often on linear molecules with two triple bonds,
    #: whose rotations are exactly flat)
    rotation_probe: float = 0.05
    rotation_probe_pairs: int = 2
    rotation_probe_below: float = 3e-2
    rotation_floor: float = 1e-2
    #: (method "coulomb") model curvatures below minus this (eV/Å^2) are replaced by their
    #: magnitude in the step instead of shifting the whole model up to the floor (an SR1
    #: update from a near-orthogonal secant can leave a large spurious negative curvature;
    #: the shifted step then runs along it to the trust radius and is rejected; measured on
    #: the 64-structure benchmark: evaluations sum 922 -> 884, max 26 -> 23; 0: off)
    mirror_curvature: float = 1.0
    #: a structure whose accepted pairs include two closer than this (Å) has collapsed (two
    #: pairs on one point, where the direction of their distance is undefined) and stops; its
    #: result fails as merged (0: never stop; measurements: docs/relaxation.md)
    collapse_distance: float = COLLAPSE_DISTANCE
    #: smallest pair curvatures above minus this (eV/Å^2) are a flat valley, not a saddle
    #: (:func:`~emlpack.pairs.checks.check_pairs`): the azimuth of a triple bond's pairs is
    #: flat (cylindrical symmetry), and a relaxation stopped at ``fmax`` = 1e-4 eV/Å sits
    #: anywhere along it (measured: docs/relaxation.md)
    flat_curvature: float = FLAT_CURVATURE
    #: a relaxation that ends at a saddle (converged, its only failure a pair curvature at or
    #: below ``-flat_curvature``; e.g. a symmetric start whose gradient keeps the symmetry) is
    #: displaced along the softest mode of the exact pair Hessian, both ways, and relaxed
    #: again, at most this many times; the lower minimum is kept (0: off; needs
    #: ``check_curvature``)
    saddle_escapes: int = 2
    #: ... by this much (Å, the largest pair displacement)
    saddle_step: float = 0.1
