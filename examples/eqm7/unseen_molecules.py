"""A model's errors on the molecules of a data set that its training data did not hold.

    python examples/eqm7/unseen_molecules.py MODEL TRAINED_ON [DATA] [--json OUT.json]

The campaign keeps labeling after a model's data snapshot, so the training-split molecules
labeled since are molecules the model never saw (neither trained nor validated on): a larger
sample of unseen chemistry than the card's test split. MODEL is a checkpoint of
``emlp train``; TRAINED_ON the data-set folder it was trained on (a shard prefix, e.g. the
learning curve's ``runs/eqm7-lc/data/shards-79``); DATA the grown folder (default
``datasets/mini-eqm7``). The unseen configurations are DATA's train and validation
configurations whose molecule is absent from TRAINED_ON (test molecules are left to the
study). Static and dynamic errors as in Tables 2 and 3 (``emlpack.train.evaluate.evaluate``;
eV, Å, Debye), with the intrinsic variability, and the static errors by molecule size (heavy
atoms of the molecule in ``molecules.csv``; dimer configurations apart); printed and written
to ``--json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from emlpack._files import write_json_atomic
from emlpack.data.dataset import molecule_id
from emlpack.data.shards import read_molecule_table, read_shards
from emlpack.train.evaluate import evaluate, load_for_evaluation, static_errors


def unseen(trained_on: str | Path, data: str | Path) -> list:
    """DATA's train and validation configurations of molecules absent from ``trained_on``."""
    seen = {molecule_id(s) for s in read_shards(trained_on).structures}
    grown = read_shards(data)
    split = grown.split_indices()
    return [grown.structures[i] for key in ("train", "val") for i in split[key]
            if molecule_id(grown.structures[i]) not in seen]


def by_size(model, reference, structures, data: str | Path) -> list[dict]:
    """Static energy and core-force MAE (eV/atom, eV/Å) per molecule size (heavy atoms) and
    kind (monomer or dimer configuration)."""
    heavy = {row["name"]: row["n_heavy"] for row in read_molecule_table(data)}
    groups: dict[tuple[int, bool], list] = {}
    for s in structures:
        key = (heavy[molecule_id(s)], str(s.info.get("kind", "")).endswith("dimer"))
        groups.setdefault(key, []).append(s)
    out = []
    for (n_heavy, dimer), members in sorted(groups.items()):
        a = static_errors(model, reference, members)
        out.append({"heavy_atoms": n_heavy, "dimers": dimer,
                    "molecules": len({molecule_id(s) for s in members}),
                    "configurations": len(members),
                    "energy_mae": float(abs(a["e_pred"] - a["e_true"]).mean()),
                    "forces_mae": float(abs(a["f_pred"] - a["f_true"]).mean())})
    return out


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model")
    p.add_argument("trained_on")
    p.add_argument("data", nargs="?", default="datasets/mini-eqm7")
    p.add_argument("--json", type=Path, help="write the summary here")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, reference, _ = load_for_evaluation(args.model)
    structures = unseen(args.trained_on, args.data)
    molecules = sorted({molecule_id(s) for s in structures})
    print(f"{len(structures)} configurations of {len(molecules)} unseen molecules", flush=True)
    metrics, _ = evaluate(model, reference, structures, dynamic=True)
    st, dy = metrics["static"], metrics["dynamic"]
    summary = {
        "model": args.model, "trained_on": args.trained_on, "data": args.data,
        "n_configurations": len(structures), "molecules": molecules,
        "static_mae": {k: st[k]["mae"] for k in ("energy", "forces", "pair_forces")},
        "static_median": {k: st[k]["median"] for k in ("energy", "forces", "pair_forces")},
        "pair_field_slope": st["pair_field_slope"],
        "intrinsic": metrics["intrinsic"],
        "dynamic_mae": {k: dy[k]["mae"] for k in ("energy", "forces", "dipole")},
        "dynamic_error_rate": dy["error_rate"], "dynamic_failed": dy["n_failed"],
        "static_by_size": by_size(model, reference, structures, args.data),
        "units": "eV/atom (energy), eV/Å (forces), Debye (dipole)",
    }
    print(json.dumps({k: v for k, v in summary.items() if k != "molecules"}, indent=1))
    if args.json:
        write_json_atomic(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
