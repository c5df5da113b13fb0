"""Smoke test of an installed emlpack wheel without extras (run by ``.ci/wheel_check.sh``).

Run with the Python of a fresh virtual environment that holds only CPU torch and the wheel:
``python .ci/wheel_smoke.py WORK_DIR [--shared DIR]``. Every command of ``emlp --help`` either
works on a small input (exit 0 and its output checked) or, where it needs an extra, exits 2
with one line that names the extra (``pip install 'emlpack[qm]'``); a command of the parser
that no check covers fails the run. Also the calculator and the pretrained model from Python.
Results (one row per check, with its wall time) go to ``WORK_DIR/wheel_smoke.json``; exit 1
when a check failed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

#: the optional packages; none may be importable here, or the check proves nothing
OPTIONAL = ("pyscf", "dask", "distributed", "tblite", "spglib", "tensorboard")
#: water cores (Å), no electron pairs: the base install guesses them (Lewis structure)
WATER = [("O", 0.0, 0.0, 0.119), ("H", 0.0, 0.763, -0.477), ("H", 0.0, -0.763, -0.477)]
#: the same with its four valence pairs, in a periodic cell (a small "crystal")
PAIRS = [("Es", 0.0, 0.28, -0.05), ("Es", 0.0, -0.28, -0.05), ("Es", 0.28, 0.0, 0.30),
         ("Es", -0.28, 0.0, 0.30)]
CRYSTAL = 'Lattice="4.5 0 0 0.5 4.6 0 -0.3 0.4 4.8" Properties=species:S:1:pos:R:3 pbc="T T T"'
MOLECULE = 'Properties=species:S:1:pos:R:3 pbc="F F F"'
#: a SMILES list for `campaign init` (QM7's first rows are reserved, as in the real list)
SMILES = ["C", "O", "N", "CC", "CO", "CN", "C=O", "OO", "NN", "CCO", "CC=O", "OCCO", "NCCO",
          "CC(C)O"]


def write_xyz(path: Path, rows: list[tuple], comment: str = MOLECULE) -> Path:
    """An extxyz file of ``rows`` (symbol, x, y, z in Å)."""
    lines = [str(len(rows)), comment, *(f"{s} {x:.6f} {y:.6f} {z:.6f}" for s, x, y, z in rows)]
    path.write_text("\n".join(lines) + "\n")
    return path


class Smoke:
    """Runs the checks in ``work`` and records one row per check."""

    def __init__(self, work: Path, shared: Path | None) -> None:
        self.work = work
        self.shared = shared
        self.emlp = str(Path(sys.executable).with_name("emlp"))
        self.rows: list[dict] = []
        self.covered: set[str] = set()

    # ------------------------------------------------------------------ running
    def run(self, argv: list[str], timeout: float = 600) -> tuple[int, str, str, float]:
        """``emlp ARGV`` in ``work``: (exit status, stdout, stderr, seconds)."""
        t0 = time.perf_counter()
        env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
        p = subprocess.run([self.emlp, *argv], cwd=self.work, capture_output=True, text=True,
                           timeout=timeout, env=env)
        return p.returncode, p.stdout, p.stderr, time.perf_counter() - t0

    def record(self, name: str, ok: bool, seconds: float, detail: str = "") -> bool:
        """Record and print one check."""
        self.rows.append({"check": name, "ok": ok, "seconds": round(seconds, 2),
                          "detail": detail})
        print(f"{'ok  ' if ok else 'FAIL'} {seconds:6.1f} s  {name}" + (
            f"\n       {detail}" if detail and not ok else ""), flush=True)
        return ok

    def works(self, argv: list[str], check: Callable[[str], str | None] | None = None) -> bool:
        """``emlp ARGV`` must exit 0; ``check(stdout)`` returns a problem or None."""
        self.covered.add(argv[0])
        rc, out, err, dt = self.run(argv)
        problem = None
        if rc != 0:
            problem = f"exit {rc}: {(err or out).strip()[-800:]}"
        elif "Traceback" in err:
            problem = f"a traceback on stderr: {err.strip()[-800:]}"
        elif check is not None:
            try:
                problem = check(out)
            except Exception as exc:  # noqa: BLE001 - a failed check, reported
                problem = f"{type(exc).__name__}: {exc}"
        return self.record("emlp " + " ".join(argv), problem is None, dt, problem or "")

    def needs(self, argv: list[str], extra: str, absent: Path | None = None) -> bool:
        """``emlp ARGV`` must exit 2 with one stderr line naming ``pip install 'emlpack[extra]'``
        and, when given, leave ``absent`` unwritten."""
        self.covered.add(argv[0])
        rc, out, err, dt = self.run(argv)
        lines = err.strip().splitlines()
        hint = f"pip install 'emlpack[{extra}]'"
        problem = None
        if rc != 2:
            problem = f"exit {rc}, not 2: {(err or out).strip()[-800:]}"
        elif len(lines) != 1 or not lines[0].startswith(f"emlp {argv[0]}: error: "):
            problem = f"not one error line: {err.strip()[-800:]}"
        elif hint not in lines[0]:
            problem = f"does not name {hint}: {lines[0]}"
        elif absent is not None and absent.exists():
            problem = f"wrote {absent} before refusing"
        return self.record(f"emlp {' '.join(argv)}  -> needs [{extra}]", problem is None, dt,
                           problem or lines[0])

    def python(self, name: str, fn: Callable[[], str | None]) -> bool:
        """A check in this process: ``fn()`` returns a problem or None."""
        t0 = time.perf_counter()
        try:
            problem = fn()
        except Exception:  # noqa: BLE001 - a failed check, reported
            problem = traceback.format_exc(limit=4).strip()
        return self.record(name, problem is None, time.perf_counter() - t0, problem or "")

    # ------------------------------------------------------------------ checks
    def installed(self) -> str | None:
        """The package is the wheel (not the source tree), bare, with the pretrained model."""
        import emlpack
        from emlpack.pretrained import available, resolve_model

        where = Path(emlpack.__file__).resolve()
        if "site-packages" not in where.parts:
            return f"emlpack imported from {where}, not from the installed wheel"
        present = [m for m in OPTIONAL if _importable(m)]
        if present:
            return f"not a bare install: {present} importable"
        if "mini-eqm7" not in available():
            return f"the pretrained mini-eqm7 is not in the wheel (available: {available()})"
        files, _ = resolve_model("mini-eqm7")
        if len(files) < 2 or not all(f.is_file() and where.parent in f.parents for f in files):
            return f"pretrained files not inside the installed package: {files}"
        return None

    def calculator(self) -> str | None:
        """EMLPCalculator("mini-eqm7") on water: forces are minus the energy gradient (central
        difference of the Born-Oppenheimer energy, pairs relaxed at each point), a dipole."""
        import numpy as np
        from ase.build import molecule

        from emlpack import EMLPCalculator

        atoms = molecule("H2O")
        atoms.calc = EMLPCalculator("mini-eqm7")
        forces = atoms.get_forces()
        dipole = atoms.get_dipole_moment()
        h, (i, k) = 1e-3, (1, 2)
        e = []
        for sign in (1, -1):
            a = atoms.copy()
            a.calc = EMLPCalculator("mini-eqm7")
            a.positions[i, k] += sign * h
            e.append(a.get_potential_energy())
        fd = -(e[0] - e[1]) / (2 * h)
        if not np.isfinite(forces).all() or forces.shape != (3, 3):
            return f"forces {forces}"
        if abs(fd - forces[i, k]) > 1e-3 + 1e-3 * abs(fd):
            return f"force {forces[i, k]:.6f} eV/Å, finite difference {fd:.6f}"
        if not 0.05 < np.linalg.norm(dipole) < 2.0:
            return f"water dipole {dipole} e·Å"
        return None

    def training_data(self) -> str | None:
        """Eight displaced waters labelled with the pretrained ensemble (relaxed pairs) for
        ``emlp train``/``evaluate``; written in the native extxyz convention."""
        import numpy as np
        from ase.build import molecule

        from emlpack import EMLPCalculator
        from emlpack.io import atoms_to_structure, write_structures

        rng = np.random.default_rng(0)
        calc = EMLPCalculator("mini-eqm7")
        frames = []
        for k in range(8):
            atoms = molecule("H2O")
            atoms.positions += rng.normal(scale=0.03, size=atoms.positions.shape)
            atoms.calc = calc
            energy = atoms.get_potential_energy()
            pairs = calc.results["electron_pairs"]
            s = atoms_to_structure(atoms, pairs=pairs, source=f"water {k}")
            frames.append(s.copy(energy=energy, forces=atoms.get_forces(),
                                 pair_forces=np.zeros_like(pairs),
                                 info={"molecule_id": "water"}))
        write_structures(self.work / "train.xyz", frames)
        return None

    def main(self) -> int:
        """Every check; 0 when all pass."""
        w = self.work
        water = write_xyz(w / "water.xyz", WATER)
        ice = write_xyz(w / "ice.xyz", WATER + PAIRS, CRYSTAL)
        labelled = write_xyz(w / "labelled.xyz", WATER + PAIRS,
                             MOLECULE.replace("pbc=", "energy=0.0 pbc="))
        smiles = w / "smiles.csv"
        smiles.write_text("smiles\n" + "\n".join(SMILES) + "\n")
        if not self.python("installed: the wheel, bare, with mini-eqm7", self.installed):
            return 1
        from emlpack.cli import build_parser
        from emlpack.pretrained import resolve_model

        member = str(resolve_model("mini-eqm7")[0][0])  # md takes one model
        sub = next(a for a in build_parser()._actions if a.dest == "command")
        commands = sorted(sub.choices)

        # the commands a user of the pretrained models runs: they work
        self.works(["--version"], lambda out: None if out.startswith("emlpack ") else out)
        self.works(["--help"], lambda out: next(
            (f"{c} missing from --help" for c in commands if c not in out), None))
        self.works(["pretrained"], lambda out: None if "mini-eqm7 (installed)" in out else out)
        self.works(["pretrained", "mini-eqm7"])
        self.works(["ir", "mini-eqm7", str(water), "-o", "ir.json", "--plot", "ir.png",
                    "--quiet"], lambda out: _json_check(
                        w / "ir.json", lambda d: len(d["frequencies_cm-1"]) == 3))
        self.works(["ir", "mini-eqm7", "--smiles", "O", "-o", "ir_smiles.json", "--quiet"],
                   lambda out: _json_check(w / "ir_smiles.json",
                                           lambda d: len(d["frequencies_cm-1"]) == 3))
        self.works(["raman", "mini-eqm7", "--smiles", "C1CN1", "-o", "raman.json", "--plot",
                    "raman.png", "--quiet"], lambda out: _json_check(
                        w / "raman.json", lambda d: len(d["activities_A4_per_amu"]) == 18
                        and (w / "raman.png").exists()))
        self.works(["polarizability", "mini-eqm7", str(water), "-o", "pol.json", "--quiet"],
                   lambda out: _json_check(w / "pol.json", lambda d: len(d) > 3))
        self.works(["optimize", "mini-eqm7", str(water), "-o", "opt.xyz", "--quiet"],
                   lambda out: None if (w / "opt.xyz").exists() else "no opt.xyz")
        self.works(["response", "mini-eqm7", str(ice), "--relax", "none", "-o", "resp.json",
                    "--quiet"], lambda out: _json_check(
                        w / "resp.json", lambda d: len(d["stiffness_voigt_GPa"]) == 6))
        self.works(["md", member, str(water), "--steps", "10", "--dt", "0.25", "--nve",
                    "--temperature", "100", "-o", "md", "--quiet"])
        self.works(["md-analysis", "md/trajectory.xyz", "--discard", "0", "-o", "stab.json"])
        self.works(["md-ir", "md/trajectory.xyz", "-o", "md_ir.json"])
        self.python("EMLPCalculator('mini-eqm7'): forces = -dE/dx, dipole", self.calculator)
        self.python("training data labelled with the pretrained ensemble", self.training_data)
        cfg = w / "train.yaml"
        cfg.write_text(json.dumps({  # JSON is YAML
            "data": {"path": "train.xyz", "reference": "constant", "split": "configuration",
                     "fractions": [0.75, 0.25, 0.0]},
            "model": {"n_features": 8, "n_filters": 8, "n_rbf": 8, "n_interactions": 1},
            "training": {"batch_size": 4, "max_epochs": 2, "threads": 1},
            "output": {"dir": "run", "progress": False}}))
        self.works(["train", str(cfg)],
                   lambda out: None if (w / "run" / "best.pt").exists() else "no best.pt")
        self.works(["evaluate", "run/best.pt", "train.xyz", "--subset", "all", "-o", "ev",
                    "--quiet"], lambda out: None if (w / "ev" / "evaluation.json").exists()
                   else "no evaluation.json")
        self.works(["campaign", "init", "ds", "--smiles", str(smiles), "--n-large", "0"],
                   lambda out: None if "molecules listed" in out else out)
        self.works(["campaign", "card", "ds"])
        prefix = self.shared / "fixtures/reference_tf/tf_checkpoint_small/small" if (
            self.shared) else None
        if prefix is not None and prefix.with_suffix(".index").exists():
            self.works(["convert-reference", str(prefix), "-o", "reference.pt"],
                       lambda out: None if (w / "reference.pt").exists() else out)
        elif os.environ.get("CI", "").lower() == "true":
            self.record("emlp convert-reference (fixture in ../shared)", False, 0.0,
                        f"no reference checkpoint at {prefix}")
        else:
            self.covered.add("convert-reference")
            self.record("emlp convert-reference: skipped, no ../shared fixture", True, 0.0)

        # the commands that need an extra: one line naming it, nothing written
        self.needs(["label", str(water), "-o", "label.h5", "--workers", "0", "--quiet"], "qm",
                   absent=w / "label.h5")
        self.needs(["label", str(smiles), "-o", "label2.h5", "--quiet"], "qm",
                   absent=w / "label2.h5")
        self.needs(["relabel", str(labelled), "-o", "relabel.xyz", "--quiet"], "qm",
                   absent=w / "relabel.xyz")
        self.needs(["campaign", "run", "ds", "--workers", "0", "--quiet"], "qm")
        self.needs(["demo", "-o", "demo"], "qm", absent=w / "demo")
        self.needs(["ir", "mini-eqm7", str(water), "--guess", "boys", "-o", "boys.json",
                    "--quiet"], "qm", absent=w / "boys.json")
        self.needs(["train", str(cfg), "output.tensorboard=true", "output.dir=run_tb"],
                   "tensorboard", absent=w / "run_tb")
        self.python("optimize_crystal(symprec=0.01) names [periodic]", self.needs_spglib)

        missing = sorted(set(commands) - self.covered)
        self.record("every command of emlp --help is checked", not missing, 0.0,
                    f"not checked: {missing}")
        failed = [r for r in self.rows if not r["ok"]]
        total = sum(r["seconds"] for r in self.rows)
        (w / "wheel_smoke.json").write_text(json.dumps(
            {"checks": self.rows, "failed": len(failed), "seconds": round(total, 1)}, indent=1))
        print(f"{len(self.rows) - len(failed)}/{len(self.rows)} checks passed in {total:.0f} s")
        return 1 if failed else 0

    def needs_spglib(self) -> str | None:
        """The documented crystal optimisation refuses in one line naming its extra."""
        from emlpack.calculators.labeler import ModelLabeler
        from emlpack.errors import MissingDependencyError
        from emlpack.io import read_structures
        from emlpack.nn.checkpoint import load_model
        from emlpack.pretrained import resolve_model
        from emlpack.qm.crystal_optimize import optimize_crystal

        s = read_structures(self.work / "ice.xyz")[0]
        labeler = ModelLabeler(load_model(resolve_model("mini-eqm7")[0][0]))
        try:
            optimize_crystal(labeler, s, max_steps=1, symprec=0.01, log=lambda m: None)
        except MissingDependencyError as exc:
            text = str(exc)
            ok = "pip install 'emlpack[periodic]'" in text and "\n" not in text
            return None if ok else text
        return "optimize_crystal(symprec=0.01) ran without spglib"


def _importable(module: str) -> bool:
    import importlib

    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def _json_check(path: Path, test: Callable[[dict], bool]) -> str | None:
    if not path.exists():
        return f"{path} not written"
    data = json.loads(path.read_text())
    return None if test(data) else f"{path}: unexpected content {str(data)[:300]}"


def main() -> int:
    """Parse the arguments and run the checks."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("work", type=Path, help="an empty folder for the inputs and outputs")
    p.add_argument("--shared", type=Path, help="the ../shared folder (reference fixtures)")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    return Smoke(args.work.resolve(), args.shared).main()


if __name__ == "__main__":
    sys.exit(main())
