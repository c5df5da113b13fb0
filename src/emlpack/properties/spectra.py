"""Line spectra as people read them: Lorentzian broadening, an ensemble's spread and the plot.

A harmonic spectrum is a set of lines (wavenumbers in cm^-1 and heights: IR intensities in
km/mol, Raman activities in Å^4/amu). :func:`spectrum_curves` builds what is plotted, so that
tests assert on the very arrays the figure shows:

* every model's lines broadened by Lorentzians of FWHM ``w``,
  ``h_k (1/pi) (w/2) / ((nu - nu_k)^2 + (w/2)^2)`` (height per cm^-1; the area of a line is
  its height), on a 1 cm^-1 grid;
* an ensemble's mean curve and the members' population standard deviation (the band);
* the stick spectrum: the lines (an ensemble's mode-by-mode means, modes matched by rank);
* optionally a reference spectrum, broadened the same way, with its own label.

:func:`spectrum_figure` draws them (matplotlib, Agg canvas): the broadened spectrum with the
band and the reference above, the sticks beneath it (the reference's pointing down), wavenumber
increasing from left to right. Reference files are read by
:mod:`emlpack.properties.spectrum_reference`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from emlpack._files import write_figure_atomic

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: highest wavenumber of the default grid (cm^-1): a far-off imaginary or broken mode must not
#: make a grid of a million points
GRID_TOP_LIMIT = 10000.0


@dataclass(frozen=True)
class SpectrumKind:
    """What the heights of a line spectrum are: their JSON key, quantity and unit."""

    name: str
    key: str
    quantity: str
    unit: str

    @property
    def curve_key(self) -> str:
        """The JSON key of the broadened spectrum (height per cm^-1)."""
        return f"spectrum_{self.key.split('_', 1)[1]}_per_cm-1"


KINDS = {
    "ir": SpectrumKind("IR", "intensities_km_per_mol", "IR intensity", "km mol$^{-1}$"),
    "raman": SpectrumKind("Raman", "activities_A4_per_amu", "Raman activity",
                          "Å$^4$ amu$^{-1}$"),
}


@dataclass
class LineSpectrum:
    """Lines of a spectrum: wavenumbers (cm^-1) and heights (``None``: wavenumbers only, e.g.
    a reference Hessian without dipole or polarizability derivatives), with a label."""

    frequencies: np.ndarray
    heights: np.ndarray | None
    label: str


@dataclass
class SpectrumCurves:
    """Everything a spectrum plot shows, as arrays.

    Attributes:
        kind: IR or Raman (:data:`KINDS`).
        fwhm: Lorentzian FWHM (cm^-1).
        grid: wavenumbers (cm^-1), 1 cm^-1 apart.
        mean: broadened spectrum (heights per cm^-1); an ensemble's mean curve.
        std: the members' standard deviation at each grid point (``None`` for one model).
        sticks: the lines (an ensemble's mode-by-mode mean), with ``sticks_std`` their
            wavenumber spread (cm^-1, ``None`` for one model).
        n_members: number of models.
        reference: a reference line spectrum and ``reference_curve`` its broadened spectrum
            (``None`` without heights).
    """

    kind: SpectrumKind
    fwhm: float
    grid: np.ndarray
    mean: np.ndarray
    std: np.ndarray | None
    sticks: LineSpectrum
    sticks_std: np.ndarray | None
    n_members: int
    reference: LineSpectrum | None = None
    reference_curve: np.ndarray | None = None

    def as_dict(self) -> dict:
        """The plotted curves for JSON: grid, broadened spectrum (and its ``_std``), FWHM."""
        out = {"fwhm_cm-1": self.fwhm, "spectrum_grid_cm-1": self.grid.tolist(),
               self.kind.curve_key: self.mean.tolist()}
        if self.std is not None:
            out[f"{self.kind.curve_key}_std"] = self.std.tolist()
        return out


def lorentzian(grid: np.ndarray, centres: np.ndarray, heights: np.ndarray,
               fwhm: float) -> np.ndarray:
    """sum_k heights_k (1/pi) (fwhm/2) / ((grid - centres_k)^2 + (fwhm/2)^2)."""
    g = 0.5 * fwhm
    d = np.asarray(grid)[:, None] - np.asarray(centres)[None, :]
    return (np.asarray(heights)[None, :] * (g / np.pi) / (d * d + g * g)).sum(axis=1)


def default_grid(*frequency_sets: np.ndarray) -> np.ndarray:
    """1 cm^-1 grid from 0 (or below the lowest imaginary mode) to 4000 cm^-1 or 200 above
    the highest line, at most :data:`GRID_TOP_LIMIT`."""
    freqs = np.concatenate([np.asarray(f, float).ravel() for f in frequency_sets] or [[0.0]])
    freqs = freqs[np.isfinite(freqs)]
    top = min(max(4000.0, float(freqs.max(initial=0.0)) + 200.0), GRID_TOP_LIMIT)
    lowest = float(freqs.min(initial=0.0))
    bottom = max(lowest - 200.0, -GRID_TOP_LIMIT) if lowest < 0 else 0.0
    return np.arange(np.floor(bottom), top, 1.0)


def spectrum_curves(
    members: Sequence[tuple[np.ndarray, np.ndarray]],
    kind: str,
    fwhm: float = 10.0,
    reference: LineSpectrum | None = None,
    grid: np.ndarray | None = None,
    label: str = "eMLP",
) -> SpectrumCurves:
    """The curves of a spectrum plot from every model's lines ``(wavenumbers cm^-1,
    heights)``: the mean of the members' broadened spectra, their standard deviation, the
    sticks (by rank when all members have the same number of modes, else every member's
    lines at 1/N of their height) and the ``reference`` broadened the same way."""
    spec = KINDS[kind]
    lines = [(np.asarray(f, float), np.asarray(h, float)) for f, h in members]
    if grid is None:
        grid = default_grid(*(f for f, _ in lines),
                            *([reference.frequencies] if reference is not None else []))
    curves = np.array([lorentzian(grid, f, h, fwhm) for f, h in lines])
    n = len(lines)
    if len({len(f) for f, _ in lines}) == 1:
        freqs = np.array([f for f, _ in lines])
        sticks = LineSpectrum(freqs.mean(axis=0), np.mean([h for _, h in lines], axis=0),
                              label)
        sticks_std = freqs.std(axis=0) if n > 1 else None
    else:
        sticks = LineSpectrum(np.concatenate([f for f, _ in lines]),
                              np.concatenate([h for _, h in lines]) / n, label)
        sticks_std = None
    ref_curve = None
    if reference is not None and reference.heights is not None:
        ref_curve = lorentzian(grid, reference.frequencies, reference.heights, fwhm)
    return SpectrumCurves(spec, float(fwhm), np.asarray(grid, float), curves.mean(axis=0),
                          curves.std(axis=0) if n > 1 else None, sticks, sticks_std, n,
                          reference, ref_curve)


def spectrum_figure(curves: SpectrumCurves, title: str = "") -> Figure:
    """The spectrum plot: the broadened spectrum (an ensemble's mean with a band of ±1
    standard deviation of its members) and the reference above; the stick spectrum beneath,
    the reference's sticks pointing down (or, without heights, short marks at its
    wavenumbers). matplotlib ``Figure`` on an Agg canvas (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    kind = curves.kind
    fig = Figure(figsize=(8, 5.2))
    FigureCanvasAgg(fig)
    top, sticks = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.4],
                                                               "hspace": 0.06})
    model = curves.sticks.label
    if curves.n_members > 1:
        model = f"{model} (mean of {curves.n_members} models)"
        top.fill_between(curves.grid, curves.mean - curves.std, curves.mean + curves.std,
                         color="C0", alpha=0.3, lw=0,
                         label=f"±1 std over the {curves.n_members} models")
    top.plot(curves.grid, curves.mean, color="C0", lw=1.2, label=model)
    ref = curves.reference
    if curves.reference_curve is not None:
        top.plot(curves.grid, curves.reference_curve, color="C3", lw=1.0, ls="--",
                 label=ref.label)
    top.set_ylabel(f"{kind.quantity}\n({kind.unit} per cm$^{{-1}}$)")
    top.set_ylim(bottom=0.0)
    top.legend(loc="upper left", fontsize=9, frameon=False)
    top.set_title(title or f"{kind.name} spectrum, Lorentzian FWHM {curves.fwhm:g} cm$^{{-1}}$")

    f, h = curves.sticks.frequencies, curves.sticks.heights
    sticks.vlines(f, 0.0, h, color="C0", lw=1.4, label=curves.sticks.label)
    if curves.sticks_std is not None:
        sticks.errorbar(f, h, xerr=curves.sticks_std, fmt="none", ecolor="C0", elinewidth=0.8,
                        capsize=1.5)
    scale = float(np.max(h, initial=0.0)) or 1.0
    if ref is not None:
        if ref.heights is not None:
            sticks.vlines(ref.frequencies, 0.0, -ref.heights, color="C3", lw=1.4, label=ref.label)
            scale = max(scale, float(np.max(ref.heights, initial=0.0)))
            sticks.set_ylim(-1.1 * scale, 1.1 * scale)
        else:
            sticks.vlines(ref.frequencies, 0.0, -0.3 * scale, color="C3", lw=1.4,
                          label=f"{ref.label} (wavenumbers only)")
            sticks.set_ylim(-0.6 * scale, 1.1 * scale)
        sticks.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{abs(v):g}"))
        sticks.legend(loc="lower left", fontsize=8, frameon=False, ncol=2)
    else:
        sticks.set_ylim(0.0, 1.1 * scale)
    sticks.axhline(0.0, color="0.4", lw=0.6)
    sticks.set_ylabel(f"{kind.quantity.split()[-1]}\n({kind.unit})")
    sticks.set_xlabel("wavenumber (cm$^{-1}$)")
    sticks.set_xlim(curves.grid[0], curves.grid[-1])
    fig.subplots_adjust(left=0.12, right=0.98, top=0.93, bottom=0.1)
    fig.align_ylabels([top, sticks])
    return fig


