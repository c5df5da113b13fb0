"""Conserved-quantity analysis of MD runs and IR spectra from the dipole autocorrelation.

Physics checks: exact least-squares slope and jump of synthetic series, the paper's thresholds
(per atom), Parseval's sum rule of the ACF spectrum, the quantum correction factors' classical
limit, and a low-temperature BO MD of a water model whose ACF IR peaks and line areas match
the harmonic IR of the same model (equipartition: each mode's line area is its harmonic
intensity when its mean kinetic energy is kT/2).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from ase.data import atomic_masses

from emlpack.dynamics.analysis import (
    STABLE_MAX_JUMP,
    UNSTABLE_MAX_JUMP,
    TrajectoryAnalysisError,
    analyze_conserved,
    analyze_trajectory,
    classify,
)
from emlpack.dynamics.ir_acf import (
    find_peaks,
    ir_from_dipoles,
    ir_from_trajectory,
    quantum_correction,
    write_dipole_ir,
)
from emlpack.io import write_structures
from emlpack.structure import Structure
from emlpack.units import (
    BOLTZMANN_EV_K,
    EV_IN_AMU_A2_PER_FS2,
    IR_KM_PER_MOL_PER_E2_AMU,
    PLANCK_C_EV_CM,
    SPEED_OF_LIGHT_CM_PER_FS,
)

DT = 0.5  # fs


def _series(n_frames=200, slope=2e-6, jump=0.0, jump_at=120, n_atoms=5, e0=-40.0):
    """Times (fs), total conserved energy (eV) = n_atoms (e0 + slope t + jump [step>=jump_at])."""
    steps = np.arange(n_frames)
    t = DT * steps
    per_atom = e0 + slope * t + jump * (steps >= jump_at)
    return t, n_atoms * per_atom, steps


# ------------------------------------------------------------------ conserved quantity
def test_linear_drift_gives_exact_slope_and_jump():
    t, e, steps = _series(slope=3e-6, n_atoms=7)
    r = analyze_conserved(t, e, 7, steps)
    assert r.slope == pytest.approx(3e-6, rel=1e-9)
    # consecutive frames of a straight line differ by slope x dt everywhere
    assert r.max_jump == pytest.approx(3e-6 * DT, rel=1e-6)
    assert r.residual_std < 1e-12
    assert r.classification == "stable"
    assert (r.n_discarded, r.first_step, r.last_step, r.stride_steps) == (10, 10, 199, 1)
    assert r.duration == pytest.approx(DT * 189)
    assert r.drift == pytest.approx(3e-6 * DT * 189)


def test_step_in_conserved_quantity_is_the_max_jump():
    """A drop of 2e-3 eV/atom at step 120 on top of a drift: the jump is the drop plus one
    step of drift, the fitted slope that of least squares (checked against numpy.polyfit)."""
    t, e, steps = _series(slope=1e-6, jump=-2e-3, jump_at=120, n_atoms=4)
    r = analyze_conserved(t, e, 4, steps)
    assert r.max_jump == pytest.approx(2e-3 - 1e-6 * DT, rel=1e-9)
    assert r.max_jump_step == 120
    keep = steps >= 10
    assert r.slope == pytest.approx(np.polyfit(t[keep], e[keep] / 4, 1)[0], rel=1e-9)
    assert r.classification == "transition"


def test_per_atom_normalisation():
    """The same per-atom series for 3 and 30 atoms gives the same analysis; the total jump of
    the 30-atom run is 10x larger."""
    t, e3, steps = _series(slope=-4e-6, jump=3e-3, n_atoms=3)
    _, e30, _ = _series(slope=-4e-6, jump=3e-3, n_atoms=30)
    a, b = analyze_conserved(t, e3, 3, steps), analyze_conserved(t, e30, 30, steps)
    assert a.slope == pytest.approx(b.slope, rel=1e-9)
    assert a.max_jump == pytest.approx(b.max_jump, rel=1e-9)
    assert np.abs(np.diff(e30)).max() == pytest.approx(10 * np.abs(np.diff(e3)).max())
    # a total jump of 0.02 eV is unstable for 1 atom but only 1e-3 eV/atom for 20 atoms
    t, e, steps = _series(slope=0.0, jump=0.02, n_atoms=1)
    assert analyze_conserved(t, e, 1, steps).classification == "unstable"
    assert analyze_conserved(t, e, 20, steps).classification == "transition"


def test_classification_thresholds_are_the_papers():
    """Stable below 5e-4 eV/atom, transition from 5e-4 to 0.01 inclusive, unstable above."""
    assert (STABLE_MAX_JUMP, UNSTABLE_MAX_JUMP) == (5e-4, 1e-2)
    assert classify(np.nextafter(5e-4, 0)) == "stable"
    assert classify(5e-4) == "transition"
    assert classify(1e-2) == "transition"
    assert classify(np.nextafter(1e-2, 1)) == "unstable"
    assert classify(float("inf")) == "unstable"
    for jump, expected in ((0.99 * 5e-4, "stable"), (1.01 * 5e-4, "transition"),
                           (0.99e-2, "transition"), (1.01e-2, "unstable")):
        t, e, steps = _series(slope=0.0, jump=jump, n_atoms=6)
        assert analyze_conserved(t, e, 6, steps).classification == expected, jump


def test_discard_uses_steps_and_stride():
    """Garbage in the first 10 steps (the initialisation) is ignored; with a stride of 4 steps
    the frames at steps 0, 4, 8 are dropped and the jump is between frames 4 steps apart."""
    t, e, steps = _series(slope=1e-6, n_atoms=2)
    e = e.copy()
    e[3] += 5.0  # a huge spike in the discarded part
    assert analyze_conserved(t, e, 2, steps).classification == "stable"
    assert analyze_conserved(t, e, 2, steps, discard_steps=0).classification == "unstable"
    sel = slice(0, None, 4)
    r = analyze_conserved(t[sel], e[sel], 2, steps[sel])
    assert (r.n_discarded, r.first_step, r.stride_steps) == (3, 12, 4)
    assert r.max_jump == pytest.approx(4 * DT * 1e-6, rel=1e-6)
    # a trajectory starting at step 50 (e.g. resumed) discards steps 50..59
    r = analyze_conserved(t[50:], e[50:], 2, steps[50:])
    assert (r.n_discarded, r.first_step) == (10, 60)


def test_bad_series_errors_name_source_and_frame():
    t, e, steps = _series(n_frames=12)
    with pytest.raises(TrajectoryAnalysisError, match=r"run\.xyz: 2 frames left.*at least 3"):
        analyze_conserved(t, e, 5, steps, source="run.xyz")
    t, e, steps = _series()
    e = e.copy()
    e[17] = np.nan
    with pytest.raises(TrajectoryAnalysisError, match=r"run\.xyz, frame 17: conserved energy"):
        analyze_conserved(t, e, 5, steps, source="run.xyz")
    t2 = t.copy()
    t2[30] = t2[29]
    with pytest.raises(TrajectoryAnalysisError, match="frame 30: time"):
        analyze_conserved(t2, np.zeros_like(e), 5, steps, source="run.xyz")
    with pytest.raises(TrajectoryAnalysisError, match="n_atoms"):
        analyze_conserved(t, np.zeros_like(e), 0, steps)


def _water_frames(t, e, steps, dipoles=None, temperature=20.0):
    frames = []
    for k, (ti, ei, si) in enumerate(zip(t, e, steps, strict=True)):
        s = Structure([8, 1, 1], [[0, 0, 0], [0.96, 0, 0], [-0.24, 0.93, 0]],
                      [[0.1, 0.1, 0.3], [0.1, 0.1, -0.3], [0.5, 0.0, 0.0], [-0.1, 0.45, 0]])
        mu = np.zeros(3) if dipoles is None else dipoles[k]
        s.info.update(step=int(si), time=float(ti), potential_energy=float(ei),
                      kinetic_energy=0.0, thermostat_energy=0.0, conserved_energy=float(ei),
                      temperature=temperature, dipole=mu, relax_evaluations=2,
                      watchdog_events=0)
        frames.append(s)
    return frames


def test_trajectory_file_analysis_plot_and_cli(tmp_path):
    """extxyz trajectories (the ``emlp md`` keys) -> analysis, scatter and E_cons(t) PNGs
    (:func:`plot_conserved` via the CLI) and JSON; the file analysis equals the array analysis
    with 3 nuclei."""
    from emlpack.cli import main

    paths = []
    for k, jump in enumerate((1e-4, 3e-3, 0.05)):
        t, e, steps = _series(n_frames=30, slope=(k + 1) * 1e-6, jump=jump, jump_at=20,
                              n_atoms=3)
        path = tmp_path / f"run{k}.xyz"
        write_structures(path, _water_frames(t, e, steps))
        paths.append(path)
        r = analyze_trajectory(path)
        ref = analyze_conserved(t, e, 3, steps)
        assert r.n_atoms == 3
        assert r.slope == pytest.approx(ref.slope, rel=1e-9)
        assert r.max_jump == pytest.approx(ref.max_jump, rel=1e-9)
    # an 'emlp md' output directory stands for its trajectory file
    from emlpack.dynamics.md import TRAJECTORY

    run_dir = tmp_path / "run_dir"
    run_dir.mkdir()
    (run_dir / TRAJECTORY).write_bytes(paths[0].read_bytes())
    assert analyze_trajectory(run_dir).max_jump == analyze_trajectory(paths[0]).max_jump
    out_json, out_png, series = tmp_path / "a.json", tmp_path / "cli.png", tmp_path / "e.png"
    assert main(["md-analysis", *map(str, paths), "--plot", str(out_png), "--groups", "a", "a",
                 "b", "--json", str(out_json), "--series", str(series)]) == 0
    data = json.loads(out_json.read_text())
    assert [d["classification"] for d in data["runs"]] == ["stable", "transition", "unstable"]
    assert data["runs"][1]["max_jump_eV_per_atom"] == pytest.approx(
        analyze_trajectory(paths[1]).max_jump)
    for png in (out_png, series):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_series_legend_gives_the_trajectory_class_or_the_callers(tmp_path, monkeypatch):
    """Panels (b)/(c): each run's class in the legend is its trajectory's, unless the caller
    gives its own (the eqm7 study counts a run the MD watchdog stopped as unstable)."""
    from emlpack.dynamics import analysis

    path = tmp_path / "run.xyz"
    t, e, steps = _series(n_frames=30, slope=1e-6, jump=3e-3, jump_at=20, n_atoms=3)
    write_structures(path, _water_frames(t, e, steps))
    legends = []

    def capture(png_path, figure, dpi=120):
        legends.append([x.get_text() for x in figure.axes[0].get_legend().get_texts()])

    monkeypatch.setattr(analysis, "write_figure_atomic", capture)
    analysis.plot_conserved_series([path], tmp_path / "e.png", labels=["w"])
    analysis.plot_conserved_series([path], tmp_path / "e.png", labels=["w"],
                                   classes=["unstable (stopped)"])
    jump = f"{analyze_trajectory(path).max_jump:.1e}"
    assert legends == [[f"w: transition, max jump {jump}"],
                       [f"w: unstable (stopped), max jump {jump}"]]


def test_scatter_marks_the_runs_the_watchdog_stopped(tmp_path, monkeypatch):
    """Panel (a): a run the MD watchdog stopped is a cross of its group's colour with its own
    legend entry (a study counts it unstable wherever its short trajectory puts it)."""
    from emlpack.dynamics import analysis

    runs = []
    for k, jump in enumerate((1e-4, 2e-4, 3e-3)):
        t, e, steps = _series(n_frames=30, slope=(k + 1) * 1e-6, jump=jump, jump_at=20,
                              n_atoms=3)
        runs.append(analyze_conserved(t, e, 3, steps))
    drawn = []

    def capture(png_path, figure, dpi=120):
        ax = figure.axes[0]
        drawn.append(([x.get_text() for x in ax.get_legend().get_texts()],
                      [len(c.get_offsets()) for c in ax.collections if len(c.get_offsets())]))

    monkeypatch.setattr(analysis, "write_figure_atomic", capture)
    analysis.plot_conserved(runs, tmp_path / "a.png", groups=["aug", "aug", "noaug"],
                            stopped=[False, True, False])
    assert drawn == [(["aug", "aug, stopped by the watchdog", "noaug"], [1, 1, 1])]
    with pytest.raises(ValueError, match="2 stopped flags"):
        analysis.plot_conserved(runs, tmp_path / "a.png", stopped=[True, False])


def test_trajectory_errors_name_file_and_frame(tmp_path):
    t, e, steps = _series(n_frames=30)
    frames = _water_frames(t, e, steps)
    del frames[7].info["conserved_energy"]
    path = tmp_path / "broken.xyz"
    write_structures(path, frames)
    with pytest.raises(TrajectoryAnalysisError, match=r"broken\.xyz, frame 7: no 'conserved"):
        analyze_trajectory(path)
    frames = _water_frames(t, e, steps)
    frames[12].info["conserved_energy"] = float("nan")
    write_structures(path, frames)
    with pytest.raises(TrajectoryAnalysisError, match=r"broken\.xyz, frame 12: conserved"):
        analyze_trajectory(path)


# ------------------------------------------------------------------ IR from the dipole ACF
def _cosines(n, dt, wavenumbers, amplitudes):
    """Dipole (e·Å) = sum of cosines along x, y, z in turn; and the exact <|dmu/dt|^2>."""
    t = np.arange(n) * dt
    mu = np.zeros((n, 3))
    mean_sq = 0.0
    for k, (nu, a) in enumerate(zip(wavenumbers, amplitudes, strict=True)):
        omega = 2 * np.pi * SPEED_OF_LIGHT_CM_PER_FS * nu  # rad/fs
        mu[:, k % 3] += a * np.cos(omega * t + 0.7 * k)
        mean_sq += 0.5 * (a * omega) ** 2
    return mu, mean_sq


@pytest.mark.parametrize("window", ["hann", "gaussian"])
def test_acf_spectrum_of_cosines_peaks_and_sum_rule(window):
    """Peaks at the cosines' wavenumbers within the resolution, no other peak above 1e-3, and
    Parseval: the total area is N_A/(12 eps0 c^2) <|dmu/dt|^2> / kT."""
    nus, amps = [640.0, 1650.0, 3100.0], [0.01, 0.003, 0.002]
    mu, mean_sq = _cosines(600, DT, nus, amps)
    temperature = 300.0
    spec = ir_from_dipoles(mu, DT, temperature, window=window)
    assert spec.resolution == pytest.approx(1 / (SPEED_OF_LIGHT_CM_PER_FS * 600 * DT))
    pos, _ = spec.peaks(1e-3)
    assert len(pos) == 3
    np.testing.assert_allclose(pos, nus, atol=0.05 * spec.resolution)
    kt = BOLTZMANN_EV_K * temperature * EV_IN_AMU_A2_PER_FS2
    assert spec.area() == pytest.approx(IR_KM_PER_MOL_PER_E2_AMU * mean_sq / kt, rel=2e-3)
    # each line's area (within 2 resolutions) is its own share, up to the leakage of the
    # biased ACF's triangle
    for nu, a in zip(nus, amps, strict=True):
        omega = 2 * np.pi * SPEED_OF_LIGHT_CM_PER_FS * nu
        share = IR_KM_PER_MOL_PER_E2_AMU * 0.5 * (a * omega) ** 2 / kt
        area = spec.area(nu - 2 * spec.resolution, nu + 2 * spec.resolution)
        assert area == pytest.approx(share, rel=0.08)


def test_find_peaks_refines_between_grid_points():
    grid = np.arange(0.0, 3000.0, 7.0)
    curve = np.exp(-0.5 * ((grid - 1234.5) / 20) ** 2) + 0.3 * np.exp(
        -0.5 * ((grid - 2100.2) / 25) ** 2)
    pos, height = find_peaks(grid, curve)
    np.testing.assert_allclose(pos, [1234.5, 2100.2], atol=0.5)
    np.testing.assert_allclose(height, [1.0, 0.3], rtol=5e-3)


def test_quantum_corrections_classical_limit_and_order():
    """Every Q -> 1 for h c nu << kT; Schofield >= harmonic >= 1; the "none" spectrum is the
    harmonic one times (1 - e^-x)/x."""
    nu = np.array([1e-3, 0.1, 1.0])
    for kind in ("harmonic", "schofield", "standard", "none"):
        np.testing.assert_allclose(quantum_correction(nu, 3000.0, kind), 1.0, atol=3e-4)
    nu = np.linspace(0.0, 4000.0, 41)
    x = PLANCK_C_EV_CM * nu / (BOLTZMANN_EV_K * 300.0)
    harmonic = quantum_correction(nu, 300.0, "harmonic")
    assert np.all(quantum_correction(nu, 300.0, "schofield") >= harmonic - 1e-12)
    assert np.all(harmonic >= 1.0)
    np.testing.assert_allclose(harmonic[1:], x[1:] / -np.expm1(-x[1:]), rtol=1e-12)
    mu, _ = _cosines(300, DT, [1000.0, 2500.0], [0.01, 0.01])
    a = ir_from_dipoles(mu, DT, 300.0, correction="harmonic")
    b = ir_from_dipoles(mu, DT, 300.0, correction="none")
    x = PLANCK_C_EV_CM * a.wavenumbers[1:] / (BOLTZMANN_EV_K * 300.0)
    np.testing.assert_allclose(b.absorbance[1:], a.absorbance[1:] * -np.expm1(-x) / x,
                               rtol=1e-10, atol=1e-14 * a.absorbance.max())
    with pytest.raises(ValueError, match="quantum correction"):
        quantum_correction(nu, 300.0, "kubo")


def test_dipole_ir_errors_and_files(tmp_path):
    mu, _ = _cosines(100, DT, [1500.0], [0.01])
    bad = mu.copy()
    bad[42, 1] = np.nan
    with pytest.raises(ValueError, match="frame 42: dipole is not finite"):
        ir_from_dipoles(bad, DT, 300.0)
    with pytest.raises(ValueError, match="at least 8"):
        ir_from_dipoles(mu[:5], DT, 300.0)
    t = DT * np.arange(100)
    path = tmp_path / "md.xyz"
    write_structures(path, _water_frames(t, np.zeros(100), np.arange(100), dipoles=mu,
                                         temperature=300.0))
    spec = ir_from_trajectory(path)
    assert spec.temperature == pytest.approx(300.0)
    np.testing.assert_allclose(spec.absorbance, ir_from_dipoles(mu, DT, 300.0).absorbance)
    write_dipole_ir(spec, tmp_path / "ir.json", tmp_path / "ir.png")
    data = json.loads((tmp_path / "ir.json").read_text())
    assert data["peaks_cm-1"][0] == pytest.approx(1500.0, abs=spec.resolution / 10)
    assert (tmp_path / "ir.png").read_bytes()[:4] == b"\x89PNG"


# ------------------------------------------------------------------ MD vs harmonic IR
@pytest.fixture(scope="module")
def water_minimum():
    """Water with the response tests' spring model at its minimum, the harmonic IR and the
    pair-pair block of the extended Hessian (for the chord-Newton pair relaxation)."""
    from emlpack.properties.hessian import extended_hessian
    from emlpack.properties.ir import ir_from_hessian
    from emlpack.properties.optimize import optimize
    from tests.nn.helpers import water_molecule
    from tests.properties.toy import spring_model

    s = water_molecule()
    model = spring_model(s)
    res = optimize(model, s, fmax=1e-9)
    assert res.converged, res.reason
    s = res.structure
    _, h = extended_hessian(model, s)
    h = h.numpy()
    harmonic = ir_from_hessian(h, s)
    pairs = slice(3 * s.n_cores, 3 * (s.n_cores + len(s.pairs)))
    return model, s, harmonic, np.linalg.inv(h[pairs, pairs])


def _mode_velocities(harmonic, masses, temperature, seed):
    """Cartesian velocities (Å/fs) giving every normal mode a kinetic energy kT at t = 0 (so
    its mean kinetic energy is kT/2, the canonical average), random signs."""
    rng = np.random.default_rng(seed)
    kt = BOLTZMANN_EV_K * temperature * EV_IN_AMU_A2_PER_FS2  # amu Å²/fs²
    sqrt_m = np.sqrt(masses)[:, None]
    v = np.zeros((len(masses), 3))
    for mode in harmonic.modes:
        q = mode * sqrt_m
        q /= np.linalg.norm(q)  # mass-weighted unit vector
        v += rng.choice([-1.0, 1.0]) * np.sqrt(2 * kt) * q / sqrt_m
    return v


def _bo_dynamics(model, s, h_pp_inv, velocities, dt, n_steps, fmax=1e-6):
    """Velocity Verlet (dt fs) on the Born-Oppenheimer surface; the pairs are relaxed at every
    step to max pair force < fmax (eV/Å) by Newton iterations with the pair Hessian of the
    minimum (chord method), from a quadratic extrapolation of the last three steps. Returns
    dipoles (e·Å), total energies (eV) and the mean number of evaluations per step."""
    masses = atomic_masses[s.numbers][:, None]

    def relaxed(positions, pairs):
        for evaluation in range(1, 31):
            out = model.evaluate(s.copy(positions=positions, pairs=pairs))
            if np.abs(out["pair_forces"]).max() < fmax:
                return out, pairs, evaluation
            pairs = pairs + (h_pp_inv @ out["pair_forces"].reshape(-1)).reshape(-1, 3)
        raise AssertionError("pair relaxation did not converge")

    positions, velocities = s.positions.copy(), velocities.copy()
    out, pairs, _ = relaxed(positions, s.pairs.copy())
    history = [pairs, pairs]
    acc = out["forces"] / masses * EV_IN_AMU_A2_PER_FS2  # Å/fs²
    dipoles, energies, evaluations = [], [], []
    for _ in range(n_steps):
        dipoles.append(s.copy(positions=positions, pairs=pairs).dipole())
        energies.append(out["energy"] + 0.5 * (masses * velocities**2).sum()
                        / EV_IN_AMU_A2_PER_FS2)
        velocities += 0.5 * dt * acc
        positions = positions + dt * velocities
        guess = 3 * pairs - 3 * history[-1] + history[-2]
        history = [history[-1], pairs]
        out, pairs, n = relaxed(positions, guess)
        evaluations.append(n)
        acc = out["forces"] / masses * EV_IN_AMU_A2_PER_FS2
        velocities += 0.5 * dt * acc
    return np.array(dipoles), np.array(energies), float(np.mean(evaluations))


def _compare_with_harmonic(spec, harmonic, temperature):
    """Every IR-active harmonic line (> 1e-3 of the strongest) has an MD peak within the
    resolution plus 2% (anharmonicity at low T, velocity Verlet's blue shift ~ (w dt)^2/24);
    the total line area equals the sum of harmonic intensities (equipartition) within 10%:
    velocity Verlet's sampled kinetic energy differs by O((w dt)^2) (up to ~8% at w dt = 0.48,
    the highest mode here) and the cross terms between modes average out only as 1/(dw T)."""
    pos, _ = spec.peaks(1e-4)
    active = harmonic.intensities > 1e-3 * harmonic.intensities.max()
    assert active.sum() >= 2
    for nu in harmonic.frequencies[active]:
        nearest = pos[np.argmin(np.abs(pos - nu))]
        assert abs(nearest - nu) < spec.resolution + 0.02 * nu, (nu, pos)
    top = harmonic.frequencies.max() + 4 * spec.resolution
    assert spec.area(0.0, top) == pytest.approx(harmonic.intensities.sum(), rel=0.1)
    return pos


def test_md_dipole_ir_matches_harmonic_ir(water_minimum):
    """BO MD of water at 20 K from the minimum, each normal mode given kT: the ACF IR peaks
    agree with the harmonic frequencies within the resolution, the area with the intensities,
    and the energy is conserved."""
    model, s, harmonic, h_pp_inv = water_minimum
    temperature, dt, n_steps = 20.0, 0.5, 256
    v0 = _mode_velocities(harmonic, atomic_masses[s.numbers], temperature, seed=1)
    dipoles, energies, evaluations = _bo_dynamics(model, s, h_pp_inv, v0, dt, n_steps,
                                                  fmax=1e-5)
    kt = BOLTZMANN_EV_K * temperature
    n_modes = len(harmonic.frequencies)
    # velocity Verlet at w dt < 0.5: energy fluctuations a few % of the mode energies
    assert np.ptp(energies) < 0.1 * n_modes * kt
    spec = ir_from_dipoles(dipoles, dt, temperature)
    assert spec.resolution < 0.5 * np.diff(np.sort(harmonic.frequencies)).min()
    _compare_with_harmonic(spec, harmonic, temperature)
    print(f"{evaluations:.2f} evaluations per step")


def test_ase_velocity_verlet_on_the_calculator_follows_the_bo_trajectory(water_minimum):
    """The default-suite version of the slow test below: 20 steps (10 fs) of ase VelocityVerlet on
    EMLPCalculator give the dipoles and total energies of the test's own BO velocity Verlet
    (Å/fs, amu, eV) from the same start, to 1e-6 e·Å and 1e-6 eV (pairs to 1e-7 eV/Å in both)."""
    from ase import units
    from ase.md.verlet import VelocityVerlet

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.io import structure_to_atoms
    from emlpack.pairs.relax import RelaxOptions

    model, s, harmonic, h_pp_inv = water_minimum
    temperature, dt, n_steps = 20.0, 0.5, 20
    v0 = _mode_velocities(harmonic, atomic_masses[s.numbers], temperature, seed=1)
    dipoles_ref, energies_ref, _ = _bo_dynamics(model, s, h_pp_inv, v0, dt, n_steps, fmax=1e-7)
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(model, relax_options=RelaxOptions(fmax=1e-7))
    atoms.set_velocities(v0 * units.Ang / units.fs)  # Å/fs -> ASE units
    dipoles, energies = [], []
    dyn = VelocityVerlet(atoms, timestep=dt * units.fs)
    dyn.attach(lambda: (dipoles.append(atoms.get_dipole_moment()),
                        energies.append(atoms.get_total_energy())), interval=1)
    dyn.run(n_steps - 1)
    dipoles = np.array(dipoles)
    assert dipoles.shape == dipoles_ref.shape
    assert np.ptp(dipoles_ref, axis=0).max() > 1e-3  # the dipole does oscillate
    np.testing.assert_allclose(dipoles, dipoles_ref, atol=1e-6, rtol=0)
    np.testing.assert_allclose(energies, energies_ref, atol=1e-6, rtol=0)


@pytest.mark.slow
def test_md_with_ase_velocity_verlet_and_calculator_matches_harmonic_ir(water_minimum):
    """The product path: ase VelocityVerlet on EMLPCalculator (pairs relaxed by relax_pairs
    at every step, warm-started), dipoles from the calculator."""
    from ase import units
    from ase.md.verlet import VelocityVerlet

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.io import structure_to_atoms
    from emlpack.pairs.relax import RelaxOptions

    model, s, harmonic, _ = water_minimum
    temperature, dt, n_steps = 20.0, 0.5, 320
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(model, relax_options=RelaxOptions(fmax=1e-7))
    v0 = _mode_velocities(harmonic, atoms.get_masses(), temperature, seed=1)
    atoms.set_velocities(v0 * units.Ang / units.fs)  # Å/fs -> ASE units
    dipoles = []
    dyn = VelocityVerlet(atoms, timestep=dt * units.fs)
    dyn.attach(lambda: dipoles.append(atoms.get_dipole_moment()), interval=1)
    dyn.run(n_steps - 1)
    spec = ir_from_dipoles(np.array(dipoles), dt, temperature)
    _compare_with_harmonic(spec, harmonic, temperature)
