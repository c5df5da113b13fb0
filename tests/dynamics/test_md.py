"""Born-Oppenheimer MD (emlpack.dynamics.md): energy conservation ~dt^2, watchdog, resume, NVT,
field.

Water with a small random SchNet plus springs (tests/properties/toy.py) at its minimum: a stable
model whose pairs do not merge, float64, one thread.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

from emlpack.dynamics.analysis import analyze_trajectory, classify, run_analysis
from emlpack.dynamics.md import (
    CHECKPOINT,
    STOPPED,
    TRAJECTORY,
    MDWatchdogError,
    Watchdog,
    run_md,
)
from emlpack.io import read_structures
from emlpack.properties.optimize import optimize
from tests.nn.helpers import FAMILIES, water_molecule
from tests.properties.toy import spring_model

CONTRACT_KEYS = {"step", "time", "potential_energy", "kinetic_energy", "thermostat_energy",
                 "conserved_energy", "temperature", "dipole", "relax_evaluations",
                 "watchdog_events", "velocities"}


@pytest.fixture(scope="module")
def water():
    torch.set_num_threads(1)
    s = water_molecule()
    model = spring_model(s)
    res = optimize(model, s, fmax=1e-9)
    assert res.converged, res.reason
    return model, res.structure


def _frames(path):
    return read_structures(path / TRAJECTORY)


def _econs(frames):
    return np.array([f.info["conserved_energy"] for f in frames])


def test_nve_energy_error_shrinks_as_dt_squared(water, tmp_path):
    model, s = water
    spread = {}
    for dt in (0.4, 0.2):
        out = tmp_path / f"nve{dt}"
        r = run_md(model, s, int(round(8.0 / dt)), out, dt_fs=dt, temperature_K=300,
                   ensemble="nve", seed=1, checkpoint_every=100)
        frames = _frames(out)
        assert len(frames) == r.steps + 1 and r.watchdog_events == 0
        assert CONTRACT_KEYS <= set(frames[-1].info)
        e = _econs(frames)
        # NVE: no thermostat energy; conserved = kinetic + potential
        assert all(f.info["thermostat_energy"] == 0.0 for f in frames)
        np.testing.assert_allclose(
            e, [f.info["kinetic_energy"] + f.info["potential_energy"] for f in frames])
        spread[dt] = np.abs(e - e[0]).max()
        assert np.mean([f.info["temperature"] for f in frames]) > 50
    ratio = spread[0.4] / spread[0.2]
    assert 2.8 < ratio < 5.6, (spread, ratio)  # velocity Verlet: error ~ dt^2 -> 4


def test_watchdog_catches_merged_start_pairs_and_recovers(water, tmp_path, caplog):
    model, s = water
    caplog.set_level(logging.WARNING, logger="emlpack")
    pairs = s.pairs.copy()
    pairs[1] = pairs[0]  # two pairs on top of each other: relaxation keeps them merged
    r = run_md(model, s.copy(pairs=pairs), 4, tmp_path, ensemble="nve", temperature_K=100,
               guess_method="lewis")
    assert r.watchdog_events == 1
    event = r.events[0]
    assert event["step"] == 0 and event["fallback"] == "guess" and event["ok"]
    assert "merged" in event["reason"]
    frames = _frames(tmp_path)
    assert [f.info["watchdog_events"] for f in frames] == [1] * 5
    for f in frames:  # never continues with broken pairs
        d = np.linalg.norm(f.pairs[:, None] - f.pairs[None], axis=-1) + 9 * np.eye(len(f.pairs))
        assert d.min() > 0.2
    assert "watchdog" in caplog.text  # logged, not written: the library installs no handler
    assert not (tmp_path / "md.log").exists()


def test_watchdog_rolls_back_a_broken_step(water, tmp_path, monkeypatch):
    """A step whose extrapolated pairs are merged is rolled back and redone from the rigidly
    moved pairs of the last good step; the trajectory equals an undisturbed one."""
    model, s = water
    ref = run_md(model, s, 8, tmp_path / "ref", ensemble="nve", temperature_K=300, seed=2)
    from emlpack.pairs.solvers import WarmStartSolver

    predict = WarmStartSolver.predict
    calls = {"n": 0}

    def broken(self, cores):
        calls["n"] += 1
        x = predict(self, cores)
        if calls["n"] == 5:
            x[2] = x[3]
        return x

    monkeypatch.setattr(WarmStartSolver, "predict", broken)
    r = run_md(model, s, 8, tmp_path / "hit", ensemble="nve", temperature_K=300, seed=2)
    assert r.watchdog_events == 1 and r.events[0]["fallback"] == "rigid" and r.events[0]["ok"]
    a, b = _frames(tmp_path / "ref"), _frames(tmp_path / "hit")
    # same up to the relaxation tolerance (1e-5 eV/Å pair forces from another start)
    np.testing.assert_allclose(b[-1].positions, a[-1].positions, atol=1e-6)
    assert ref.watchdog_events == 0


def test_watchdog_catches_a_step_whose_energy_jumps(water, tmp_path, monkeypatch):
    """A relaxation that reports convergence at pairs of another energy (as a jump to another
    minimum does) breaks energy conservation: the watchdog sees the potential energy change
    by more than the work of the forces, rolls the step back and redoes it from the rigidly
    moved pairs; the trajectory equals an undisturbed one."""
    from dataclasses import replace

    from emlpack.pairs.solvers import WarmStartSolver

    model, s = water
    ref = run_md(model, s, 8, tmp_path / "ref", ensemble="nve", temperature_K=300, seed=2)
    relax = WarmStartSolver.relax
    calls = {"n": 0}

    def jumped(self, model, structure):
        calls["n"] += 1
        result = relax(self, model, structure)
        return replace(result, energy=result.energy + 0.05) if calls["n"] == 5 else result

    monkeypatch.setattr(WarmStartSolver, "relax", jumped)
    r = run_md(model, s, 8, tmp_path / "hit", ensemble="nve", temperature_K=300, seed=2)
    assert r.watchdog_events == 1 and r.events[0]["fallback"] == "rigid" and r.events[0]["ok"]
    assert "the pairs left their minimum" in r.events[0]["reason"]
    assert "(0.0167 eV per core; threshold 0.001)" in r.events[0]["reason"]
    a, b = _frames(tmp_path / "ref"), _frames(tmp_path / "hit")
    np.testing.assert_allclose(b[-1].positions, a[-1].positions, atol=1e-6)
    np.testing.assert_allclose(_econs(b), _econs(a), atol=1e-6)
    assert ref.watchdog_events == 0
    # a surface that really jumps (every start gives the higher energy from that step on):
    # the step is kept, the event says so, and the run goes on with the jump in its
    # conserved quantity for the analysis to see
    calls["n"] = 0

    def shifted(self, model, structure):
        calls["n"] += 1
        result = relax(self, model, structure)
        return replace(result, energy=result.energy + 0.05) if calls["n"] >= 5 else result

    monkeypatch.setattr(WarmStartSolver, "relax", shifted)
    r = run_md(model, s, 8, tmp_path / "jump", ensemble="nve", temperature_K=300, seed=2)
    assert [e["fallback"] for e in r.events] == ["rigid", "guess", "kept"]
    assert r.events[-1]["ok"] and r.events[-1]["energy_mismatch_eV_per_core"] == pytest.approx(
        0.05 / 3, rel=0.01)
    c = _frames(tmp_path / "jump")
    assert len(c) == 9
    jump = np.diff(_econs(c)) - np.diff(_econs(a))
    assert np.argmax(jump) == r.events[0]["step"] - 1
    assert jump.max() == pytest.approx(0.05, rel=1e-3)
    np.testing.assert_allclose(c[-1].positions, a[-1].positions, atol=1e-6)  # forces unchanged
    # the check itself: trapezoid work against the energy change, per core
    w = Watchdog()
    r0, f = np.zeros((2, 3)), np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    r1 = r0 + [[0.01, 0.0, 0.0], [0.0, 0.0, 0.0]]
    assert w.check_step((0.0, f, r0), (-0.01, f, r1)) == ""         # dU = -F.dR
    assert "0.0015 eV per core" in w.check_step((0.0, f, r0), (-0.007, f, r1))
    assert Watchdog(max_energy_mismatch=0).check_step((0.0, f, r0), (1.0, f, r1)) == ""


def test_watchdog_stops_with_clear_error_after_writing(water, tmp_path):
    model, s = water
    wd = Watchdog()

    def sabotage(step, atoms, calc):
        if step == 3:
            wd.max_core_distance = 1e-3  # from now on every pair is "far from all cores"

    with pytest.raises(MDWatchdogError, match=r"step 4: .*from the nearest core"):
        run_md(model, s, 10, tmp_path, ensemble="nve", temperature_K=300, watchdog=wd,
               callback=sabotage, guess_method="lewis")
    frames = _frames(tmp_path)
    assert [f.info["step"] for f in frames] == [0, 1, 2, 3]
    assert (tmp_path / CHECKPOINT).exists()
    # the folder says the run was stopped: its analysis is "unstable" whatever the four
    # steps' conserved quantity shows (here a smooth NVE start)
    stop = json.loads((tmp_path / STOPPED).read_text())
    assert stop["step"] == 4 and stop["last_good_step"] == 3
    assert "from the nearest core" in stop["reason"]
    a = analyze_trajectory(tmp_path, discard_steps=0)
    assert classify(a.max_jump) == "stable" and a.classification == "unstable"
    assert a.stopped == stop["reason"] and "stopped by the MD watchdog" in a.text()
    lines: list[str] = []  # emlp md-analysis of the folder: its line, JSON and scatter say so
    run_analysis([tmp_path], plot=tmp_path / "a.png", json_path=tmp_path / "a.json",
                 discard_steps=0, log=lines.append)
    (run,) = json.loads((tmp_path / "a.json").read_text())["runs"]
    assert run["classification"] == "unstable" and run["stopped"] == stop["reason"]
    assert "unstable" in lines[0] and "stopped by the MD watchdog" in lines[0]
    # resumed with a sane watchdog, the run finishes and the marker goes
    run_md(model, s, 10, tmp_path, ensemble="nve", temperature_K=300, guess_method="lewis")
    assert not (tmp_path / STOPPED).exists()
    assert analyze_trajectory(tmp_path, discard_steps=0).stopped == ""


#: the SIGKILLed run of test_resume_continues_the_same_trajectory, in its own process
_KILLED_RUN = """
import sys, time
import numpy as np, torch
torch.set_num_threads(1)
from emlpack.dynamics.md import run_md
from emlpack.structure import Structure
from tests.nn.helpers import FAMILIES, water_molecule
from tests.properties.toy import spring_model
start = np.load(sys.argv[1])
s = Structure([8, 1, 1], start["positions"], start["pairs"])
run_md(spring_model(water_molecule()), s, 20, sys.argv[2], dt_fs=0.5, temperature_K=300,
       seed=3, checkpoint_every=5, tdamp_fs=20.0, callback=lambda *a: time.sleep(0.2))
