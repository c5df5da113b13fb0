"""No broken member in a reported mean: a member whose pairs are not at a minimum (an
imaginary pair mode, a negative clamped polarizability eigenvalue) or whose relaxation failed
is left out of the mean and spread; with fewer than two members left, or the single model's
result broken, the command writes no values and exits 3 with one line.

The broken result is a real one: ethylene with its two C=C pairs turned by 90° about the C=C
axis into the molecular plane, the top of the pairs' rotation barrier (an imaginary pair mode
of the small trained benchmark model)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from emlpack.calculators.ensemble import load_member
from emlpack.cli import main
from emlpack.io import write_structures
from emlpack.pairs.relax import relax_pairs
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.response import pair_minimum_problem
from emlpack.structure import Structure

MODEL = Path(__file__).resolve().parents[2] / "benchmarks" / "fixtures" / "eqm7_small_trained.pt"


def _ethylene() -> Structure:
    c = np.array([[0.667, 0.0, 0.0], [-0.667, 0.0, 0.0]])
    h = np.array([[1.23, 0.92, 0.0], [1.23, -0.92, 0.0], [-1.23, 0.92, 0.0],
                  [-1.23, -0.92, 0.0]])
    ch = [c[k // 2] + 0.6 * (h[k] - c[k // 2]) for k in range(4)]
    pairs = np.vstack([ch, [[0.0, 0.0, 0.45], [0.0, 0.0, -0.45]]])
    return Structure(np.array([6, 6, 1, 1, 1, 1]), np.vstack([c, h]), pairs)


@pytest.fixture(scope="module")
def ethylene():
    """(relaxed ethylene, the same with its C=C pairs turned into the plane: a saddle)."""
    model = load_member(MODEL).model
    s = _ethylene()
    r = relax_pairs(model, s, fmax=1e-7)[0]
    assert not r.failed, r.reason
    relaxed = s.copy(pairs=r.pairs)
    turned = r.pairs.copy()
    turned[4:] = r.pairs[4:] @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T  # 90° about x
    saddle = s.copy(pairs=turned)
    for structure, broken in ((relaxed, False), (saddle, True)):
        problem = pair_minimum_problem(extended_hessian(model, structure)[1].numpy(), structure)
        assert bool(problem) == broken, problem
    return relaxed, saddle


def test_the_pair_minimum_check_reads_an_imaginary_pair_mode(ethylene):
    model = load_member(MODEL).model
    _, saddle = ethylene
    problem = pair_minimum_problem(extended_hessian(model, saddle)[1].numpy(), saddle)
    assert problem.startswith("imaginary pair mode: lowest pair-Hessian eigenvalue -")


def _lines(capsys) -> list[str]:
    return [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def test_a_single_model_not_at_a_minimum_exits_3_and_writes_nothing(ethylene, tmp_path, capsys):
    _, saddle = ethylene
    path = tmp_path / "saddle.xyz"
    write_structures(path, saddle)
    out = tmp_path / "pol.json"
    rc = main(["polarizability", str(MODEL), str(path), "--relax", "none", "-o", str(out),
               "--quiet"])
    err = _lines(capsys)
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith(f"emlp polarizability: failed: {path}, frame 0: no result to"
                             " report: imaginary pair mode")
    assert not out.exists()


@pytest.fixture()
def folders(tmp_path):
    """Ensembles of three and of two copies of the trained model."""
    out = {}
    for n in (2, 3):
        folder = tmp_path / f"ens{n}"
        folder.mkdir()
        for k in range(n):
            (folder / f"model-{k}.pt").write_bytes(MODEL.read_bytes())
        out[n] = folder
    return out


def _second_member_at_the_saddle(monkeypatch, saddle) -> list:
    """The second relaxation (clear the list returned for the next run) returns the saddle, as
    a member whose pairs stopped there would; the others relax as usual."""
    from emlpack.cli import properties

    real, calls = properties.relax, []

    def relax(model, s, level, args, log, warnings):
        out, info = real(model, s, level, args, log, warnings)
        calls.append(level)
        return (saddle, info) if len(calls) == 2 else (out, info)

    monkeypatch.setattr(properties, "relax", relax)
    return calls


@pytest.mark.parametrize("command", ["polarizability", "ir", "optimize"])
def test_a_member_not_at_a_minimum_is_left_out_and_two_left_are_needed(
        ethylene, folders, tmp_path, capsys, monkeypatch, command):
    relaxed, saddle = ethylene
    path = tmp_path / "ethylene.xyz"
    write_structures(path, relaxed)
    suffix = ".xyz" if command == "optimize" else ".json"
    alone = tmp_path / f"alone{suffix}"

    def argv(model, out):
        return [command, str(model), str(path), "--relax", "pairs", "--quiet", "-o", str(out)]

    assert main(argv(MODEL, alone)) == 0
    single = json.loads(alone.with_suffix(".json").read_text())
    calls = _second_member_at_the_saddle(monkeypatch, saddle)

    out = tmp_path / f"three{suffix}"
    assert main(argv(folders[3], out)) == 0
    capsys.readouterr()
    data = json.loads(out.with_suffix(".json").read_text())
    assert [Path(p).name for p in data["ensemble"]["left_out"]] == ["model-1.pt"]
    assert data["ensemble"]["size"] == 2
    assert any(w.startswith("model 2: imaginary pair mode") for w in data["warnings"])
    assert any(w.startswith("model 2 left out of the results (pairs not at a minimum")
               for w in data["warnings"])
    assert data["energy_eV"] == pytest.approx(single["energy_eV"], abs=1e-9)
    if command == "polarizability":
        assert data["polarizability_isotropic_bohr3"] == pytest.approx(
            single["polarizability_isotropic_bohr3"], rel=1e-9)
    if command == "ir":
        np.testing.assert_allclose(data["frequencies_cm-1"], single["frequencies_cm-1"],
                                   rtol=1e-9)

    out = tmp_path / f"two{suffix}"
    calls.clear()
    rc = main(argv(folders[2], out))
    err = _lines(capsys)
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith(f"emlp {command}: failed: {path}, frame 0: no result to report:"
                             " 1 of 2 models sound, at least 2 needed (model 2: imaginary"
                             " pair mode")
    assert not out.exists() and not out.with_suffix(".json").exists()
