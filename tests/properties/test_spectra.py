"""Spectrum plots checked on the data they draw: the curves (an ensemble's mean and band, the
sticks, the reference), the figure's lines and labels, and the reference files (JSON, CSV,
extxyz with a Hessian)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from emlpack.errors import InputError
from emlpack.properties.spectra import (
    LineSpectrum,
    default_grid,
    ensemble_modes,
    lorentzian,
    spectrum_curves,
    spectrum_figure,
    write_spectrum_plot,
)
from emlpack.properties.spectrum_reference import read_reference_spectrum

#: two models' lines of the same three modes (cm^-1, km/mol)
MEMBERS = [(np.array([1000.0, 1600.0, 3000.0]), np.array([10.0, 40.0, 5.0])),
           (np.array([1010.0, 1580.0, 3050.0]), np.array([20.0, 30.0, 5.0]))]


def test_curves_are_the_members_mean_and_spread():
    ref = LineSpectrum(np.array([1005.0, 1590.0]), np.array([12.0, 33.0]), "DFT")
    c = spectrum_curves(MEMBERS, "ir", fwhm=8.0, reference=ref)
    assert c.grid[0] == 0.0 and c.grid[-1] == 3999.0 and np.all(np.diff(c.grid) == 1.0)
    each = np.array([lorentzian(c.grid, f, h, 8.0) for f, h in MEMBERS])
    np.testing.assert_allclose(c.mean, each.mean(axis=0), rtol=1e-14)
    np.testing.assert_allclose(c.std, each.std(axis=0), rtol=1e-14, atol=1e-300)
    # the band holds both members; the area of the mean curve is the mean total intensity
    assert np.all(c.mean - c.std <= each.min(axis=0) + 1e-12)
    assert np.all(c.mean + c.std >= each.max(axis=0) - 1e-12)
    assert abs(np.trapezoid(c.mean, c.grid) - 55.0) < 0.5  # Lorentzian tails off the grid
    # the sticks: mode-by-mode means (ranks) with their wavenumber spread
    np.testing.assert_allclose(c.sticks.frequencies, [1005.0, 1590.0, 3025.0])
    np.testing.assert_allclose(c.sticks.heights, [15.0, 35.0, 5.0])
    np.testing.assert_allclose(c.sticks_std, [5.0, 10.0, 25.0])
    np.testing.assert_allclose(c.reference_curve, lorentzian(c.grid, ref.frequencies,
                                                             ref.heights, 8.0))
    d = c.as_dict()
    assert d["spectrum_km_per_mol_per_cm-1"] == c.mean.tolist() and d["fwhm_cm-1"] == 8.0
    assert len(d["spectrum_km_per_mol_per_cm-1_std"]) == len(d["spectrum_grid_cm-1"])
    one = spectrum_curves(MEMBERS[:1], "raman")
    assert one.std is None and one.sticks_std is None and one.n_members == 1
    assert "spectrum_A4_per_amu_per_cm-1" in one.as_dict()


def test_default_grid_shows_imaginary_modes_and_stays_bounded():
    assert default_grid(np.array([500.0, 3100.0]))[[0, -1]].tolist() == [0.0, 3999.0]
    assert default_grid(np.array([-150.0, 3100.0]))[0] == -350.0
    assert default_grid(np.array([4500.0]))[-1] == 4699.0
    assert len(default_grid(np.array([-1e9, 1e9]))) == 20000


def test_figure_draws_the_curves_sticks_band_and_reference(tmp_path):
    """The upper panel's lines are the mean and reference curves, the band spans mean ± std,
    the lower panel's sticks are the mean lines (up) and the reference's (down); axes say
    wavenumber in cm^-1 and the heights' units."""
    from matplotlib.collections import LineCollection, PolyCollection

    ref = LineSpectrum(np.array([1005.0, 1590.0]), np.array([12.0, 33.0]), "DFT level")
    c = spectrum_curves(MEMBERS, "ir", reference=ref)
    fig = spectrum_figure(c, title="aziridine")
    top, low = fig.axes
    lines = {line.get_label(): line for line in top.get_lines()}
    assert set(lines) == {"eMLP (mean of 2 models)", "DFT level"}
    np.testing.assert_array_equal(lines["eMLP (mean of 2 models)"].get_ydata(), c.mean)
    np.testing.assert_array_equal(lines["DFT level"].get_ydata(), c.reference_curve)
    band = [p for p in top.collections if isinstance(p, PolyCollection)]
    assert len(band) == 1 and band[0].get_label() == "±1 std over the 2 models"
    ys = band[0].get_paths()[0].vertices[:, 1]
    assert np.isclose(ys.max(), (c.mean + c.std).max())
    sticks = {s.get_label(): s for s in low.collections if isinstance(s, LineCollection)
              and not s.get_label().startswith("_")}
    up = np.array([seg[:, 1] for seg in sticks["eMLP"].get_segments()])
    np.testing.assert_allclose(up[:, 1], c.sticks.heights)
    down = np.array([seg for seg in sticks["DFT level"].get_segments()])
    np.testing.assert_allclose(down[:, 1, 1], -ref.heights)
    np.testing.assert_allclose(down[:, 0, 0], ref.frequencies)
    assert low.get_xlabel() == "wavenumber (cm$^{-1}$)"
    assert "IR intensity" in top.get_ylabel() and "km mol$^{-1}$ per cm$^{-1}$" in top.get_ylabel()
    assert "(km mol$^{-1}$)" in low.get_ylabel()
    assert low.get_xlim() == (0.0, 3999.0) and top.get_title() == "aziridine"
    raman = spectrum_figure(spectrum_curves(MEMBERS[:1], "raman",
                                            reference=LineSpectrum(ref.frequencies, None, "r")))
    assert "Å$^4$ amu$^{-1}$" in raman.axes[0].get_ylabel()
    assert [s.get_label() for s in raman.axes[1].collections][-1] == "r (wavenumbers only)"
    png = tmp_path / "s.png"
    write_spectrum_plot(png, c)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_ensemble_modes_leave_undefined_values_out():
    records = [{"frequencies_cm-1": [100.0, 200.0], "depolarization_ratios": [0.5, None],
                "method": "x"},
               {"frequencies_cm-1": [110.0, 190.0], "depolarization_ratios": [0.7, None]}]
    out = ensemble_modes(records)
    assert out["frequencies_cm-1"] == [105.0, 195.0] and out["frequencies_cm-1_std"] == [5.0, 5.0]
    assert out["depolarization_ratios"][0] == pytest.approx(0.6)
    assert out["depolarization_ratios"][1] is None and out["depolarization_ratios_std"][1] is None
    assert "method" not in out
    records[1]["depolarization_ratios"] = [None, 0.2]
    assert ensemble_modes(records)["depolarization_ratios"] == [0.5, 0.2]