"""


def _kill_md_subprocess(s, out):
    """Start the 20-step run in a subprocess, SIGKILL it once its step-10 checkpoint exists."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    start = out.parent / "start.npz"
    np.savez(start, positions=s.positions, pairs=s.pairs)
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_RUN, str(start), str(out)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 180
    step = -1
    while time.monotonic() < deadline and proc.poll() is None and step < 10:
        try:
            with np.load(out / CHECKPOINT) as data:
                step = json.loads(str(data["meta"]))["step"]
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    with np.load(out / CHECKPOINT) as data:
        step = json.loads(str(data["meta"]))["step"]
    assert 10 <= step < 20, step  # killed mid-run, after its step-10 checkpoint


def test_resume_continues_the_same_trajectory(water, tmp_path):
    """10 + 10 steps, and a run SIGKILLed in a subprocess (plus a partial frame appended),
    resumed: the trajectory equals the uninterrupted one on full-precision quantities
    (velocities, conserved energy, the final checkpoint's positions and momenta, 1e-12), and
    the printed positions and pairs (8 decimals) to their print precision."""
    model, s = water
    kw = dict(dt_fs=0.5, temperature_K=300, seed=3, checkpoint_every=5, tdamp_fs=20.0)
    run_md(model, s, 20, tmp_path / "full", **kw)
    full = _frames(tmp_path / "full")
    # stopped after 10 steps, then the same command with 20 steps
    run_md(model, s, 10, tmp_path / "split", **kw)
    r = run_md(model, s, 20, tmp_path / "split", **kw)
    assert r.resumed_from == 10
    again = run_md(model, s, 20, tmp_path / "split", **kw)  # complete: nothing to do
    assert again.steps == 20 and again.evaluations_per_step == r.evaluations_per_step
    # killed by SIGKILL after its step-10 checkpoint, then a partial frame appended
    _kill_md_subprocess(s, tmp_path / "killed")
    with open(tmp_path / "killed" / TRAJECTORY, "a") as fh:
        fh.write("7\nProperties=species:S:1:pos:R:3 step=11\nO 0.0 0.")
    r = run_md(model, s, 20, tmp_path / "killed", **kw)
    assert 10 <= r.resumed_from < 20
    with np.load(tmp_path / "full" / CHECKPOINT) as data:
        end = {k: data[k] for k in ("positions", "momenta", "eta", "p_eta")}
    for name in ("split", "killed"):
        frames = _frames(tmp_path / name)
        assert [f.info["step"] for f in frames] == list(range(21))
        for a, b in zip(full, frames, strict=True):
            np.testing.assert_allclose(b.positions, a.positions, atol=1e-8, rtol=0)
            np.testing.assert_allclose(b.pairs, a.pairs, atol=1e-8, rtol=0)
            np.testing.assert_allclose(b.info["velocities"], a.info["velocities"], atol=1e-12,
                                       rtol=0)
            assert b.info["conserved_energy"] == pytest.approx(a.info["conserved_energy"],
                                                               abs=1e-12, rel=0)
            assert b.info["potential_energy"] == pytest.approx(a.info["potential_energy"],
                                                               abs=1e-12, rel=0)
        with np.load(tmp_path / name / CHECKPOINT) as data:
            for key, value in end.items():
                np.testing.assert_allclose(data[key], value, atol=1e-12, rtol=0, err_msg=key)
    assert np.abs(end["positions"] - s.positions).max() > 1e-3  # the cores did move
    with pytest.raises(ValueError, match="different run"):
        run_md(model, s, 20, tmp_path / "full", **{**kw, "seed": 4})


