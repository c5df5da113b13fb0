"""examples/eqm7/reference_split.py: the DFT references of phase 3 split by cost."""

from __future__ import annotations

import itertools
import json

from tests.examples.eqm7_data import example_module


def test_even_split_is_the_most_even_of_all_splits():
    split = example_module("reference_split")
    cost = {"a": 96.0, "b": 90.0, "c": 84.0, "d": 84.0, "e": 84.0, "f": 72.0, "g": 72.0}
    names = list(cost)
    first, second = split.even_split(names, cost)
    assert sorted(first + second) == names
    assert first == [n for n in names if n in first]  # each half in the given order
    gap = abs(sum(cost[n] for n in first) - sum(cost[n] for n in second))
    best = min(abs(sum(cost.values()) - 2 * sum(cost[n] for n in half))
               for k in range(len(names) + 1) for half in itertools.combinations(names, k))
    assert gap == best == 42.0  # 3 molecules 96 + 90 + 84 = 270 : 312 the other 4
    alternate = abs(sum(cost[n] for n in names[::2]) - sum(cost[n] for n in names[1::2]))
    assert gap < alternate
    assert split.even_split(["only"], {"only": 1.0}) == (["only"], [])


def test_cost_counts_the_calls_left_and_the_basis(tmp_path, capsys):
    split = example_module("reference_split")
    water = {"numbers": [8, 1, 1]}  # 3 vibrational directions, 6 calls, 92 basis functions
    (tmp_path / "w.json").write_text(json.dumps(water))
    (tmp_path / "w" / "vib-internal").mkdir(parents=True)
    assert split.reference_cost(tmp_path, "w") == 6 * 92**2.5
    for f in ("000-.npz", "000+.npz", "directions.npz"):
        (tmp_path / "w" / "vib-internal" / f).touch()
    assert split.reference_cost(tmp_path, "w") == 4 * 92**2.5
    assert split.reference_cost(tmp_path, "unknown") is None
    (tmp_path / "m.json").write_text(json.dumps({"numbers": [6, 1, 1, 1, 1]}))  # methane
    split.main([str(tmp_path), "w", "unknown", "m"])
    lines = capsys.readouterr().out.splitlines()
    # the unknown molecule counts as the largest (methane: 18 calls x 138^2.5) and goes alone
    assert lines == ["w m", "unknown"]
