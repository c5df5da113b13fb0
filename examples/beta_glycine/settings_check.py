"""Cheaper CP2K settings for the crystal campaign (issue 52, item 1): labels and cost.

At the DFT optimum (``WORKDIR/optimized.xyz`` of the ``optimize`` stage, or ``--structure``)
one label from the atomic guess keeps its wavefunction; then one round-0-like sample (random
core displacements, sigma 0.05 Å, seed 0; stress set, Wannier centres) is labeled from that
wavefunction (``CP2KSettings.wavefunction_guess``, as the campaign would) at the config's level
and at each cheaper (or tighter) setting. Each setting's labels are compared with the config's
level (or ``--reference``, e.g. the tightest grid) on the same sample: energy per atom, forces,
stress, Wannier centres; cost in CPU seconds and SCF steps. One process, one calculation at a
time; each result is a file in ``--results`` (default ``runs/bg_settings/``; a rerun computes
only the missing ones, ``--commit`` commits each); the table goes to ``--out``.

Usage (from the project root)::

    OMP_NUM_THREADS=1 python examples/beta_glycine/settings_check.py [--structure X.xyz]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from emlpack.commits import git_commit
from emlpack.io import read_structures, write_structures
from emlpack.qm.cp2k import CP2KLabeler, CP2KSettings
from emlpack.structure import Structure
from emlpack.units import EV_PER_A3_IN_GPA

HERE = Path(__file__).resolve().parent
OUT = Path("runs/bg_settings")

#: the cheaper settings, each a change of the config's cp2k section
CANDIDATES: dict[str, dict] = {
    "config": {},
    "eps-scf-1e-7": {"eps_scf": 1e-7},  # tighter: the config's own SCF error
    "cutoff-500": {"cutoff_ry": 500.0},  # tighter: the config's own grid error
    "cutoff-350": {"cutoff_ry": 350.0},
    "cutoff-300": {"cutoff_ry": 300.0},
    "cutoff-300-rel-40": {"cutoff_ry": 300.0, "rel_cutoff_ry": 40.0},
    "eps-scf-1e-5": {"eps_scf": 1e-5},
    "eps-default-1e-10": {"eps_default": 1e-10},
    "rel-60": {"rel_cutoff_ry": 60.0},  # the finest grid's share of the density (tighter)
    "cutoff-600": {"cutoff_ry": 600.0},  # tighter still: the grid error of 400 and 500 Ry
    "cutoff-600-rel-60": {"cutoff_ry": 600.0, "rel_cutoff_ry": 60.0},
}


def base_settings(config: Path) -> CP2KSettings:
    """The study's CP2K settings, one process, no MPI launcher."""
    cfg = yaml.safe_load(config.read_text())
    return CP2KSettings(**{**cfg.get("cp2k", {}), "n_processes": 1, "mpirun": None,
                           "reuse_wavefunction": False})


def sample_of(structure: Structure, sigma: float = 0.05, seed: int = 0) -> Structure:
    """The structure with its cores displaced by N(0, sigma²) per component (Å)."""
    rng = np.random.default_rng(seed)
    shift = rng.normal(0.0, sigma, (structure.n_cores, 3))
    return structure.copy(positions=structure.positions + shift,
                          source=f"{structure.source} displaced (sigma {sigma} Å, seed {seed})")


def cpu_label(labeler: CP2KLabeler, s: Structure) -> tuple[Structure, float]:
    """The labeled structure (stress set) and the CPU seconds CP2K took (children's time)."""
    t0 = time.process_time(), _children_cpu()
    out = labeler(s, stress=True)
    return out, (time.process_time() - t0[0]) + (_children_cpu() - t0[1])


def _children_cpu() -> float:
    t = os.times()
    return t.children_user + t.children_system


def optimum_wavefunction(st: CP2KSettings, structure: Structure) -> tuple[Path, dict]:
    """The optimum's wavefunction from the atomic guess (kept in OUT), and that label's cost."""
    wfn, meta = OUT / "optimum.wfn", OUT / "optimum.json"
    if wfn.exists() and meta.exists():
        return wfn, json.loads(meta.read_text())
    lab = CP2KLabeler(replace(st, reuse_wavefunction=True), workdir=OUT / "scratch")
    out, cpu = cpu_label(lab, structure)
    tmp = OUT / ".optimum.wfn.tmp"
    shutil.copyfile(lab.wavefunction(structure), tmp)
    tmp.replace(wfn)
    info = {"cpu_s": cpu, "wall_s": out.info["wall_time"], "scf_steps": out.info["scf_steps"],
            "guess": "atomic"}
    meta.write_text(json.dumps(info, indent=1))
    return wfn, info