def test_nvt_conserved_energy_bounded_and_temperature_near_target(water, tmp_path):
    model, s = water
    run_md(model, s, 100, tmp_path, dt_fs=0.5, temperature_K=300, tdamp_fs=10.0, seed=5,
           checkpoint_every=50, log_every=50)
    frames = _frames(tmp_path)
    e = _econs(frames)
    thermo = np.array([f.info["thermostat_energy"] for f in frames])
    assert np.ptp(thermo) > 1e-3  # the thermostat does work ...
    assert np.abs(e - e[0]).max() < 0.1 * np.ptp(thermo)  # ... and the total is conserved
    temps = np.array([f.info["temperature"] for f in frames[30:]])
    assert 150 < temps.mean() < 450  # 9 degrees of freedom: loose


@pytest.mark.parametrize("relax", ["corrected", "warm"])
def test_md_in_a_field(water, tmp_path, relax):
    model, s = water
    field = np.array([0.15, -0.1, 0.2])  # V/Å
    run_md(model, s, 20, tmp_path, ensemble="nve", temperature_K=300, field=field, seed=6,
           relax=relax)
    # "warm" reports the model's forces at its last evaluation; "corrected" (the default) the
    # Newton-corrected pairs and core forces g_c + C s (carried models, no evaluation), whose
    # residual is estimated, not measured: measured here up to 2.7x fmax (1e-5 eV/Å)
    force_tol, pair_tol = (1e-5, 2e-5) if relax == "warm" else (3e-5, 5e-5)
    frames = _frames(tmp_path)
    e = _econs(frames)
    assert np.abs(e - e[0]).max() < 2e-3
    for f in frames[::5]:
        np.testing.assert_allclose(f.field, field)
        # energy and dipole of the frame are the model's at the stored pairs, field included
        out = model.evaluate(f)
        # (the file holds positions to 1e-8 Å)
        assert f.energy == pytest.approx(out["energy"], abs=1e-7)
        np.testing.assert_allclose(f.forces, out["forces"], atol=force_tol)
        np.testing.assert_allclose(f.info["dipole"], f.dipole(), atol=1e-7)
        # relaxed pairs: the field's net force on the neutral molecule is zero and the pair
        # forces vanish, so the BO forces on the cores sum to zero
        assert np.abs(out["pair_forces"]).max() < pair_tol
        assert np.linalg.norm(f.forces.sum(0)) < 1e-4
    # the field polarises the molecule: the dipole differs from the zero-field relaxation
    assert np.linalg.norm(frames[0].info["dipole"] - s.dipole()) > 1e-3