def write_spectrum_plot(path: str | Path, curves: SpectrumCurves, title: str = "",
                        dpi: int = 120) -> None:
    """:func:`spectrum_figure` written atomically to ``path`` (format from its suffix)."""
    write_figure_atomic(path, spectrum_figure(curves, title), dpi=dpi)


def ensemble_modes(records: Sequence[dict], exclude: Sequence[str] = ()) -> dict:
    """Mode-by-mode mean and ``KEY_std`` (population standard deviation, as
    :func:`emlpack.calculators.ensemble.member_spread`) over the members' per-mode lists (modes
    matched by rank, ascending wavenumber), skipping ``exclude``; ``None`` entries (an
    undefined value, e.g. the depolarisation ratio of an inactive mode) are left out of their
    mode's mean, which is ``None`` when no member has one."""
    out: dict = {}
    for key in records[0]:
        if key in exclude:
            continue
        try:
            values = np.array([r[key] for r in records], dtype=float)  # None -> NaN
        except (KeyError, TypeError, ValueError):
            continue  # text or ragged: no mean
        defined = np.isfinite(values)
        count = defined.sum(axis=0)
        total = np.where(defined, values, 0.0).sum(axis=0)
        mean = np.divide(total, count, out=np.full(total.shape, np.nan), where=count > 0)
        dev = np.where(defined, values - mean, 0.0)
        std = np.sqrt(np.divide((dev * dev).sum(axis=0), count,
                                out=np.full(total.shape, np.nan), where=count > 0))
        out[key] = nan_as_none(mean)
        out[f"{key}_std"] = nan_as_none(std)
    return out


def nan_as_none(values: np.ndarray) -> object:
    """``values.tolist()`` with NaN as ``None`` (JSON has no NaN)."""
    if values.ndim == 0:
        return None if not np.isfinite(values) else float(values)
    return [nan_as_none(v) for v in values]
