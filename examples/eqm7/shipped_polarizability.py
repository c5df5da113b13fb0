"""Polarizabilities of the shipped (pretrained) mini-eqm7 members at every finished DFT optimum.

    python examples/eqm7/shipped_polarizability.py [--workdir runs/eqm7-shipped-pol]

Runs the study's ``polarizability`` stage (pairs relaxed from the DFT centres, cores clamped,
against the DFT finite-field tensors of ``datasets/mini-eqm7/references/``) on the members
installed under ``emlpack/pretrained/mini-eqm7`` and prints, for the card's test molecules and
for the second test set's (the authors' six molecules), the Table 3 figures (tensor-component
MAE and median, mean ± std over the members) and, per molecule, the isotropic polarizabilities
of the members against DFT. The numbers in docs/pretrained.md come from here; rerun it when
more DFT references are finished.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import run_study  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", type=Path, default=Path("runs/eqm7-shipped-pol"))
    args = ap.parse_args()
    from emlpack.pretrained import resolve_model

    paths, _ = resolve_model("mini-eqm7")
    for seed, path in enumerate(paths):  # the study's layout of finished models
        run = args.workdir / "models" / "aug" / f"seed{seed}"
        run.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, run / "best.pt")
        (run / "done.json").write_text(json.dumps({"best": str(path)}))
    cfg = run_study.load_config(HERE / "config.yaml", [
        f"workdir={args.workdir}", "groups=[aug]", f"seeds={list(range(len(paths)))}"])
    study = run_study.run(["polarizability"], cfg)
    for set_name, title in (("test", "test molecules of the card"),
                            ("pbe0_subset", "the second test set (the authors' six molecules)")):
        report(study, len(paths), set_name, title)


def report(study, n_members: int, set_name: str, title: str) -> None:
    """Table 3's polarizability figures of one set, and each molecule's isotropic values."""
    summary = run_study.polarizability_summary(study, set_name)
    if summary is None:
        print(f"{title}: no DFT reference finished yet")
        return
    g = summary["groups"]["aug"]
    print(f"{title}: {summary['n_molecules']} molecules; tensor components (bohr^3): MAE"
          f" {g['mae']['mean']:.1f} ± {g['mae']['std']:.1f}, median {g['median']['mean']:.1f}"
          f" ± {g['median']['std']:.1f}, error rate {g['error_rate']['mean']:.3f}; ensemble mean"
          f" tensor MAE {g['ensemble_mae']:.1f}, median {g['ensemble_median']:.1f}; intrinsic"
          f" variability {summary['intrinsic_mae']:.1f}")
    rows = [json.loads(run_study.stage_file(study, "polarizability", f"aug-s{seed}", set_name)
                       .read_text())["molecules"] for seed in range(n_members)]
    for mol, ref in run_study.dft_results(study, set_name).items():
        if any(mol not in r for r in rows):
            continue  # its reference finished after the stage ran
        iso = []
        for r in rows:
            t = r[mol].get("polarizability_bohr3")
            iso.append(np.trace(t) / 3.0 if t is not None else float("nan"))
        ref_iso = np.trace(ref["polarizability_bohr3"]) / 3.0
        print(f"{mol}: DFT {ref_iso:.1f} bohr^3, members "
              + ", ".join("failed" if np.isnan(x) else f"{x:.1f}" for x in iso)
              + f" (mean / DFT {np.nanmean(iso) / ref_iso:.2f})")


if __name__ == "__main__":
    main()
