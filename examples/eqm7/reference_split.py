"""Split the DFT references still to compute between two processes, as evenly as their cost
allows (long_jobs.sh, phase 3).

The cost of a molecule is its force calls still to do (``2 (3N - 6)`` central differences along
the vibrational directions, less the displacement files already in ``NAME/vib-internal/``) times
``n_bf ** 2.5``, ``n_bf`` its aug-cc-pVTZ basis functions (23 per H, 46 per C, N, O), from its
committed static reference ``NAME.json``; a molecule without one counts as the largest known.
Of all ``2 ** n`` splits (at most 15 test molecules) the most even is taken; each half keeps
the given order (the dft stage computes each half's Hessians cheapest first by the same cost:
``run_study.dft_plan``).

Usage (from the project root)::

    python examples/eqm7/reference_split.py REFS_DIR NAME ...

prints two lines of names, the first never empty (one molecule: one line and an empty one).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

#: aug-cc-pVTZ basis functions (spherical) per element: H, and C, N, O
BASIS_FUNCTIONS = {1: 23, 6: 46, 7: 46, 8: 46}


def reference_cost(refs: Path, name: str) -> float | None:
    """Force calls still to do x basis functions^2.5 of molecule ``name`` (None: no static
    reference yet, so its size is unknown)."""
    static = refs / f"{name}.json"
    if not static.exists():
        return None
    numbers = json.loads(static.read_text())["numbers"]
    n_bf = sum(BASIS_FUNCTIONS[z] for z in numbers)
    done = len(list((refs / name / "vib-internal").glob("*[+-].npz")))
    calls = max(2 * (3 * len(numbers) - 6) - done, 1)
    return calls * n_bf**2.5


def even_split(names: Sequence[str], cost: dict[str, float]) -> tuple[list[str], list[str]]:
    """The two halves of ``names`` whose total costs differ least (every split tried), each in
    the order of ``names``; the larger half (by count) first."""
    total = sum(cost[n] for n in names)

    def imbalance(mask: int) -> float:
        return abs(total - 2 * sum(cost[n] for i, n in enumerate(names) if mask >> i & 1))

    best = min(range(2 ** len(names)), key=imbalance)
    halves = ([n for i, n in enumerate(names) if best >> i & 1],
              [n for i, n in enumerate(names) if not best >> i & 1])
    return tuple(sorted(halves, key=len, reverse=True))


def main(argv: Sequence[str]) -> None:
    refs, names = Path(argv[0]), list(argv[1:])
    cost = {n: reference_cost(refs, n) for n in names}
    largest = max((c for c in cost.values() if c is not None), default=1.0)
    a, b = even_split(names, {n: largest if c is None else c for n, c in cost.items()})
    print(" ".join(a))
    print(" ".join(b))


if __name__ == "__main__":
    main(sys.argv[1:])