def run_candidate(name: str, st: CP2KSettings, sample: Structure, wfn: Path,
                  results: Path = OUT) -> dict:
    """One setting's labels of the sample from the optimum's wavefunction (cached in
    ``results``: NAME.xyz, NAME.json)."""
    done = results / f"{name}.xyz"
    meta = results / f"{name}.json"
    if done.exists() and meta.exists():
        return {"labels": read_structures(done)[0], **json.loads(meta.read_text())}
    settings = replace(st, **CANDIDATES[name], wavefunction_guess=str(wfn))
    out, cpu = cpu_label(CP2KLabeler(settings, workdir=OUT / "scratch"), sample)
    info = {"cpu_s": cpu, "wall_s": out.info["wall_time"], "scf_steps": out.info["scf_steps"],
            "settings": CANDIDATES[name]}
    write_structures(done, [out])  # atomic
    meta.write_text(json.dumps(info, indent=1))
    return {"labels": out, **info}


def compare(ref: Structure, other: Structure) -> dict:
    """Label differences (other - ref): energy per atom (meV), forces (meV/Å), stress (GPa),
    Wannier centres (Å, matched by index: the same localisation from the same guess); and
    ``other``'s net force |sum F| (eV/Å: zero in exact arithmetic, a measure of its numerical
    force error)."""
    df = 1e3 * np.abs(other.forces - ref.forces)
    dc = np.linalg.norm(other.pairs - ref.pairs, axis=1) if other.n_pairs == ref.n_pairs else None
    return {
        "net_force_eV_per_A": float(np.linalg.norm(other.forces.sum(axis=0))),
        "energy_meV_per_atom": 1e3 * (other.energy - ref.energy) / ref.n_cores,
        "forces_mae_meV_per_A": float(df.mean()), "forces_max_meV_per_A": float(df.max()),
        "stress_max_GPa": float(np.abs(other.stress - ref.stress).max() * EV_PER_A3_IN_GPA),
        "centres_max_A": None if dc is None else float(dc.max()),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", default=str(HERE / "config.yaml"))
    p.add_argument("--structure", default=None,
                   help="extxyz of the optimum (default: WORKDIR/optimized.xyz of the config)")
    p.add_argument("--out", default=str(HERE / "settings_check.json"), help="the table (JSON)")
    p.add_argument("--only", nargs="+", choices=list(CANDIDATES), default=list(CANDIDATES))
    p.add_argument("--reference", choices=list(CANDIDATES), default="config",
                   help="the setting the others are compared with (default: the config's)")
    p.add_argument("--results", default=str(OUT),
                   help="folder of the finished candidates' labels (NAME.xyz, NAME.json); the"
                   " wavefunction and CP2K's scratch stay in runs/bg_settings")
    p.add_argument("--commit", action="store_true",
                   help="commit the results folder after every candidate")
    args = p.parse_args(argv)
    cfg = yaml.safe_load(Path(args.config).read_text())
    path = Path(args.structure or Path(cfg["workdir"]) / "optimized.xyz")
    if not path.exists():
        sys.exit(f"settings_check: {path}: no such file (the optimize stage writes it when it"
                 " converges; or pass --structure)")
    optimum = read_structures(path)[-1].copy(field=np.zeros(3))
    OUT.mkdir(parents=True, exist_ok=True)
    st = base_settings(Path(args.config))
    wfn, cold = optimum_wavefunction(st, optimum)
    print(f"optimum from the atomic guess: {cold['cpu_s']:.0f} CPU s, {cold['scf_steps']} SCF"
          " steps", flush=True)
    sample = sample_of(optimum)
    names = list(dict.fromkeys(["config", args.reference, *args.only]))
    folder = Path(args.results)
    folder.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in names:
        fresh = not (folder / f"{name}.json").exists()
        r = run_candidate(name, st, sample, wfn, folder)
        results[name] = r
        if fresh and args.commit:
            git_commit([folder], f"beta-glycine settings check at the optimum: {name}")
        print(f"{name}: {r['cpu_s']:.0f} CPU s, {r['scf_steps']} SCF steps", flush=True)
    ref = results[args.reference]["labels"]
    table = {"structure": str(path), "level": st.level(), "optimum_atomic_guess": cold,
             "sample": "cores displaced by N(0, 0.05 Å), seed 0; stress set; from the"
             " optimum's wavefunction", "reference": args.reference, "settings": {}}
    for name, r in results.items():
        row = {k: r[k] for k in ("cpu_s", "wall_s", "scf_steps")}
        row["changes"] = CANDIDATES[name]
        row["cost_ratio"] = r["cpu_s"] / results["config"]["cpu_s"]
        row.update(compare(ref, r["labels"]))
        table["settings"][name] = row
    target = Path(args.out)
    tmp = target.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(table, indent=1) + "\n")
    tmp.replace(target)
    if args.commit:
        git_commit([target], "beta-glycine settings check at the optimum: table")
    for name, row in table["settings"].items():
        print(f"{name:>20}: x{row['cost_ratio']:.2f} cost, dE {row['energy_meV_per_atom']:+.3f}"
              f" meV/atom, dF mae/max {row['forces_mae_meV_per_A']:.1f}/"
              f"{row['forces_max_meV_per_A']:.1f} meV/Å, dσ {row['stress_max_GPa']:.3f} GPa,"
              f" centres {row['centres_max_A']}")


if __name__ == "__main__":
    main()
