"""Choosing the cheap level of the QM7-wide pretraining set by measurement (issue 50, item 1).

For ten training molecules of mini-eQM7 (two each of 3-7 heavy atoms, seeded), every candidate
level relabels two stored configurations (an NMS-600 K and an NMS-800 K torsion sample, at the
field they were labeled with) and computes the finite-field polarizability at the molecule's
prepared (GFN2-xTB) optimum; the paper's level computes the same polarizability. Against the
paper's level (the stored labels): force MAE, Foster-Boys centre distances (matched one to one),
dipole (from the centres: for localized orbitals it equals the density's), the energy difference
between the two configurations, the isotropic polarizability; and the CPU seconds of a label
(forces + centres, one thread).

Every measurement is a small JSON file ``OUT/LEVEL/NAME-KIND.json`` (written atomically, never
recomputed), so the job resumes where it stopped; ``--table`` writes ``OUT/table.md`` and
``OUT/summary.json`` from what is there::

    OMP_NUM_THREADS=1 python examples/qm7_cheap/level_choice.py [--commit]
    python examples/qm7_cheap/level_choice.py --table
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from emlpack._files import write_text_atomic
from emlpack.commits import git_commit
from emlpack.data.shards import read_molecule_table, shard_paths
from emlpack.data.store import DatasetStore
from emlpack.qm.levels import PAPER, Level
from emlpack.qm.pyscf_labeler import PySCFLabeler
from emlpack.qm.relabel import match_centres
from emlpack.structure import core_charges
from emlpack.units import COULOMB_EV_A, FIELD_AU_IN_V_PER_A, POLARIZABILITY_A3_IN_BOHR3

DATA = Path("datasets/mini-eqm7")
OUT = Path("examples/qm7_cheap/level_choice")
KINDS = ("nms600", "nms800-torsion")
FIELD_AU = 1e-3  # finite-field step, as the eqm7 study's references
DEBYE_PER_E_A = 4.803204

#: candidate levels: name -> (Level, Boys starts). The paper's level is ``paper`` (polarizability
#: only: its labels are the stored ones).
CANDIDATES: dict[str, tuple[Level, int]] = {
    "pbe0_6-31gs": (Level(basis="6-31g*"), 3),
    "pbe0_6-31+gs": (Level(basis="6-31+g*"), 3),
    "pbe0_def2-svp": (Level(basis="def2-svp"), 3),
    "pbe0_def2-svpd": (Level(basis="def2-svpd"), 3),
    # trade-offs measured one at a time on the cheapest basis
    "pbe0_6-31gs_grid1": (Level(basis="6-31g*", grid_level=1), 3),
    "pbe0_6-31gs_boys1": (Level(basis="6-31g*"), 1),
    "pbe0_6-31gs_tol1e-8": (Level(basis="6-31g*", conv_tol=1e-8), 3),
    # all three at once on the diffuse bases
    "pbe0_6-31+gs_fast": (Level(basis="6-31+g*", grid_level=1, conv_tol=1e-8), 1),
    "pbe0_def2-svpd_fast": (Level(basis="def2-svpd", grid_level=1, conv_tol=1e-8), 1),
}


def labeled_molecules() -> set[str]:
    """Molecules with labeled configurations in the shards."""
    names = set()
    for path in shard_paths(DATA):
        with DatasetStore(path, "r") as store:
            names |= {k.split("/")[0] for k in store.keys()}
    return names


def pick_molecules(seed: int = 0, per_size: int = 2) -> list[dict]:
    """Two labeled training molecules of each size 3-7 heavy atoms (seeded), in size order."""
    labeled = labeled_molecules()
    rows = [r for r in read_molecule_table(DATA) if r["split"] == "train"
            and r["name"].startswith("qm7-") and r["name"] in labeled]
    rng = np.random.default_rng(seed)
    out = []
    for n in range(3, 8):
        pool = [r for r in rows if r["n_heavy"] == n]
        out += [pool[i] for i in sorted(rng.choice(len(pool), per_size, replace=False))]
    return out


def stored_configurations(names: set[str]) -> dict[tuple[str, str], object]:
    """(molecule, kind) -> the first stored configuration of that kind (paper's level)."""
    found = {}
    for path in shard_paths(DATA):
        with DatasetStore(path, "r") as store:
            for s in store:
                key = (s.info.get("molecule_id"), s.info.get("kind"))
                if key[0] in names and key[1] in KINDS and key not in found:
                    found[key] = s
    return found


def dipole(numbers: np.ndarray, positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Dipole (e·Å) of cores and valence pairs (charge -2)."""
    return core_charges(numbers) @ positions - 2.0 * pairs.sum(axis=0)


def label_measurement(level: Level, starts: int, s) -> dict:
    """Relabel one stored configuration; differences from its stored (paper-level) labels."""
    lab = PySCFLabeler(level, boys_starts=starts, threads=1)
    t0, c0 = time.perf_counter(), time.process_time()
    r = lab(s.numbers, s.positions, field=s.field, charge=s.charge)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    if not r.ok:
        return {"ok": False, "error": r.error, "cpu_s": cpu}
    order, dmax = match_centres(s.pairs, r.pairs)
    d = np.linalg.norm(r.pairs[order] - s.pairs, axis=1)
    dp = dipole(s.numbers, s.positions, r.pairs) - dipole(s.numbers, s.positions, s.pairs)
    return {"ok": True, "cpu_s": cpu, "wall_s": wall, "scf_cycles": r.scf_cycles,
            "n_atoms": len(s.numbers), "energy_eV": r.energy, "paper_energy_eV": s.energy,
            "force_mae_meV_A": 1000 * float(np.abs(r.forces - s.forces).mean()),
            "force_max_meV_A": 1000 * float(np.abs(r.forces - s.forces).max()),
            "centre_median_A": float(np.median(d)), "centre_max_A": float(dmax),
            "dipole_error_D": float(np.linalg.norm(dp) * DEBYE_PER_E_A),
            "boys_note": r.boys_note}


def polarizability(level: Level, numbers: np.ndarray, positions: np.ndarray) -> dict:
    """Finite-field polarizability (bohr³) at a fixed geometry: six SCFs, no forces, no Boys."""
    lab = PySCFLabeler(level, boys_starts=1, threads=1, reuse_density=True)
    f = FIELD_AU * FIELD_AU_IN_V_PER_A
    c0 = time.process_time()
    dip = np.zeros((3, 2, 3))
    for a in range(3):
        for k, sign in enumerate((1.0, -1.0)):
            field = np.zeros(3)
            field[a] = sign * f
            r = lab(numbers, positions, field=field, forces=False, localize=False)
            if not r.ok:
                return {"ok": False, "error": r.error}
            dip[a, k] = r.dipole
    alpha = ((dip[:, 0] - dip[:, 1]) / (2 * f)).T
    alpha = 0.5 * (alpha + alpha.T) * COULOMB_EV_A * POLARIZABILITY_A3_IN_BOHR3
    return {"ok": True, "cpu_s": time.process_time() - c0, "alpha_bohr3": alpha.tolist(),
            "alpha_iso_bohr3": float(np.trace(alpha) / 3)}


def complete() -> bool:
    """Every measurement file exists (the job has nothing left to do)."""
    molecules = pick_molecules()
    levels = ["paper", *CANDIDATES]
    return all((OUT / name / f"{m['name']}-{kind}.json").exists() for m in molecules
               for name in levels for kind in (("alpha",) if name == "paper"
                                                else ("alpha", *KINDS)))


def run(commit: bool, commit_minutes: float = 25.0) -> None:
    molecules = pick_molecules()
    names = {m["name"] for m in molecules}
    configs = stored_configurations(names)
    last = time.monotonic()
    levels = {"paper": (PAPER, 1), **CANDIDATES}
    # the polarizabilities of the paper's level interleaved with the cheap levels' work, so
    # that a short run already compares every candidate on the first molecules
    for m in molecules:
        with np.load(DATA / "prepared" / f"{m['name']}.npz") as prep:
            numbers, positions = prep["numbers"], prep["positions"]
        for name, (level, starts) in levels.items():
            jobs = [("alpha", None)] + ([] if name == "paper" else
                                        [(k, configs.get((m["name"], k))) for k in KINDS])
            for kind, s in jobs:
                path = OUT / name / f"{m['name']}-{kind}.json"
                if path.exists() or (kind != "alpha" and s is None):
                    continue
                res = (polarizability(level, numbers, positions) if kind == "alpha"
                       else label_measurement(level, starts, s))
                res.update(molecule=m["name"], n_heavy=m["n_heavy"], kind=kind, level=name,
                           settings=dict(replace(level).as_dict(), boys_starts=starts))
                path.parent.mkdir(parents=True, exist_ok=True)
                write_text_atomic(path, json.dumps(res, indent=1))
                print(time.strftime("%H:%M:%S"), name, m["name"], kind,
                      f"{res.get('cpu_s', 0):.1f} s", flush=True)
                if commit and time.monotonic() - last > commit_minutes * 60:
                    table()
                    git_commit([OUT], "qm7 cheap level choice: measurements")
                    last = time.monotonic()
    table()
    if commit:
        git_commit([OUT], "qm7 cheap level choice: measurements (all)")


def table() -> dict:
    """``OUT/summary.json`` and ``OUT/table.md`` from the measurement files there."""
    rows = [json.loads(p.read_text()) for p in sorted(OUT.glob("*/*.json"))
            if p.name != "summary.json"]
    paper = {r["molecule"]: r["alpha_iso_bohr3"] for r in rows
             if r["level"] == "paper" and r["kind"] == "alpha" and r["ok"]}
    summary = {}
    for name in CANDIDATES:
        lab = [r for r in rows if r["level"] == name and r["kind"] != "alpha" and r["ok"]]
        alp = [r for r in rows if r["level"] == name and r["kind"] == "alpha" and r["ok"]
               and r["molecule"] in paper]
        if not lab:
            continue
        # energy difference between a molecule's two configurations, against the paper's
        by_mol: dict[str, list[dict]] = {}
        for r in lab:
            by_mol.setdefault(r["molecule"], []).append(r)
        dde = [1000 * abs((a["energy_eV"] - b["energy_eV"])
                          - (a["paper_energy_eV"] - b["paper_energy_eV"])) / a["n_atoms"]
               for a, b in (v for v in by_mol.values() if len(v) == 2)]
        rel = [r["alpha_iso_bohr3"] / paper[r["molecule"]] - 1 for r in alp]
        summary[name] = {
            "settings": lab[0]["settings"], "configurations": len(lab),
            "molecules": len(by_mol), "cpu_s_mean": float(np.mean([r["cpu_s"] for r in lab])),
            "cpu_s_per_atom": float(np.mean([r["cpu_s"] / r["n_atoms"] for r in lab])),
            "force_mae_meV_A": float(np.mean([r["force_mae_meV_A"] for r in lab])),
            "centre_median_A": float(np.median([r["centre_median_A"] for r in lab])),
            "centre_max_A": float(np.max([r["centre_max_A"] for r in lab])),
            "dipole_error_D": float(np.mean([r["dipole_error_D"] for r in lab])),
            "relative_energy_error_meV_atom": float(np.mean(dde)) if dde else None,
            "alpha_molecules": len(rel),
            "alpha_iso_relative_error": float(np.mean(rel)) if rel else None,
            "alpha_iso_abs_relative_error": float(np.mean(np.abs(rel))) if rel else None,
        }
    OUT.mkdir(parents=True, exist_ok=True)
    write_text_atomic(OUT / "summary.json", json.dumps(summary, indent=1))
    lines = ["| variant | level | grid | SCF tol | Boys starts | configs | CPU s / config |"
             " force MAE"
             " meV/Å | centre median / max Å | dipole error D | ΔE error meV/atom |"
             " α_iso vs paper |", "|---" * 12 + "|"]
    for name, s in summary.items():
        st = s["settings"]
        a, n_alpha = s["alpha_iso_relative_error"], s["alpha_molecules"]
        e = s["relative_energy_error_meV_atom"]
        lines.append(
            f"| {name} | {st['xc']}/{st['basis']} | {st['grid_level']} | {st['conv_tol']:g} |"
            f" {st['boys_starts']} | {s['configurations']} | {s['cpu_s_mean']:.1f} |"
            f" {s['force_mae_meV_A']:.0f} | {s['centre_median_A']:.4f} / {s['centre_max_A']:.3f}"
            f" | {s['dipole_error_D']:.3f} | {'' if e is None else f'{e:.2f}'} |"
            f" {'' if a is None else f'{100 * a:+.1f} % ({n_alpha} mol.)'} |")
    write_text_atomic(OUT / "table.md", "\n".join(lines) + "\n")
    return summary


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--commit", action="store_true")
    p.add_argument("--table", action="store_true", help="only write the table")
    a = p.parse_args()
    if a.table:
        print(json.dumps(table(), indent=1))
    else:
        run(a.commit)
