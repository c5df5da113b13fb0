"""DFT polarizability labels for a subset of mini-eQM7's training configurations (issue 51,
item 2a: the labels of the loss's ``polarizability`` term, ``loss.polarizability``).

    OMP_NUM_THREADS=1 python examples/eqm7/polarizability_labels.py [--count 300] [--commit]
    python examples/eqm7/polarizability_labels.py --estimate        the selection's CPU hours
    python examples/eqm7/polarizability_labels.py --smoke           one configuration, small
                                                                    basis, temporary folder

Per configuration: the record's own geometry and field (cores as stored, the field ``F0`` of
its labels), at the paper's level (PBE0/aug-cc-pVTZ + DF, :data:`emlpack.qm.levels.PAPER`, the
level of mini-eQM7): the polarizability from six central finite fields ``F0 ± h e_a`` with
``h = 1e-3`` au (:func:`emlpack.qm.finite_field.finite_field_response`, as the validation
references of ``validation_references.py``), with the nuclei clamped. Each field's dipole is
a small file ``OUT/fields/STEM/field_{x,y,z}{+,-}.npz`` and the result ``OUT/STEM.json``
(``STEM``: the record key with ``/`` as ``__``, :func:`emlpack.data.shards.label_file_name`),
each written atomically (temporary file, then rename) and never recomputed: the run resumes
where it stopped, on any machine, from the committed files. ``read_shards`` attaches
``OUT = datasets/mini-eqm7/polarizability`` to its configurations.

Selection (:func:`select_configurations`): training-split molecules of ``molecules.csv`` only,
never a validation or test molecule, the IR molecules (aziridine, 3-(methylamino)but-2-enal)
nor QM7 rows 0-9 (rows 5, 6, 8, 9 reserved), compared by molecular graph
(:func:`emlpack.qm.campaign.graph_key`); configurations in a seeded order by a hash of their
key, one per molecule before a second of any (so a prefix spreads over the molecules and does
not change when shards are added).

Cost: ``--estimate`` fits the paper-level finite-field CPU seconds of
``examples/qm7_cheap/level_choice/paper/*-alpha.json`` (the same six SCFs at the prepared
optima, one thread) as ``a n_heavy^b`` and sums it over the selection (heavy atoms of the
configuration, a dimer's probe included).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from emlpack._files import write_text_atomic
from emlpack.commits import git_commit
from emlpack.data.shards import (
    POLARIZABILITY_DIR,
    label_file_name,
    read_molecule_table,
    read_shards,
)
from emlpack.qm.campaign import excluded_graphs, graph_key
from emlpack.qm.finite_field import finite_field_response
from emlpack.qm.levels import PAPER, parse_level
from emlpack.qm.pyscf_labeler import PySCFLabeler
from emlpack.structure import Structure

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "datasets" / "mini-eqm7"
QM7_SMILES = ROOT.parent / "shared" / "data" / "qm7_smiles.csv"
LEVEL_CHOICE = ROOT / "examples" / "qm7_cheap" / "level_choice" / "paper"
FIELD_AU = 1e-3
SMOKE_LEVEL = "pbe0/6-31g*"


def banned_graphs(data: Path = DATA, smiles_csv: Path = QM7_SMILES) -> dict[str, str]:
    """Molecular graphs never labelled here, with the reason: the validation and test
    molecules of ``data``, the IR molecules and QM7 rows 0-9 (:func:`excluded_graphs`)."""
    return excluded_graphs(data, smiles_csv)


def _rank(key: str, seed: int) -> str:
    return hashlib.sha256(f"{seed}:{key}".encode()).hexdigest()


def select_configurations(structures: list[Structure], molecules: list[dict],
                          banned: dict[str, str], count: int, seed: int = 0
                          ) -> list[Structure]:
    """The first ``count`` labelable configurations of ``structures`` (module docstring):
    training-split molecules whose graph is not in ``banned``, ordered by (their rank within
    their molecule, the hash of their key)."""
    split = {m["name"]: m["split"] for m in molecules}
    smiles = {m["name"]: m["smiles"] for m in molecules}
    allowed: dict[str, bool] = {}
    by_molecule: dict[str, list[tuple[str, Structure]]] = {}
    for s in structures:
        name = str(s.info.get("molecule_id", ""))
        if name not in allowed:
            allowed[name] = split.get(name) == "train" and graph_key(smiles[name]) not in banned
        if allowed[name]:
            by_molecule.setdefault(name, []).append((_rank(str(s.info["key"]), seed), s))
    ordered = []
    for items in by_molecule.values():
        for rank, (h, s) in enumerate(sorted(items, key=lambda item: item[0])):
            ordered.append((rank, h, s))
    ordered.sort(key=lambda item: item[:2])
    return [s for _, _, s in ordered[:count]]


def label(s: Structure, out: Path, level: str | None = None) -> dict:
    """The label of configuration ``s`` (its per-field files cached under OUT/fields/)."""
    lev = PAPER if level is None else parse_level(level)
    stem = label_file_name(str(s.info["key"]))[: -len(".json")]
    t0 = time.process_time()
    resp = finite_field_response(
        PySCFLabeler(lev, boys_starts=1, threads=1, reuse_density=True), s.numbers,
        s.positions, FIELD_AU, cache=out / "fields" / stem, charge=s.charge, base_field=s.field)
    alpha = resp.polarizability
    return {"key": s.info["key"], "molecule_id": s.info.get("molecule_id", ""),
            "kind": s.info.get("kind", ""), "level": lev.name,
            "method": "central finite fields F0 +- h e_a at clamped nuclei (F0: the"
                      " configuration's field)",
            "field_step_au": FIELD_AU, "base_field_V_per_A": s.field.tolist(),
            "charge": s.charge, "numbers": s.numbers.tolist(),
            "positions": s.positions.tolist(),
            "polarizability_e_A2_per_V": alpha.tolist(),
            "polarizability_bohr3": resp.polarizability_bohr3.tolist(),
            "polarizability_isotropic_bohr3": float(np.trace(resp.polarizability_bohr3) / 3),
            "cpu_s_this_call": time.process_time() - t0}


def cost_model(folder: Path = LEVEL_CHOICE) -> tuple[float, float]:
    """``(a, b)`` of CPU seconds ``a n_heavy^b`` fitted to the paper-level finite-field runs."""
    rows = [json.loads(p.read_text()) for p in sorted(folder.glob("*-alpha.json"))]
    n = np.log([r["n_heavy"] for r in rows if r.get("ok")])
    cpu = np.log([r["cpu_s"] for r in rows if r.get("ok")])
    b, log_a = np.polyfit(n, cpu, 1)
    return float(np.exp(log_a)), float(b)


def heavy_atoms(s: Structure) -> int:
    """Heavy atoms of a configuration (a dimer's probe included)."""
    return int(np.sum(s.numbers > 1))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--out", type=Path, default=None,
                   help=f"label folder (default DATA/{POLARIZABILITY_DIR})")
    p.add_argument("--count", type=int, default=300, help="configurations to label")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--smiles", type=Path, default=QM7_SMILES, help="QM7 SMILES (rows 0-9)")
    p.add_argument("--level", default=None, help="another level (tests only; default paper)")
    p.add_argument("--estimate", action="store_true", help="print the CPU hours and stop")
    p.add_argument("--smoke", action="store_true",
                   help=f"one configuration at {SMOKE_LEVEL} in a temporary folder")
    p.add_argument("--commit", action="store_true", help="git-commit finished files")
    args = p.parse_args(argv)
    data = read_shards(args.data)
    chosen = select_configurations(data.structures, read_molecule_table(args.data),
                                   banned_graphs(args.data, args.smiles), args.count, args.seed)
    out = args.out or args.data / POLARIZABILITY_DIR
    if args.estimate:
        a, b = cost_model()
        todo = [s for s in chosen if not (out / label_file_name(s.info["key"])).exists()]
        hours = sum(a * heavy_atoms(s) ** b for s in todo) / 3600
        print(f"{len(chosen)} configurations of {len({s.info['molecule_id'] for s in chosen})}"
              f" molecules selected, {len(todo)} to label: about {hours:.1f} CPU hours at the"
              f" paper's level (one thread; {a:.3g} s x n_heavy^{b:.2f} per configuration)")
        return 0
    if args.smoke:
        with tempfile.TemporaryDirectory() as tmp:
            res = label(chosen[0], Path(tmp), args.level or SMOKE_LEVEL)
        print(f"{res['key']} ({heavy_atoms(chosen[0])} heavy atoms) at {res['level']}:"
              f" {res['cpu_s_this_call']:.1f} CPU s, isotropic"
              f" {res['polarizability_isotropic_bohr3']:.2f} bohr³")
        return 0
    last = time.monotonic()
    for s in chosen:
        path = out / label_file_name(s.info["key"])
        if path.exists():
            continue
        res = label(s, out, args.level)
        write_text_atomic(path, json.dumps(res, indent=1))
        print(time.strftime("%H:%M:%S"), res["key"],
              f"alpha_iso {res['polarizability_isotropic_bohr3']:.2f} bohr³,"
              f" {res['cpu_s_this_call']:.0f} s", flush=True)
        if args.commit and time.monotonic() - last > 25 * 60:
            git_commit([out], "mini-eqm7 polarizability labels: finished files")
            last = time.monotonic()
    if args.commit:
        git_commit([out], f"mini-eqm7 polarizability labels: {len(chosen)} configurations")
    return 0


if __name__ == "__main__":
    sys.exit(main())