def test_paper_relaxation_gives_the_same_trajectory(water, tmp_path):
    """The paper's boxed L-BFGS-B (from the previous pairs) and the warm-started relaxation
    follow the same Born-Oppenheimer trajectory to within the relaxation tolerance."""
    model, s = water
    kw = dict(ensemble="nve", temperature_K=300, seed=7)
    warm = run_md(model, s, 10, tmp_path / "warm", **kw)
    paper = run_md(model, s, 10, tmp_path / "paper", relax="paper", **kw)
    a, b = _frames(tmp_path / "warm"), _frames(tmp_path / "paper")
    np.testing.assert_allclose(b[-1].positions, a[-1].positions, atol=1e-5)
    np.testing.assert_allclose(b[-1].pairs, a[-1].pairs, atol=1e-4)
    assert paper.watchdog_events == warm.watchdog_events == 0
    assert paper.evaluations_per_step > warm.evaluations_per_step


def test_newton_correction_of_core_forces_is_second_order(water):
    """The "corrected" mode's final step: pairs p + s with s = -H_pp^-1 g_p, core gradient
    g_c + H_cp s. With exact blocks the error against the relaxed pairs shrinks ~4x when the
    pair error halves (second order), while the uncorrected core-force error shrinks ~2x."""
    from emlpack.pairs.solvers import difference_blocks, energy_gradient_function

    model, s = water
    rng = np.random.default_rng(3)
    direction = rng.normal(size=s.pairs.shape)
    g = model.graph(s, dtype=torch.float64)
    nc = s.n_cores

    def gradient(pairs):
        pos = torch.cat([g.positions.detach()[:nc], torch.as_tensor(pairs)]).requires_grad_()
        (grad,) = torch.autograd.grad(model.energy(g, pos)[0], pos)
        return grad.numpy()

    exact = gradient(s.pairs)[:nc].reshape(-1)  # s is relaxed to 1e-9 eV/Å
    raw, corrected = [], []
    for delta in (2e-3, 1e-3):
        pairs = s.pairs + delta * direction
        evaluate, _ = energy_gradient_function(model, s.copy(pairs=pairs))
        hpp, hcp = difference_blocks(evaluate, pairs, nc, h=1e-6)
        grad = gradient(pairs)
        step = -np.linalg.solve(hpp, grad[nc:].reshape(-1))
        raw.append(np.abs(grad[:nc].reshape(-1) - exact).max())
        corrected.append(np.abs(grad[:nc].reshape(-1) + hcp @ step - exact).max())
    assert 1.7 < raw[0] / raw[1] < 2.3, raw
    assert 3.3 < corrected[0] / corrected[1] < 4.7, corrected
    assert corrected[1] < 0.05 * raw[1]


