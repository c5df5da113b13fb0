"""Where the study's harmonic frequencies go wrong: geometry or curvature, and the pairs' part.

    python examples/eqm7/ir_modes.py [--groups aug noaug] [--json examples/eqm7/ir_modes.json]

For every test molecule with a DFT Hessian (``datasets/mini-eqm7/references/``) and every
model of the study (``config.yaml``'s work directory), the electron pairs relaxed at the DFT
optimum from the DFT Boys centres, cores at the DFT optimum (no optimisation):

* ``dft_geometry``: the frequencies of the model's Born-Oppenheimer Hessian there, matched to
  the DFT ones in ascending order as in the study's ``ir`` stage (which optimises first): the
  curvature error without the geometry error;
* ``dft_modes``: each DFT normal mode's frequency from the model's Hessian (the Rayleigh
  quotient u^T H u of the mass-weighted DFT eigenvector u, signed square root): the same
  motion on both sides, no mode matching;
* ``stiffer_pairs``: as ``dft_geometry`` with the pair-pair block of the extended Hessian
  multiplied by 1/(1 - slope), ``slope`` the model's pair-field slope on the test molecules
  (``results.json``: the pair-force error is about slope x qE when the model's pair stiffness
  is (1 - slope) times DFT's): the frequencies if the pairs were as stiff as DFT's centres.

Each is summarised like the study's ``ir_summary`` (MAE per molecule, then mean over them; and
by band of the DFT frequency, ``run_study.IR_BANDS``), beside the study's own values from
``results.json``. A molecule is skipped for a model whose pair relaxation at the DFT geometry
fails (the study's ``ir`` stage fails there too). About 0.3 s CPU per molecule and model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run_study  # noqa: E402

WAYS = ("dft_geometry", "dft_modes", "stiffer_pairs")


def model_frequencies(model, structure, dft_hessian: np.ndarray, slope: float) -> dict | None:
    """The three ways' frequencies (cm⁻¹) of one model at one DFT optimum (module docstring);
    None when the pairs cannot be relaxed there."""
    from emlpack.geometry import normal_modes
    from emlpack.pairs.relax import relax_pairs
    from emlpack.properties.hessian import extended_hessian
    from emlpack.properties.ir import ir_from_hessian
    from emlpack.units import WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU

    res = relax_pairs(model, structure)[0]
    if res.reason:
        return None
    s = structure.copy(pairs=res.pairs)
    h = extended_hessian(model, s)[1].numpy()
    spec = ir_from_hessian(h, s)
    # the DFT modes through the model's Born-Oppenheimer core Hessian (mass-weighted)
    inv_sqm = 1.0 / np.sqrt(np.repeat(spec.masses, 3))
    _, modes = normal_modes(dft_hessian, s.positions, spec.masses)
    k_model = spec.hessian * inv_sqm[:, None] * inv_sqm[None, :]
    lam = np.einsum("ik,ij,jk->k", modes, 0.5 * (k_model + k_model.T), modes)
    along = np.sign(lam) * np.sqrt(np.abs(lam)) * WAVENUMBER_CM1_PER_SQRT_EV_A2_AMU
    # the pair-pair block stiffened by 1/(1 - slope)
    nc, n = 3 * s.n_cores, 3 * (s.n_cores + s.n_pairs)
    stiff = h.copy()
    stiff[nc:n, nc:n] /= 1.0 - slope
    return {"dft_geometry": spec.frequencies.tolist(), "dft_modes": along.tolist(),
            "stiffer_pairs": ir_from_hessian(stiff, s).frequencies.tolist()}


def summary(rows: dict[str, dict[str, dict]], refs: dict) -> dict:
    """Per way: the frequency MAE (per molecule, then the mean over molecules) and the band
    errors, per model, then mean ± std over the models."""
    out = {}
    for way in WAYS:
        per_model = {}
        for name, mols in rows.items():
            errors = []
            for mol, freqs in mols.items():
                ref = refs[mol]["frequencies_cm-1"]
                if way == "dft_modes":  # the same modes on both sides: no matching
                    errors.append((np.asarray(freqs[way]) - np.asarray(ref), np.asarray(ref)))
                else:
                    err = run_study.freq_errors(freqs[way], ref)
                    if err is not None:
                        errors.append(err)
            per_model[name] = {
                "frequency_mae": float(np.mean([np.abs(e).mean() for e, _ in errors]))
                if errors else None,
                "molecules": len(errors), "bands": run_study.band_errors(errors)}
        out[way] = {"per_model": per_model,
                    "frequency_mae": run_study.mean_std(
                        [m["frequency_mae"] for m in per_model.values()]),
                    "bands": run_study.bands_over_models(per_model.values())}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--groups", nargs="+", default=["aug", "noaug"])
    ap.add_argument("--results", type=Path, default=HERE / "results.json",
                    help="the study's results.json (pair-field slopes, the study's own IR)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    import torch

    from emlpack._files import write_json_atomic
    from emlpack.train.evaluate import load_for_evaluation

    torch.set_num_threads(1)
    cfg = run_study.load_config(HERE / "config.yaml", [f"groups={args.groups}"])
    study = run_study.Study(cfg, log=lambda m: None)
    refs = run_study.ir_references(study)
    results = json.loads(args.results.read_text())
    groups = results["evaluation"]["test"]["groups"]
    report: dict = {"molecules": sorted(refs), "groups": {}}
    for group in args.groups:
        slopes = dict(zip(groups[group]["models"],
                          groups[group]["static"]["pair_field_slope"]["values"], strict=True))
        rows: dict[str, dict] = {}
        skipped = []
        for g, name, path in study.require_models():
            if g != group:
                continue
            model = load_for_evaluation(path)[0]
            rows[name] = {}
            for mol, r in refs.items():
                f = model_frequencies(model, run_study.dft_structure(r),
                                      np.asarray(r["hessian_eV_A2"]), slopes[name])
                if f is None:
                    skipped.append(f"{name}/{mol}")
                else:
                    rows[name][mol] = f
        imaginary = {way: sum(int((np.asarray(f[way]) < 0).sum()) for mols in rows.values()
                              for f in mols.values()) for way in WAYS}
        report["groups"][group] = {"slopes": slopes, "skipped": skipped,
                                   "imaginary_modes": imaginary,
                                   "modes": sum(len(f["dft_geometry"]) for mols in rows.values()
                                                for f in mols.values()),
                                   "study": results["ir"]["groups"][group],
                                   **summary(rows, refs), "frequencies": rows}
        print_group(group, report["groups"][group])
    if args.json:
        write_json_atomic(args.json, report)


def print_group(group: str, g: dict) -> None:
    """One table per group: MAE and mean error by band, the study's (own optimum) and the
    three ways'."""
    cols = [("own optimum (study)", g["study"]), *((w, g[w]) for w in WAYS)]
    print(f"\n{run_study.GROUP_LABEL[group]} (pair-field slopes "
          + ", ".join(f"{v:.2f}" for v in g["slopes"].values()) + "; skipped: "
          + (", ".join(g["skipped"]) or "none") + f"; imaginary modes of {g['modes']}: "
          + ", ".join(f"{w} {n}" for w, n in g["imaginary_modes"].items()) + ")")
    print("| band [cm⁻¹] | " + " | ".join(c for c, _ in cols) + " |")
    print("|---|" + "---|" * len(cols))
    print("| all (MAE) | " + " | ".join(_ms(v["frequency_mae"]) for _, v in cols) + " |")
    for k, band in enumerate(run_study.IR_BANDS):
        print(f"| {band[0]:g}-{band[1]:g}: MAE / mean error | " + " | ".join(
            f"{_ms(v['bands'][k]['mae'])} / {_ms(v['bands'][k]['mean_error'])}"
            for _, v in cols) + " |")


def _ms(d: dict) -> str:
    """mean (± std) over models, cm⁻¹."""
    return "–" if d["mean"] is None else f"{d['mean']:.1f} (± {d['std']:.1f})"


if __name__ == "__main__":
    main()