# ------------------------------------------------------------------ reference files
def test_reference_from_json_csv_and_text(tmp_path):
    path = tmp_path / "ir.json"
    path.write_text(json.dumps({"frequencies_cm-1": [900.0, 1200.0], "level": "pbe0/x",
                                "intensities_km_per_mol": [3.0, 4.0]}))
    ref = read_reference_spectrum(path, "ir")
    assert ref.frequencies.tolist() == [900.0, 1200.0] and ref.heights.tolist() == [3.0, 4.0]
    assert ref.label == "reference: pbe0/x (ir.json)"
    raman = read_reference_spectrum(path, "raman", label="DFT")  # an IR file: wavenumbers only
    assert raman.heights is None and raman.label == "DFT"
    csv = tmp_path / "exp.csv"
    csv.write_text("# measured\nwavenumber,intensity\n900.5, 1.5\n1200,2\n\n")
    ref = read_reference_spectrum(csv, "ir")
    assert ref.frequencies.tolist() == [900.5, 1200.0] and ref.heights.tolist() == [1.5, 2.0]
    text = tmp_path / "exp.txt"
    text.write_text("900 1\n1200\t2.5   # strong\n")
    assert read_reference_spectrum(text, "raman").heights.tolist() == [1.0, 2.5]


def test_reference_from_extxyz_with_a_dft_hessian(tmp_path):
    """An extxyz frame with a Hessian and dipole derivatives gives the wavenumbers and
    intensities of emlpack.properties.ir; polarizability derivatives give activities."""
    import ase.io

    from emlpack.io import structure_to_atoms
    from emlpack.properties.hessian import extended_hessian
    from emlpack.properties.ir import ir_from_hessian
    from emlpack.properties.optimize import optimize
    from emlpack.properties.raman import raman_activities
    from tests.nn.helpers import water_molecule
    from tests.properties.toy import spring_model

    s = water_molecule()
    model = spring_model(s)
    s = optimize(model, s, fmax=1e-8).structure
    ir = ir_from_hessian(extended_hessian(model, s)[1].numpy(), s)
    atoms = structure_to_atoms(s)  # pairs as Es rows: dropped by the reader
    rng = np.random.default_rng(0)
    dalpha = rng.normal(size=(9, 3, 3))
    dalpha = dalpha + np.swapaxes(dalpha, 1, 2)
    atoms.info.update(hessian=ir.hessian, dipole_derivatives=ir.dipole_derivatives,
                      polarizability_derivatives=dalpha.reshape(9, 9), level="toy")
    path = tmp_path / "ref.xyz"
    ase.io.write(path, atoms, format="extxyz")
    ref = read_reference_spectrum(path, "ir")
    np.testing.assert_allclose(ref.frequencies, ir.frequencies, rtol=1e-10)
    np.testing.assert_allclose(ref.heights, ir.intensities, rtol=1e-8)
    assert ref.label == "reference: toy (ref.xyz)"
    raman = read_reference_spectrum(path, "raman")
    d_dq = np.einsum("kx,xab->kab", ir.modes.reshape(3, -1), dalpha) / np.linalg.norm(
        ir.modes * np.sqrt(ir.masses)[:, None], axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(raman.heights, raman_activities(d_dq), rtol=1e-7)  # 8 decimals
    del atoms.info["dipole_derivatives"]
    ase.io.write(path, atoms, format="extxyz")
    assert read_reference_spectrum(path, "ir").heights is None


@pytest.mark.parametrize(("name", "text", "message"), [
    ("a.csv", "wavenumber,intensity\n900,1\n1000,x\n", "a.csv, line 3: not two numbers"),
    ("b.csv", "900\n", "b.csv, line 1: the reference spectrum needs two columns"),
    ("c.txt", "only words\n", "c.txt: no rows of two numbers"),
    ("d.txt", "900 nan\n", "d.txt: the reference spectrum has values that are not finite"),
    ("e.txt", "900 -1\n", "e.txt: the reference spectrum has negative intensities"),
    ("f.json", "{", "f.json: cannot read the reference spectrum"),
    ("g.json", '{"intensities_km_per_mol": [1]}', "g.json: no 'frequencies_cm-1'"),
    ("h.json", '{"frequencies_cm-1": [1, 2], "intensities_km_per_mol": [1]}',
     "h.json: 2 frequencies but 1 values"),
    ("i.xyz", '1\nProperties=species:S:1:pos:R:3\nH 0 0 0\n', "i.xyz, frame 0: no Cartesian"),
    ("j.xyz", '1\nProperties=species:S:1:pos:R:3 hessian="1 2"\nH 0 0 0\n',
     "j.xyz, frame 0: the Hessian has 2 entries, 3 x 3 needed"),
])
def test_bad_reference_files_are_one_line_errors(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_reference_spectrum(path, "ir")
    assert str(err.value).startswith(f"{tmp_path}/{message}"), str(err.value)
    assert "\n" not in str(err.value)
    with pytest.raises(InputError, match="no such file"):
        read_reference_spectrum(tmp_path / "missing.csv", "ir")