def test_corrected_mode_forces_within_tolerance_of_tight_relaxation(water, tmp_path):
    """relax="corrected" (stops when model error x residual < fmax, then one Newton correction
    of pairs, energy and core forces without an evaluation): every step's core forces and
    energy agree with tightly relaxed pairs at the same cores, as well as the plain warm
    mode's at the same tolerance, with fewer evaluations."""
    from ase import Atoms

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.pairs.solvers import WarmStartSolver

    model, s = water
    kw = dict(ensemble="nve", temperature_K=300, seed=7, fmax=1e-4)
    runs = {m: run_md(model, s, 12, tmp_path / m, relax=m, **kw) for m in ("warm", "corrected")}
    errors = {}
    for mode in runs:
        df = de = 0.0
        for f in _frames(tmp_path / mode)[1:]:
            calc = EMLPCalculator(model, pairs=f.pairs, check_bonding=False,
                                  pair_solver=WarmStartSolver(fmax=1e-10))
            atoms = Atoms(f.numbers, f.positions)
            atoms.calc = calc
            df = max(df, np.abs(atoms.get_forces() - f.forces).max())
            de = max(de, abs(atoms.get_potential_energy() - f.energy))
        errors[mode] = (df, de)
    assert runs["corrected"].watchdog_events == 0
    assert errors["corrected"][0] < 3e-4, errors  # core-force error ~ the pair tolerance
    assert errors["corrected"][0] <= 2 * errors["warm"][0] + 1e-6, errors
    assert errors["corrected"][1] < 1e-8, errors
    assert runs["corrected"].evaluations_per_step <= runs["warm"].evaluations_per_step


