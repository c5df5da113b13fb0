"""IR spectra from MD by the dipole autocorrelation.

From the dipole time series ``mu(t_i)``, ``t_i = i dt``, ``n`` frames:

1. the dipole derivative by differences, ``v_i = (mu_{i+1} - mu_i) / dt`` (e·Å/fs, ``n - 1``
   values, mean removed), and its autocorrelation ``C_k = 1/(n-1) sum_i v_i . v_{i+k}``
   (the biased estimate, by FFT with zero padding to >= 2n: no circular wrap) in (e·Å/fs)²;
2. a lag window ``w_k`` (Hann ``cos^2(pi k / 2L)``, Gaussian ``exp(-(k/L)^2 9/2)`` or none,
   ``L = n - 1``) and zero padding (``padding`` x 2L points), then the cosine transform
   ``S(f) = dt [C_0 + 2 sum_k w_k C_k cos(2 pi f k dt)]``, divided by the transfer function of
   the difference, ``sinc^2(f dt)`` (``sin(pi f dt)/(pi f dt)``), to give the spectrum of the
   derivative; before that division the integral of ``S`` over all frequencies is exactly
   ``C_0 = <|v|^2>`` (Parseval; ``w_0 = 1``); wavenumbers ``nu = f / c``; nominal resolution
   ``1/(c n dt)``;
3. absorbance in km/mol per cm^-1, normalised so that for a classical harmonic molecule in
   equilibrium at ``T`` (each mode's mean kinetic energy kT/2) the area of each line is the
   harmonic intensity of :func:`~emlpack.properties.ir.ir_from_hessian`:
   ``A(nu) = N_A/(12 eps0 c^2) (2 c S(f)) / (k T) x Q(nu)/Q_harmonic(nu)``, since
   ``sum_k |dmu/dQ_k|^2 = <|dmu/dt|^2>/kT`` there;
4. the quantum correction factor ``Q`` turns the classical line shape into the quantum one
   (``x = h c nu / kT``; Ramirez, Lopez-Ciudad, Kumar, Marx, J. Chem. Phys. 121, 3973 (2004);
   the absorption is ``alpha ~ nu (1 - e^-x) Q(nu) I_classical(nu)``):
   ``"harmonic"`` ``Q = x / (1 - e^-x)`` (default; gives ``alpha ~ nu^2 I_classical``, exact
   for a harmonic oscillator with a linear dipole, and the same as the classical absorption
   formula), ``"schofield"`` (the "standard" correction) ``Q = e^(x/2)``, and ``"none"``
   ``Q = 1`` (the classical correlation function taken as the quantum one). Every ``Q -> 1``
   for ``x -> 0``.

The harmonic spectrum of the same model is :func:`emlpack.properties.ir.ir_from_hessian`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from emlpack._files import write_figure_atomic, write_json_atomic
from emlpack.properties.ir import IRSpectrum, lorentzian
from emlpack.units import (
    BOLTZMANN_EV_K,
    EV_IN_AMU_A2_PER_FS2,
    IR_KM_PER_MOL_PER_E2_AMU,
    PLANCK_C_EV_CM,
    SPEED_OF_LIGHT_CM_PER_FS,
)

# ------------------------------------------------------------------ IR from MD: dipole ACF
QUANTUM_CORRECTIONS = ("harmonic", "schofield", "none")
LAG_WINDOWS = ("hann", "gaussian", "none")


def quantum_correction(wavenumbers: np.ndarray, temperature: float, kind: str) -> np.ndarray:
    """Quantum correction factor ``Q(nu)`` (module docstring), ``x = h c nu / (k T)``:
    ``harmonic`` x/(1 - e^-x), ``schofield`` (``standard``) e^(x/2), ``none`` 1."""
    if kind == "standard":
        kind = "schofield"
    if kind not in QUANTUM_CORRECTIONS:
        raise ValueError(f"quantum correction must be one of {QUANTUM_CORRECTIONS} (or"
                         f" 'standard'), got {kind!r}")
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0 K, got {temperature}")
    x = PLANCK_C_EV_CM * np.abs(np.asarray(wavenumbers, float)) / (BOLTZMANN_EV_K * temperature)
    if kind == "none":
        return np.ones_like(x)
    if kind == "schofield":
        return np.exp(np.minimum(0.5 * x, 700.0))  # capped: finite (1e304) at any T
    safe = np.where(x > 0, x, 1.0)
    return np.where(x > 0, safe / -np.expm1(-safe), 1.0)


def autocorrelation(signal: np.ndarray) -> np.ndarray:
    """Biased autocorrelation ``C_k = 1/n sum_i x_i . x_{i+k}`` (k = 0..n-1) of ``signal``
    [n, d] with its mean removed, summed over the d components (FFT, zero padded to >= 2n)."""
    x = np.asarray(signal, float)
    x = x - x.mean(axis=0)
    n = len(x)
    n_fft = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(x, n_fft, axis=0)
    return np.fft.irfft((f * f.conj()).real.sum(axis=1), n_fft)[:n] / n


def lag_window(n: int, kind: str = "hann") -> np.ndarray:
    """Lag window ``w_k``, k = 0..n-1, w_0 = 1: Hann cos²(pi k/2n), Gaussian
    exp(-(9/2)(k/n)²) (w_n ~ 0.011), or ones."""
    k = np.arange(n) / n
    if kind == "hann":
        return np.cos(0.5 * np.pi * k) ** 2
    if kind == "gaussian":
        return np.exp(-4.5 * k * k)
    if kind == "none":
        return np.ones(n)
    raise ValueError(f"window must be one of {LAG_WINDOWS}, got {kind!r}")


def find_peaks(
    wavenumbers: np.ndarray, intensities: np.ndarray, min_relative_height: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima with height and prominence above ``min_relative_height`` x the largest
    value; positions refined by a parabola through the three highest grid points. Returns
    (positions cm^-1, heights), ascending in position."""
    import scipy.signal

    y = np.asarray(intensities, float)
    nu = np.asarray(wavenumbers, float)
    top = float(y.max(initial=0.0))
    if top <= 0:
        return np.zeros(0), np.zeros(0)
    idx, _ = scipy.signal.find_peaks(y, height=min_relative_height * top,
                                     prominence=min_relative_height * top)
    pos, height = [], []
    for i in idx:
        if 0 < i < len(y) - 1:
            a, b, c = y[i - 1], y[i], y[i + 1]
            denom = a - 2 * b + c
            shift = 0.5 * (a - c) / denom if denom != 0 else 0.0
            pos.append(nu[i] + shift * (nu[i + 1] - nu[i]))
            height.append(b - 0.25 * (a - c) * shift)
        else:
            pos.append(nu[i])
            height.append(y[i])
    return np.array(pos), np.array(height)


