"""Does the loss's polarizability term move the pairs' stiffness? A mechanism check with
stand-in labels (issue 51, item 2; docs/stiffness.md), before the DFT labels exist.

    OMP_NUM_THREADS=1 python examples/eqm7/stiffness_lever_check.py [--epochs 3] [--weight 3e-4]
        [--json examples/eqm7/stiffness/lever_check.json]

Stand-in labels: for the configurations ``polarizability_labels.py`` would label first (300),
the shipped member 0's own polarizability at the DFT centres divided by the median ratio of its
polarizabilities to DFT's on the molecules of ``stiffness_estimate.py`` (1.42: what DFT would
say if the model's error were a uniform factor), written as label files into a temporary copy
of the data-set folder (shards linked, not copied). Two fine-tunes of member 0 with the
study's recipe (``examples/eqm7/train.yaml``, augmented, lr 1e-4), identical but for
``loss.polarizability`` (0 and ``--weight``), for ``--epochs`` epochs each. Printed and saved:
the validation molecules' core- and pair-force MAE and pair-field slope (``log.csv``), and the
isotropic polarizabilities of the DFT molecules of ``stiffness_estimate.py`` against DFT
(clamped cores at the prepared optima: molecules and geometries the labels never saw).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import polarizability_labels  # noqa: E402
import stiffness_estimate  # noqa: E402

from emlpack._files import write_text_atomic  # noqa: E402
from emlpack.data.shards import (  # noqa: E402
    POLARIZABILITY_DIR,
    label_file_name,
    read_molecule_table,
    read_shards,
)
from emlpack.nn.checkpoint import load_model  # noqa: E402
from emlpack.pretrained import resolve_model  # noqa: E402
from emlpack.properties.response import clamped_polarizabilities  # noqa: E402
from emlpack.train.config import load_config  # noqa: E402
from emlpack.train.trainer import Trainer  # noqa: E402

ROOT = HERE.parents[1]
DATA = ROOT / "datasets" / "mini-eqm7"


def stand_in_labels(folder: Path, model, ratio: float, count: int) -> int:
    """Write the stand-in labels into ``folder/polarizability``; returns how many."""
    data = read_shards(DATA)
    chosen = polarizability_labels.select_configurations(
        data.structures, read_molecule_table(DATA), polarizability_labels.banned_graphs(),
        count)
    out = folder / POLARIZABILITY_DIR
    out.mkdir()
    n = 0
    for s in chosen:
        res = clamped_polarizabilities(model, model.graph(s, dtype=torch.float64))
        if res.problems[0]:
            continue
        alpha = res.alpha[0].numpy() / ratio
        write_text_atomic(out / label_file_name(s.info["key"]), json.dumps({
            "key": s.info["key"], "numbers": s.numbers.tolist(),
            "positions": s.positions.tolist(), "polarizability_e_A2_per_V": alpha.tolist(),
            "note": f"stand-in: shipped member 0 / {ratio}"}))
        n += 1
    return n


def fine_tune(folder: Path, out: Path, member: Path, weight: float, epochs: int) -> dict:
    """One fine-tune; the last row of its log.csv and the path of its last weights."""
    cfg = load_config(ROOT / "examples" / "eqm7" / "train.yaml", [
        f"data.path={folder}", f"output.dir={out}", "augmentation.enabled=true",
        f"training.init_weights={member}", "training.lr=1e-4", f"training.max_epochs={epochs}",
        "training.max_time_minutes=null", "training.patience=null",
        f"loss.polarizability={weight}"])
    trainer = Trainer(cfg)
    trainer.init_weights(member)
    start = trainer.validate()
    trainer.train()
    with open(out / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {"start": start, "first": rows[0], "last": rows[-1], "weights": str(out / "last.pt")}


def dft_molecules(path: str) -> list[dict]:
    """Isotropic polarizabilities of the model at ``path`` on the DFT molecules."""
    model = load_model(path, dtype=torch.float64)
    out = []
    for ref_path in sorted(stiffness_estimate.PAPER_ALPHA.glob("*-alpha.json")):
        ref = json.loads(ref_path.read_text())
        m = stiffness_estimate.member_numbers(model, stiffness_estimate.molecule(ref["molecule"]))
        out.append({"molecule": ref["molecule"], "dft": ref["alpha_iso_bohr3"],
                    "model": m["alpha_iso_bohr3"], "k1_model": m["k1_model"],
                    "problem": m["problem"]})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--weight", type=float, default=3e-4, help="loss.polarizability (1/bohr^6)")
    ap.add_argument("--ratio", type=float, default=1.42)
    ap.add_argument("--count", type=int, default=300)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    member = resolve_model("mini-eqm7")[0][0]
    result = {"settings": vars(args) | {"json": str(args.json)}, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "data"
        folder.mkdir()
        for name in ("molecules.csv", "shards"):
            (folder / name).symlink_to(DATA / name)
        model = load_model(member, dtype=torch.float64)
        result["n_labels"] = stand_in_labels(folder, model, args.ratio, args.count)
        print(f"{result['n_labels']} stand-in labels", flush=True)
        result["shipped"] = dft_molecules(str(member))
        for weight in (0.0, args.weight):
            run = fine_tune(folder, Path(tmp) / f"run-{weight:g}", member, weight, args.epochs)
            run["dft_molecules"] = dft_molecules(run.pop("weights"))
            result["runs"][f"{weight:g}"] = run
    for name, mols in [("shipped", result["shipped"])] + [
            (f"lambda_a {w}", r["dft_molecules"]) for w, r in result["runs"].items()]:
        ratio = np.median([m["model"] / m["dft"] for m in mols if not m["problem"]])
        k1 = np.median([m["k1_model"] for m in mols if not m["problem"]])
        print(f"{name:16s} alpha/DFT median {ratio:.3f}, single-pair curvature {k1:.1f} eV/Å²")
    for w, r in result["runs"].items():
        last = r["last"]
        print(f"lambda_a {w}: epoch {last['epoch']}, val core F MAE"
              f" {1000 * float(last['val_forces_mae']):.1f} meV/Å, pair F MAE"
              f" {1000 * float(last['val_pair_forces_mae']):.1f} meV/Å, slope"
              f" {float(last['val_pair_field_slope']):.3f} (first epoch"
              f" {float(r['first']['val_pair_field_slope']):.3f}; shipped member 0:"
              f" {r['start']['pair_field_slope']:.3f}, core F MAE"
              f" {1000 * r['start']['forces_mae']:.1f}, pair F MAE"
              f" {1000 * r['start']['pair_forces_mae']:.1f})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(args.json, json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
