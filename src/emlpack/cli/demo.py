"""``emlp demo``: the whole pipeline on data the package generates itself (< 15 min, 2 cores).

0. **Pretrained model first**: when the pretrained ``mini-eqm7`` ensemble is installed, the
   IR spectrum and polarizability of a molecule built from SMILES (seconds), through the same
   commands a user runs (``emlp ir mini-eqm7 --smiles ...``, ``emlp polarizability ...``).
1. **Label**: small molecules (H2O, NH3, CH4; ASE geometries) randomly displaced, each under a
   random homogeneous field, plus the four reference hydrides, labelled with the project's
   PySCF labeler at the ``quick`` preset (PBE0/6-31G*): energy, forces, Foster-Boys centres.
   Written to an HDF5 dataset store (``data.h5``), resumable: finished labels are kept.
2. **Train** a small eMLP for a few minutes (the paper's loss with live hydride references,
   split by configuration, best/last checkpoints; ``emlp train`` with ``demo_config.yaml``).
3. **Evaluate** on the held-out test configurations: static errors, pair relaxation (dynamic
   errors, error rate), parity plots (``emlp evaluate``).
4. **Use** the model through the ASE calculator: Born-Oppenheimer relaxed pairs and dipoles
   of the test configurations against DFT, and the harmonic IR spectrum of water
   (``emlp ir run/best.pt --smiles O``).
5. **Report**: ``report.md`` with the tables (one sentence each on what they measure), the
   dipoles, the parity plot and the IR plots; molecules are named by formula.

The command-line steps run ``emlp`` in a subprocess (:func:`run_command`), so the demo shows
exactly what a user types and the library does not import the CLI.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from ase.build import molecule

from emlpack._files import write_text_atomic

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

    from emlpack.structure import Structure

MOLECULES = ("H2O", "NH3", "CH4")
HYDRIDE_NAMES = ("H2", "CH4", "NH3", "H2O")
DEMO_LEVEL = "quick"
N_PER_MOLECULE = 12
TRAIN_MINUTES = 5.0
#: the pretrained model the demo starts with, and its molecule: aziridine, the paper's IR
#: example, in mini-eQM7's test split (the models never saw it)
PRETRAINED = "mini-eqm7"
PRETRAINED_SMILES = "C1CN1"
#: the demo molecule's DFT reference at the labels' level (in a clone of the repository)
PRETRAINED_REFERENCE = "datasets/mini-eqm7/references/pbe0_aug-cc-pvtz/qm7-0011.json"
ROOT = Path(__file__).resolve().parents[3]

#: runs an ``emlp`` command line (argv without ``emlp``) and returns its exit status
Command = Callable[[list[str]], int]


def run_command(argv: list[str]) -> int:
    """``emlp ARGV`` in a subprocess of this Python (its output shown as it comes)."""
    return subprocess.run([sys.executable, "-m", "emlpack.cli", *argv], check=False).returncode


def _label_one(task: tuple) -> tuple:
    """Worker: label one configuration (runs in a separate process, 1 thread)."""
    from emlpack.qm.pyscf_labeler import PySCFLabeler

    key, name, kind, numbers, positions, field = task
    labeler = PySCFLabeler(DEMO_LEVEL, seed=0, threads=1, boys_starts=2)
    result = labeler(numbers, positions, field=field)
    if not result.ok:
        return key, name, kind, None, result.error
    s = result.to_structure(source=key, info={"key": key, "molecule_id": name, "kind": kind})
    return key, name, kind, s, ""


def label_tasks(n_per_molecule: int = N_PER_MOLECULE, seed: int = 0) -> list[tuple]:
    """Displaced molecules (0.04 Å Gaussian noise) under random fields (V/Å), and hydrides."""
    from emlpack.qm.sampling import random_field

    rng = np.random.default_rng(seed)
    tasks = []
    for name in HYDRIDE_NAMES:
        a = molecule(name)
        tasks.append((f"hydride/{name}/0000", name, "hydride", a.numbers, a.positions,
                      np.zeros(3)))
    for name in MOLECULES:
        a = molecule(name)
        for k in range(n_per_molecule):
            pos = a.positions + rng.normal(scale=0.04, size=a.positions.shape)
            tasks.append((f"{name}/{k:04d}", name, "demo", a.numbers, pos, random_field(rng)))
    return tasks


def generate_labels(store_path: Path, n_per_molecule: int = N_PER_MOLECULE,
                    workers: int = 2) -> None:
    """Label every task not yet in the store (resumable), in ``workers`` processes."""
    from emlpack.data.store import DatasetStore
    from emlpack.progress import progress
    from emlpack.qm.executor import Executor

    with DatasetStore(store_path, "a") as store:
        done = store.done_keys()
        todo = [t for t in label_tasks(n_per_molecule) if t[0] not in done]
        if not todo:
            print("  all labels found from an earlier run: reused")
            return
        with Executor(workers) as executor:
            for task in todo:
                executor.submit(_label_one, task)
            results = (fut.result() for _, fut in executor.completed())
            bar = progress(results, total=len(todo), desc="  labeling", unit="conf")
            for key, name, kind, s, error in bar:
                if s is None:
                    store.add_failures([{"key": key, "molecule_id": name, "kind": kind,
                                         "reason": error}])
                    continue
                store.append(s)
                if kind == "hydride":
                    store.set_reference(name, s.energy, DEMO_LEVEL)


def demo_config(out: Path, minutes: float) -> dict:
    """The demo's training config: the data in ``out/data.h5`` (hydride reference, split by
    configuration), a small model with augmentation, at most ``minutes`` of training, output
    in ``out/run``."""
    from emlpack.train.config import load_config

    return load_config(None, [
        f"data.path={out / 'data.h5'}", "data.reference=hydrides",
        "data.split=configuration", "data.fractions=[0.67, 0.08, 0.25]",
        "model.short_range.n_features=48", "model.short_range.n_filters=32",
        "model.short_range.n_rbf=16", "model.short_range.n_interactions=2",
        "model.short_range.message_norm=10.0",
        "augmentation.enabled=true", "augmentation.probability=0.25",
        "training.batch_size=8", "training.lr=3.0e-3",
        "training.decay_epochs=300", "training.max_epochs=100000",
        f"training.max_time_minutes={minutes}", "training.threads=2",
        f"output.dir={out / 'run'}",
    ])


def dipole_table(model_path: Path, structures: Iterable[Structure]) -> list[dict]:
    """Born-Oppenheimer dipoles (ASE calculator, pairs relaxed) against DFT, in Debye."""
    from ase.calculators.calculator import CalculationFailed

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.io import structure_to_atoms
    from emlpack.units import E_A_IN_DEBYE

    rows = []
    for s in structures:
        atoms = structure_to_atoms(s)
        atoms.calc = EMLPCalculator(model_path)
        row = {"structure": s.source, "formula": atoms.get_chemical_formula(),
               "dft_dipole_D": float(np.linalg.norm(s.dipole()) * E_A_IN_DEBYE)}
        try:
            mu = atoms.get_dipole_moment()
            row["emlp_dipole_D"] = float(np.linalg.norm(mu) * E_A_IN_DEBYE)
            r = atoms.calc.relax_result
            row["relaxation"] = f"converged in {r.iterations} steps"
            row["max_pair_shift_A"] = float(np.linalg.norm(
                atoms.calc.results["electron_pairs"] - s.pairs, axis=1).max())
        except CalculationFailed as exc:
            row["emlp_dipole_D"] = float("nan")
            row["relaxation"] = f"failed: {exc}"
            row["max_pair_shift_A"] = float("nan")
        rows.append(row)
    return rows


def pretrained_step(out: Path, command: Command | None, smiles: str = PRETRAINED_SMILES,
                    name: str = PRETRAINED) -> dict:
    """IR spectrum and polarizability of ``smiles`` with the pretrained ``name`` through the
    command line, when that model is installed. Returns what the report shows: ``status``
    (``done``, ``failed`` or ``not installed``), the commands, the JSON results and files."""
    from emlpack.pretrained import KNOWN, available

    if command is None or name not in available():
        return {"status": "not installed", "name": name, "about": KNOWN.get(name, "")}
    folder = out / "pretrained"
    folder.mkdir(parents=True, exist_ok=True)
    ir_json, ir_png = folder / "ir.json", folder / "ir.png"
    pol_json = folder / "polarizability.json"
    commands = [["ir", name, "--smiles", smiles, "-o", str(ir_json), "--plot", str(ir_png),
                 "--quiet"],
                ["polarizability", name, "--smiles", smiles, "-o", str(pol_json), "--quiet"]]
    codes = [command(argv) for argv in commands]
    step = {"name": name, "smiles": smiles, "commands": [" ".join(["emlp", *c]) for c in commands],
            "status": "done" if codes == [0, 0] else "failed", "exit_codes": codes}
    if ir_json.exists():
        step["ir"] = json.loads(ir_json.read_text())
        step["ir_plot"] = str(ir_png.relative_to(out)) if ir_png.exists() else None
    if pol_json.exists():
        step["polarizability"] = json.loads(pol_json.read_text())
    return step


def ir_step(out: Path, model: Path, command: Command | None, smiles: str = "O") -> dict:
    """Harmonic IR spectrum of ``smiles`` with the demo's trained model (cores and pairs
    optimised first), through ``emlp ir``."""
    if command is None:
        return {"status": "skipped (no command runner)"}
    argv = ["ir", str(model), "--smiles", smiles, "-o", str(out / "ir_water.json"),
            "--plot", str(out / "ir_water.png"), "--quiet"]
    code = command(argv)
    step = {"command": " ".join(["emlp", *argv[:4], "-o ir_water.json --plot ir_water.png"]),
            "status": "done" if code == 0 else f"failed (exit {code})"}
    if (out / "ir_water.json").exists():
        step["ir"] = json.loads((out / "ir_water.json").read_text())
    return step


def _formula(numbers: np.ndarray | Sequence[int]) -> str:
    """Hill formula of the cores (e.g. ``H2O``)."""
    from ase.formula import Formula
    from ase.symbols import Symbols

    return Formula(str(Symbols(numbers))).format("hill")


def _pretrained_lines(step: dict) -> list[str]:
    lines = ["## 0. A pretrained model first", ""]
    if step["status"] == "not installed":
        return lines + [
            f"The pretrained ensemble `{step['name']}` ({step['about']}) is not installed with"
            " this copy of emlpack: its data set (`datasets/mini-eqm7/`) is still being"
            f" labeled. Once it ships, this step runs `emlp ir {step['name']} --smiles"
            f" {PRETRAINED_SMILES}` and `emlp polarizability {step['name']} --smiles"
            f" {PRETRAINED_SMILES}` (seconds, no training).", ""]
    lines += [f"`{step['name']}` on the molecule of SMILES `{step['smiles']}` (pairs guessed"
              " and relaxed, cores optimised for the IR spectrum):", "",
              *[f"    {c}" for c in step["commands"]], ""]
    if step["status"] != "done":
        lines += [f"**The commands failed** (exit codes {step['exit_codes']}).", ""]
    pol = step.get("polarizability")
    if pol:
        std = pol.get("polarizability_isotropic_bohr3_std")
        lines.append(f"Isotropic polarizability {pol['polarizability_isotropic_bohr3']:.2f}"
                     + (f" ± {std:.2f}" if std is not None else "") + " bohr³, dipole"
                     f" {pol['dipole_norm_debye']:.2f} D.")
    ir = step.get("ir") or {}
    if ir.get("frequencies_cm-1"):
        freqs = ir["frequencies_cm-1"]
        stds = ir.get("frequencies_cm-1_std") or [None] * len(freqs)
        lines.append("Harmonic frequencies (cm⁻¹, ensemble mean ± spread): " + ", ".join(
            f"{f:.0f}" + (f" ± {d:.0f}" if d is not None else "")
            for f, d in zip(freqs, stds, strict=False)) + ".")
    if step["smiles"] == PRETRAINED_SMILES:
        lines += _against_dft(pol or {}, ir, ROOT / PRETRAINED_REFERENCE)
    for w in dict.fromkeys((pol or {}).get("warnings", []) + ir.get("warnings", [])):
        lines.append(f"- warning: {w}")
    if step.get("ir_plot"):
        lines += ["", f"![IR spectrum, pretrained ensemble]({step['ir_plot']})"]
    return lines + [""]


def _against_dft(pol: dict, ir: dict, reference: Path) -> list[str]:
    """The demo molecule's DFT values beside the ensemble's (none when the reference file is
    absent, e.g. an installed package without the repository's data)."""
    if not reference.exists():
        return []
    from emlpack.units import E_A_IN_DEBYE

    ref = json.loads(reference.read_text())
    parts, ratio = [], None
    if pol.get("polarizability_isotropic_bohr3") and ref.get("polarizability_isotropic_bohr3"):
        ratio = pol["polarizability_isotropic_bohr3"] / ref["polarizability_isotropic_bohr3"]
        parts.append(f"isotropic polarizability {ref['polarizability_isotropic_bohr3']:.2f}"
                     f" bohr³ (the ensemble's is {ratio:.2f}x that)")
    if ref.get("dipole_e_A") is not None:
        parts.append(f"dipole {np.linalg.norm(ref['dipole_e_A']) * E_A_IN_DEBYE:.2f} D")
    ours, theirs = ir.get("frequencies_cm-1") or [], ref.get("frequencies_cm-1") or []
    if theirs and len(ours) == len(theirs):
        mae = float(np.mean(np.abs(np.sort(ours) - np.sort(theirs))))
        parts.append(f"harmonic frequencies {', '.join(f'{f:.0f}' for f in theirs)} cm⁻¹ (the"
                     f" ensemble's differ by {mae:.0f} cm⁻¹ on average)")
    if not parts:
        return []
    lines = [f"DFT (PBE0/aug-cc-pVTZ, `{PRETRAINED_REFERENCE}`): " + "; ".join(parts) + "."]
    if ratio is not None and not 0.8 < ratio < 1.2:
        lines.append("The polarizability is off by more than 20 %: its electron pairs are too"
                     " soft, see 'The mini-eqm7 ensemble' in docs/pretrained.md.")
    return lines


def write_report(out: Path, times: dict, table: str, dipoles: list[dict],
                 calc_rows: list[dict], cfg: dict, n_data: int,
                 pretrained: dict | None = None, ir: dict | None = None,
                 names: dict[str, tuple[str, str]] | None = None) -> Path:
    """``report.md``; ``names`` maps a structure's source to ``(key, formula)``."""
    from emlpack.nn.potential import nest_flat_keys

    sr = nest_flat_keys(cfg["model"])["short_range"]  # (a config of either spelling)
    lines = [
        "# emlpack demo report", "",
        *_pretrained_lines(pretrained or {"status": "not installed", "name": PRETRAINED,
                                          "about": ""}),
        "## 1-4. Label, train, evaluate and use a small model", "",
        f"Data: {n_data} configurations of {', '.join(MOLECULES)} under random fields, plus"
        f" the hydrides {', '.join(HYDRIDE_NAMES)}, labelled with PySCF at the"
        f" '{DEMO_LEVEL}' preset (PBE0/6-31G*) with Foster-Boys centres -> `data.h5`.",
        f"Model: SchNet F={sr['n_features']}, G={sr['n_filters']},"
        f" N={sr['n_rbf']}, T={sr['n_interactions']}, trained"
        f" {cfg['training']['max_time_minutes']} min (split by configuration"
        f" {cfg['data']['fractions']}, live hydride references) -> `run/best.pt`.", "",
        "| step | wall time [s] |", "|---|---|",
        *[f"| {k} | {v:.0f} |" for k, v in times.items()], "",
        "How to read the tables: *static errors* compare the model's energy and forces with DFT"
        " at the DFT geometry with the electron pairs on the DFT Foster-Boys centres (how well"
        " the network fits the labels); *dynamic errors* first relax the pairs to the model's"
        " own minimum, as every prediction does, and compare there (what a user gets), with the"
        " error rate counting relaxations that fail; the *intrinsic variability* is the error"
        " of the best constant guess, the scale an error should be far below.", "",
        table.replace("## ", "## Test set: ", 1), "",
        "![parity plots](evaluation/parity.png)", "",
        "## Dipoles of the test configurations at relaxed pairs vs DFT", "",
        "Each test configuration's dipole with the pairs relaxed by the model, against the"
        " dipole of the DFT Boys centres; the pair shift is how far the model moved a pair"
        " from its DFT centre.", "",
        "| configuration | formula | DFT [D] | eMLP [D] | max pair shift [Å] | relaxation |",
        "|---|---|---|---|---|---|",
    ]
    names = names or {}
    for r in dipoles:
        key, formula = names.get(r["structure"], (r["structure"], ""))
        lines.append(f"| {key} | {formula} | {r['dft_dipole_D']:.3f} |"
                     f" {r['emlp_dipole_D']:.3f} | {r['max_pair_shift']:.3f} |"
                     f" {r['failure'] or 'ok'} |")
    lines += ["", "## The same through the ASE calculator (one configuration per molecule)", "",
              "| configuration | formula | DFT [D] | eMLP [D] | max pair shift [Å] | relaxation |",
              "|---|---|---|---|---|---|"]
    for r in calc_rows:
        key = names.get(r["structure"], (r["structure"], ""))[0]
        lines.append(f"| {key} | {r['formula']} | {r['dft_dipole_D']:.3f} |"
                     f" {r['emlp_dipole_D']:.3f} | {r['max_pair_shift_A']:.3f} |"
                     f" {r['relaxation']} |")
    if ir:
        lines += ["", "## Harmonic IR spectrum of water with the demo model", "",
                  f"`{ir.get('command', '')}`: {ir['status']}."]
        freqs = ir.get("ir", {}).get("frequencies_cm-1")
        if freqs:
            lines.append("Wavenumbers " + ", ".join(f"{f:.0f}" for f in freqs)
                         + " cm⁻¹ (PBE0 water: about 1600, 3800, 3900 cm⁻¹ harmonic).")
        for w in ir.get("ir", {}).get("warnings", []):
            lines.append(f"- warning: {w}")
        if (out / "ir_water.png").exists():
            lines += ["", "![IR spectrum of water, demo model](ir_water.png)"]
    lines += ["", "A demo-sized model on a few dozen configurations: the numbers show the"
              " pipeline and its trends, not the paper's accuracy."]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def run_demo(output: str | Path = "demo_output", minutes: float = TRAIN_MINUTES,
             n_per_molecule: int = N_PER_MOLECULE, command: Command | None = run_command) -> int:
    """Run the pipeline, writing data, run, evaluation and ``report.md`` under ``output``.
    ``command`` runs ``emlp`` command lines (default :func:`run_command`); ``None`` skips the
    pretrained and IR steps."""
    from emlpack.data.dataset import load_data
    from emlpack.optional import import_optional
    from emlpack.train.evaluate import evaluate_models, select_structures
    from emlpack.train.trainer import train

    for module in ("pyscf", "dask", "distributed"):  # before any step: the demo labels with DFT
        import_optional(module, "emlp demo (it labels its training data with DFT)",
                        alternative=f"the pretrained model alone: emlp ir {PRETRAINED} --smiles"
                        f" {PRETRAINED_SMILES}")
    out = Path(output).resolve()
    out.mkdir(parents=True, exist_ok=True)
    times = {}
    t0 = time.monotonic()
    print(f"[0/4] pretrained model {PRETRAINED}: IR spectrum and polarizability of"
          f" {PRETRAINED_SMILES} from SMILES")
    pretrained = pretrained_step(out, command)
    if pretrained["status"] == "not installed":
        print(f"  {PRETRAINED} is not installed with this copy of emlpack (its data set is still"
              " being labeled): skipped")
    times["pretrained model"] = time.monotonic() - t0

    t0 = time.monotonic()
    print(f"[1/4] DFT labels ({DEMO_LEVEL}: PBE0/6-31G*, Foster-Boys) -> {out / 'data.h5'}")
    generate_labels(out / "data.h5", n_per_molecule)
    times["labeling"] = time.monotonic() - t0

    t0 = time.monotonic()
    cfg = demo_config(out, minutes)
    print(f"[2/4] training a small eMLP for up to {minutes} min -> {out / 'run'}")
    best = train(cfg)
    times["training"] = time.monotonic() - t0

    t0 = time.monotonic()
    print("[3/4] evaluation on the held-out test configurations (static, relaxed pairs)")
    table, results = evaluate_models([best], out / "data.h5", out / "evaluation",
                                     subset="test", progress=True)
    print(table)
    times["evaluation"] = time.monotonic() - t0

    t0 = time.monotonic()
    print("[4/4] ASE calculator (pairs relaxed on every call): one test configuration per"
          " molecule")
    from emlpack.nn.checkpoint import read_checkpoint

    structures, _ = load_data(out / "data.h5")
    meta = read_checkpoint(best)["metadata"]
    test = select_structures(structures, meta, out / "data.h5", "test")
    first = {}
    for s in test:
        first.setdefault(s.info.get("molecule_id"), s)
    calc_rows = dipole_table(best, list(first.values()))
    for r in calc_rows:
        print(f"  {r['formula']:>4}: DFT {r['dft_dipole_D']:.3f} D, eMLP {r['emlp_dipole_D']:.3f}"
              f" D ({r['relaxation']})")
    ir = ir_step(out, best, command)
    print(f"  IR spectrum of water with the demo model: {ir['status']}")
    times["calculator and IR"] = time.monotonic() - t0
    dipoles = results["models"][0]["dynamic"]["structures"]
    names = {s.source: (s.info.get("key", s.source), _formula(s.numbers)) for s in test}
    report = write_report(out, times, table, dipoles, calc_rows, cfg, len(structures),
                          pretrained, ir, names)
    print(f"wrote {report} (total {sum(times.values()) / 60:.1f} min)")
    return 0