@dataclass
class DipoleIRSpectrum:
    """IR spectrum from a dipole time series (module docstring).

    Attributes:
        wavenumbers: grid (cm^-1), 0 to the Nyquist wavenumber 1/(2 c dt).
        absorbance: km/mol per cm^-1 (line areas in km/mol, comparable with
            :class:`IRSpectrum` intensities).
        resolution: 1/(c n dt) (cm^-1), n dt = total time.
        timestep: dt between frames (fs).
        n_frames: frames used.
        temperature: K (normalisation and the quantum correction).
        window, correction, padding: settings used.
        acf: autocorrelation C_k of the dipole derivative ((e·Å/fs)², lag k dt).
    """

    wavenumbers: np.ndarray
    absorbance: np.ndarray
    resolution: float
    timestep: float
    n_frames: int
    temperature: float
    window: str
    correction: str
    padding: int
    acf: np.ndarray

    def peaks(self, min_relative_height: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """(positions cm^-1, heights km/mol/cm^-1) of :func:`find_peaks`."""
        return find_peaks(self.wavenumbers, self.absorbance, min_relative_height)

    def area(self, low: float = 0.0, high: float = np.inf) -> float:
        """Integrated absorbance between ``low`` and ``high`` cm^-1 (km/mol)."""
        sel = (self.wavenumbers >= low) & (self.wavenumbers <= high)
        return float(np.trapezoid(self.absorbance[sel], self.wavenumbers[sel]))

    def as_dict(self, min_relative_height: float = 1e-3) -> dict:
        """Plain dict for JSON (keys with units): settings, the peaks of :meth:`peaks`, the spectrum
        and the autocorrelation function."""
        pos, height = self.peaks(min_relative_height)
        return {
            "method": "dipole autocorrelation",
            "timestep_fs": self.timestep,
            "n_frames": self.n_frames,
            "total_time_fs": self.timestep * self.n_frames,
            "resolution_cm-1": self.resolution,
            "temperature_K": self.temperature,
            "window": self.window,
            "quantum_correction": self.correction,
            "padding": self.padding,
            "peaks_cm-1": pos.tolist(),
            "peak_heights_km_per_mol_per_cm-1": height.tolist(),
            "peak_min_relative_height": min_relative_height,
            "spectrum_grid_cm-1": self.wavenumbers.tolist(),
            "spectrum_km_per_mol_per_cm-1": self.absorbance.tolist(),
            "acf_lag_fs": (np.arange(len(self.acf)) * self.timestep).tolist(),
            "acf_dipole_derivative_e2_A2_per_fs2": self.acf.tolist(),
        }

    def text(self, min_relative_height: float = 1e-3) -> str:
        """The settings, then one line per peak: wavenumber (cm^-1), height (km/mol per cm^-1)."""
        pos, height = self.peaks(min_relative_height)
        lines = [f"IR from the dipole ACF: {self.n_frames} frames x {self.timestep:g} fs,"
                 f" resolution {self.resolution:.1f} cm^-1, T {self.temperature:.1f} K,"
                 f" window {self.window}, correction {self.correction}",
                 "peak  wavenumber (cm^-1)  height (km/mol per cm^-1)"]
        lines += [f"{k:4d}  {p:18.1f}  {h:18.4g}" for k, (p, h) in enumerate(zip(pos, height,
                                                                                 strict=True))]
        return "\n".join(lines)


def ir_from_dipoles(
    dipoles: np.ndarray,
    timestep: float,
    temperature: float,
    window: str = "hann",
    correction: str = "harmonic",
    padding: int = 8,
    source: str = "<arrays>",
) -> DipoleIRSpectrum:
    """IR spectrum from ``dipoles`` [n, 3] (e·Å) sampled every ``timestep`` fs of an MD run at
    ``temperature`` K (module docstring for the formulas and the corrections)."""
    mu = np.asarray(dipoles, dtype=np.float64)
    if mu.ndim != 2 or mu.shape[1] != 3:
        raise ValueError(f"{source}: dipoles must have shape (n, 3), got {mu.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(mu), axis=1))
    if len(bad):
        raise ValueError(f"{source}, frame {int(bad[0])}: dipole is not finite"
                         f" {mu[bad[0]].tolist()}")
    if len(mu) < 8:
        raise ValueError(f"{source}: {len(mu)} dipoles; at least 8 frames are needed")
    if not timestep > 0:
        raise ValueError(f"{source}: timestep must be > 0 fs, got {timestep}")
    if int(padding) < 1:
        raise ValueError(f"{source}: padding must be >= 1, got {padding}")
    correction = "schofield" if correction == "standard" else correction
    quantum_correction(np.zeros(1), temperature, correction)  # validates kind and temperature
    n = len(mu)
    acf = autocorrelation(np.diff(mu, axis=0) / timestep)  # (e·Å/fs)²
    n_lags = len(acf)
    weighted = acf * lag_window(n_lags, window)
    m = int(padding) * 2 * n_lags
    two_sided = np.zeros(m)
    two_sided[:n_lags] = weighted
    two_sided[m - n_lags + 1:] = weighted[1:][::-1]
    freq = np.fft.rfftfreq(m, timestep)  # 1/fs
    nu = freq / SPEED_OF_LIGHT_CM_PER_FS
    # spectrum of the differences / their transfer function = spectrum of the derivative;
    # per cm^-1: S(nu) = c S(f)
    s_mudot = (np.fft.rfft(two_sided).real * timestep / np.sinc(freq * timestep) ** 2
               * SPEED_OF_LIGHT_CM_PER_FS)  # (e·Å/fs)² per cm^-1
    kt = BOLTZMANN_EV_K * temperature * EV_IN_AMU_A2_PER_FS2  # amu·Å²/fs²
    ratio = (quantum_correction(nu, temperature, correction)
             / quantum_correction(nu, temperature, "harmonic"))
    absorbance = IR_KM_PER_MOL_PER_E2_AMU * 2.0 * s_mudot / kt * ratio
    return DipoleIRSpectrum(
        wavenumbers=nu,
        absorbance=absorbance,
        resolution=1.0 / (SPEED_OF_LIGHT_CM_PER_FS * n * timestep),
        timestep=float(timestep),
        n_frames=n,
        temperature=float(temperature),
        window=window,
        correction=correction,
        padding=int(padding),
        acf=acf,
    )


def trajectory_file(path: str | Path) -> Path:
    """``path`` itself, or for an ``emlp md`` output directory its trajectory file."""
    path = Path(path)
    if path.is_dir():
        from emlpack.dynamics.md import TRAJECTORY

        return path / TRAJECTORY
    return path


def read_dipoles(
    path: str | Path, discard_steps: int = 0
) -> tuple[np.ndarray, float, float]:
    """(dipoles [n, 3] e·Å, timestep fs, mean temperature K or nan) of an ``emlp md``
    trajectory or output directory (frame keys ``dipole``, ``time``, ``step``,
    ``temperature``); frames with ``step < first step + discard_steps`` are dropped. The
    frames must be evenly spaced."""
    from emlpack.io import iread_structures

    path = trajectory_file(path)
    mu, times, steps, temps = [], [], [], []
    for i, s in enumerate(iread_structures(path)):
        where = f"{path}, frame {i}"
        for key in ("dipole", "time"):
            if key not in s.info:
                raise ValueError(f"{where}: no '{key}' in the frame (not an 'emlp md'"
                                 " trajectory of a molecule?)")
        d = np.asarray(s.info["dipole"], float).reshape(-1)
        if d.shape != (3,) or not np.all(np.isfinite(d)):
            raise ValueError(f"{where}: 'dipole' must be 3 finite numbers, got {d.tolist()}")
        mu.append(d)
        times.append(float(s.info["time"]))
        steps.append(int(s.info.get("step", i)))
        temps.append(float(s.info.get("temperature", np.nan)))
    if not mu:
        raise ValueError(f"{path}: no frames")
    steps_arr = np.array(steps)
    keep = steps_arr >= steps_arr[0] + discard_steps
    mu_arr, t = np.array(mu)[keep], np.array(times)[keep]
    if len(t) < 2:
        raise ValueError(f"{path}: {len(t)} frames after discarding {discard_steps} steps")
    dt = np.diff(t)
    uneven = np.flatnonzero(np.abs(dt - dt[0]) > 1e-6 * abs(dt[0]) + 1e-9)
    if dt[0] <= 0 or len(uneven):
        k = int(uneven[0]) + 1 if len(uneven) else 1
        first = int(np.flatnonzero(keep)[0])
        raise ValueError(f"{path}, frame {first + k}: frames are not evenly spaced in time"
                         f" (dt {dt[k - 1]:g} fs, first dt {dt[0]:g} fs)")
    return mu_arr, float(dt[0]), float(np.nanmean(np.array(temps)[keep]))


def ir_from_trajectory(
    path: str | Path,
    temperature: float | None = None,
    discard_steps: int = 0,
    **options,
) -> DipoleIRSpectrum:
    """:func:`ir_from_dipoles` of an ``emlp md`` trajectory; ``temperature`` defaults to the
    mean of the frames' ``temperature``."""
    mu, dt, t_mean = read_dipoles(path, discard_steps)
    if temperature is None:
        if not np.isfinite(t_mean):
            raise ValueError(f"{path}: no 'temperature' in the frames; give the temperature")
        temperature = t_mean
    return ir_from_dipoles(mu, dt, temperature, source=str(path), **options)


def write_dipole_ir(
    spectrum: DipoleIRSpectrum,
    json_path: str | Path,
    png_path: str | Path | None = None,
    harmonic: IRSpectrum | tuple[np.ndarray, np.ndarray] | None = None,
    fwhm: float | None = None,
    title: str = "",
) -> None:
    """Write the MD spectrum as JSON and optionally a PNG (both atomically), with the
    ``harmonic`` spectrum (an :class:`IRSpectrum` or (wavenumbers cm^-1, intensities km/mol);
    Lorentzians of ``fwhm``, default the MD resolution) overlaid."""
    data = spectrum.as_dict()
    fwhm = spectrum.resolution if fwhm is None else fwhm
    if isinstance(harmonic, IRSpectrum):
        harmonic = (harmonic.frequencies, harmonic.intensities)
    if harmonic is not None:
        harmonic = (np.asarray(harmonic[0], float), np.asarray(harmonic[1], float))
        data["harmonic_frequencies_cm-1"] = harmonic[0].tolist()
        data["harmonic_intensities_km_per_mol"] = harmonic[1].tolist()
        data["harmonic_fwhm_cm-1"] = fwhm
    write_json_atomic(json_path, data)
    if png_path is None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nu, a = spectrum.wavenumbers, spectrum.absorbance
    pos, _ = spectrum.peaks()
    top = max(4000.0, float(pos.max(initial=0.0)) + 500.0)
    if harmonic is not None:
        top = max(top, float(harmonic[0].max(initial=0.0)) + 500.0)
    sel = nu <= top
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(nu[sel], a[sel], color="C0", label=f"MD dipole ACF ({spectrum.correction})")
    if harmonic is not None:
        ax.plot(nu[sel], lorentzian(nu[sel], harmonic[0], harmonic[1], fwhm),
                color="C1", ls="--", label=f"harmonic (FWHM {fwhm:.0f} cm$^{{-1}}$)")
    ax.legend()
    ax.set_xlabel("wavenumber (cm$^{-1}$)")
    ax.set_ylabel("absorbance (km/mol per cm$^{-1}$)")
    ax.set_title(title or f"IR from MD, {spectrum.temperature:.0f} K, resolution"
                 f" {spectrum.resolution:.0f} cm$^{{-1}}$")
    fig.tight_layout()
    write_figure_atomic(png_path, fig, dpi=120)
    plt.close(fig)