@pytest.mark.parametrize("method", ["corrected", "warm"])
def test_curvature_check_equals_the_exact_smallest_eigenvalue(water, method):
    """The watchdog's curvature check (Davidson on finite-difference Hessian-vector products,
    preconditioned by the carried model) gives the smallest eigenvalue of the exact pair
    Hessian at the result, with far fewer evaluations than the exact blocks (3P + 1)."""
    from emlpack.pairs.relax import pair_hessian
    from emlpack.pairs.solvers import WarmStartSolver

    model, s = water
    solver = WarmStartSolver(method, fmax=1e-6)
    solver.relax(model, s)  # fresh start: exact blocks
    rng = np.random.default_rng(5)
    cores = s.positions + 0.01 * rng.normal(size=s.positions.shape)
    for k in range(3):  # carried (inexact) models by now
        moved = s.copy(positions=cores + 0.003 * k, pairs=s.pairs)
        solver.want_curvature = k == 2
        result = solver.relax(model, moved)
    assert result.converged, result.reason
    exact = np.linalg.eigvalsh(pair_hessian(model, moved.copy(pairs=result.pairs)))[0]
    assert result.min_curvature == pytest.approx(exact, rel=1e-3)
    assert result.n_hessians == 1


def test_watchdog_thresholds_are_the_documented_ones():
    """docs/md.md: pairs closer than 0.2 Å, a pair farther than 2 Å from every core, or a
    non-positive curvature at the check (every 50 steps) fail the step."""
    w = Watchdog()
    assert (w.min_pair_distance, w.max_core_distance, w.curvature_every,
            w.max_energy_mismatch) == (0.2, 2.0, 50, 1e-3)
    cores = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    ok = {"min_curvature": 0.1}

    def pairs(d_pairs, d_core):
        return np.array([[0.5, 0.0, 0.0], [0.5, d_pairs, 0.0], [3.0, 0.0, d_core]])

    assert w.check(cores, pairs(0.21, 1.99), ok) == ""
    assert "(merged; threshold 0.2 Å)" in w.check(cores, pairs(0.19, 1.99), ok)
    assert "from the nearest core (threshold 2 Å)" in w.check(cores, pairs(0.21, 2.01), ok)
    assert "negative pair curvature" in w.check(cores, pairs(0.21, 1.99), {"min_curvature": 0.0})


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_runs_md_with_the_default_solver(family, tmp_path):
    """Water with a short range of every family (+ springs; for a family without SchNet's
    capabilities the MD blocks and relaxations take the generic exact paths): an NVE run in a
    field with the default ("corrected") pair solver conserves energy and its frames are the
    model's energies and forces at the stored pairs."""
    torch.set_num_threads(1)
    model = spring_model(water_molecule(), family=family)
    res = optimize(model, water_molecule(), fmax=1e-9)
    assert res.converged, res.reason
    field = np.array([0.1, 0.0, -0.1])
    r = run_md(model, res.structure, 20, tmp_path, ensemble="nve", temperature_K=300,
               field=field, seed=2)
    assert r.watchdog_events == 0
    frames = _frames(tmp_path)
    e = _econs(frames)
    assert np.abs(e - e[0]).max() < 2e-3
    for f in frames[::10]:
        out = model.evaluate(f)
        assert f.energy == pytest.approx(out["energy"], abs=1e-7)
        np.testing.assert_allclose(f.forces, out["forces"], atol=3e-5)
