"""Evaluation tables of the paper: static and dynamic errors, error rates, parity plots.

* Static errors (pairs at the DFT centres): energy per atom (relative to the reference, i.e.
  the same energy differences the model was trained on), core forces and pair forces per
  component; MAE and median absolute error.
* Pair field response: the slope ``c`` of the pair-force error on the field force ``q E``
  (:func:`emlpack.train.loss.field_response_slope`): 0 when the pairs respond to a field as
  DFT's centres do, ~0.5 when they are about twice too soft (polarizabilities ~2x too large).
* Intrinsic variability: the MAE of the best constant model (the median of the labels), with
  the field forces ``q E`` subtracted from the force labels (as in the paper's tables; the
  errors are unaffected by this).
* Dynamic errors (pairs relaxed with :func:`emlpack.pairs.relax.relax_pairs`): energy, core forces
  and dipole norm (Debye) at the relaxed pairs, for the relaxations that did not fail.
* Error rate: the fraction of failed relaxations. A relaxation fails when
  :func:`~emlpack.pairs.relax.relax_pairs` reports a reason (no convergence to ``fmax`` within the
  iteration limit, two pairs closer than 0.1 Å, a pair farther than 2 Å from every core,
  negative curvature at the result), or when a relaxed pair ends farther than
  ``max_pair_shift`` (0.5 Å) from its DFT centre.
* Ensembles: the table reports the mean (± standard deviation) over models.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack._files import write_figure_atomic, write_text_atomic
from emlpack.data.dataset import make_batch
from emlpack.data.references import reference_from_metadata
from emlpack.nn.checkpoint import load_model, read_checkpoint
from emlpack.train.loss import field_response_slope, predict
from emlpack.units import E_A_IN_DEBYE

if TYPE_CHECKING:
    from collections.abc import Sequence

    from emlpack.data.references import ConstantReference, HydrideReference
    from emlpack.nn.potential import EMLP
    from emlpack.structure import Structure

log = logging.getLogger(__name__)


def load_for_evaluation(
    path: str | Path,
) -> tuple[EMLP, HydrideReference | ConstantReference, dict]:
    """``(model float64, reference, metadata)`` of a checkpoint written by the trainer."""
    meta = read_checkpoint(path).get("metadata", {})
    if "reference" not in meta:
        raise ValueError(f"{path}: no reference in the checkpoint metadata (not a trained"
                         " model of `emlp train`)")
    return load_model(path, torch.float64), reference_from_metadata(meta["reference"]), meta


def static_errors(model: EMLP, reference: HydrideReference | ConstantReference,
                  structures: Sequence[Structure], batch_size: int = 32,
                  progress: bool = False) -> dict:
    """Per-quantity arrays of predictions, targets and field-free targets."""
    from emlpack.progress import progress as progress_bar

    c = model.config
    out = {k: [] for k in ("e_pred", "e_true", "f_pred", "f_true", "f_free",
                           "p_pred", "p_true", "p_free")}
    chunks = range(0, len(structures), batch_size)
    for k in progress_bar(chunks, desc="static errors", unit="batch", enabled=progress,
                          leave=False):
        chunk = structures[k:k + batch_size]
        batch = make_batch(chunk, reference, c.cutoff, c.gcut, torch.float64)
        pred = predict(model, batch, reference, stress=False, create_graph=False)
        n = batch.n_cores.double()
        out["e_pred"].append((pred["energy"].detach() / n).numpy())
        out["e_true"].append((batch.energy / n).numpy())
        f = pred["forces"].detach()
        qe = (batch.graph.charges[:, None] * batch.graph.field[batch.graph.batch])
        for key, mask in (("f", batch.core_mask), ("p", batch.pair_mask)):
            out[f"{key}_pred"].append(f[mask].numpy().reshape(-1))
            out[f"{key}_true"].append(batch.forces[mask].numpy().reshape(-1))
            out[f"{key}_free"].append((batch.forces[mask] - qe[mask]).numpy().reshape(-1))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def _stats(err: np.ndarray) -> dict:
    a = np.abs(err)
    return {"mae": float(a.mean()) if a.size else float("nan"),
            "median": float(np.median(a)) if a.size else float("nan")}


def _intrinsic(values: np.ndarray) -> float:
    return float(np.abs(values - np.median(values)).mean()) if values.size else float("nan")


def _cat(arrays: list) -> np.ndarray:
    return np.concatenate(arrays) if arrays else np.zeros(0)


def dynamic_errors(model: EMLP, reference: HydrideReference | ConstantReference,
                   structures: Sequence[Structure], batch_size: int = 16,
                   max_pair_shift: float = 0.5, progress: bool = False) -> dict:
    """Relax the pairs of every structure; errors at the relaxed pairs and the failure rate."""
    from emlpack.pairs.relax import relax_pairs
    from emlpack.progress import progress as progress_bar

    c = model.config
    e_err, f_err, d_err, d_true, e_true, f_true = [], [], [], [], [], []
    failures, records = [], []
    chunks = range(0, len(structures), batch_size)
    for k in progress_bar(chunks, desc="relaxing pairs", unit="batch", enabled=progress,
                          leave=False):
        chunk = structures[k:k + batch_size]
        results = relax_pairs(model, chunk)
        relaxed, kept = [], []
        for s, r in zip(chunk, results, strict=True):
            shift = np.linalg.norm(r.pairs - s.pairs, axis=1).max() if s.n_pairs else 0.0
            reason = r.reason or (f"a pair moved {shift:.2f} Å from its DFT centre"
                                  if shift > max_pair_shift else "")
            if reason:
                failures.append({"structure": s.source, "reason": reason})
                records.append({"structure": s.source, "max_pair_shift": float(shift),
                                "dft_dipole_D": float(np.linalg.norm(s.dipole()) * E_A_IN_DEBYE),
                                "emlp_dipole_D": float("nan"), "failure": reason})
                continue
            relaxed.append(s.copy(pairs=r.pairs))
            kept.append(s)
        if not relaxed:
            continue
        batch = make_batch(relaxed, reference, c.cutoff, c.gcut, torch.float64)
        pred = predict(model, batch, reference, stress=False, create_graph=False)
        n = batch.n_cores.double()
        e_err.append(((pred["energy"].detach() - batch.energy) / n).numpy())
        e_true.append((batch.energy / n).numpy())
        f = pred["forces"].detach()
        f_err.append((f[batch.core_mask] - batch.forces[batch.core_mask]).numpy().reshape(-1))
        # intrinsic variability of the field-free force labels, as in the static table
        qe = batch.graph.charges[:, None] * batch.graph.field[batch.graph.batch]
        f_true.append((batch.forces - qe)[batch.core_mask].numpy().reshape(-1))
        for s_rel, s in zip(relaxed, kept, strict=True):
            mu_model = np.linalg.norm(s_rel.dipole()) * E_A_IN_DEBYE
            mu_dft = np.linalg.norm(s.dipole()) * E_A_IN_DEBYE
            d_err.append(mu_model - mu_dft)
            d_true.append(mu_dft)
            shift = np.linalg.norm(s_rel.pairs - s.pairs, axis=1).max() if s.n_pairs else 0.0
            records.append({"structure": s.source, "max_pair_shift": float(shift),
                            "dft_dipole_D": float(mu_dft), "emlp_dipole_D": float(mu_model),
                            "failure": ""})
    return {
        "energy": _stats(_cat(e_err)), "forces": _stats(_cat(f_err)),
        "dipole": _stats(np.array(d_err)),
        "intrinsic": {"energy": _intrinsic(_cat(e_true)), "forces": _intrinsic(_cat(f_true)),
                      "dipole": _intrinsic(np.array(d_true))},
        "n_structures": len(structures), "n_failed": len(failures),
        "error_rate": len(failures) / max(len(structures), 1), "failures": failures,
        "structures": records,
    }


def evaluate(model: EMLP, reference: HydrideReference | ConstantReference,
             structures: Sequence[Structure], dynamic: bool = True, progress: bool = False,
             max_pair_shift: float = 0.5) -> tuple[dict, dict]:
    """``(metrics, arrays)`` of one model on ``structures`` (units: eV, Å, Debye)."""
    a = static_errors(model, reference, structures, progress=progress)
    metrics = {
        "n_structures": len(structures),
        "static": {
            "energy": _stats(a["e_pred"] - a["e_true"]),
            "forces": _stats(a["f_pred"] - a["f_true"]),
            "pair_forces": _stats(a["p_pred"] - a["p_true"]),
            "pair_field_slope": field_response_slope(a["p_pred"] - a["p_true"],
                                                     a["p_true"] - a["p_free"]),
        },
        "intrinsic": {"energy": _intrinsic(a["e_true"]), "forces": _intrinsic(a["f_free"]),
                      "pair_forces": _intrinsic(a["p_free"])},
    }
    if dynamic:
        metrics["dynamic"] = dynamic_errors(model, reference, structures, progress=progress,
                                            max_pair_shift=max_pair_shift)
    return metrics, a


def _fmt(values: list[float], scale: float, digits: int) -> str:
    v = np.asarray(values, dtype=float) * scale
    if len(v) == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} (± {v.std(ddof=1):.{digits}f})"


def markdown_table(results: list[dict], title: str = "") -> str:
    """The paper's static and dynamic tables (mean ± std over ``results``, one per model)."""
    r0 = results[0]
    lines = [f"## {title}" if title else "",
             f"{len(results)} model(s), {r0['n_structures']} structures.", "",
             "### Static errors (electron pairs at the DFT centres)", "",
             "| | energy [meV/atom] | core forces [meV/Å] | pair forces [meV/Å] |",
             "|---|---|---|---|"]
    keys = ("energy", "forces", "pair_forces")
    lines.append("| intrinsic variability (MAE) | " + " | ".join(
        f"{1000 * r0['intrinsic'][k]:.1f}" for k in keys) + " |")
    for stat in ("mae", "median"):
        lines.append(f"| {'MAE' if stat == 'mae' else 'median error'} | " + " | ".join(
            _fmt([r["static"][k][stat] for r in results], 1000, 1) for k in keys) + " |")
    ratio = r0["intrinsic"]["forces"] / np.mean([r["static"]["forces"]["mae"] for r in results])
    lines += ["", f"Core-force MAE is {ratio:.1f}x below the intrinsic variability.", ""]
    slopes = [r["static"].get("pair_field_slope") for r in results]
    if all(s is not None for s in slopes):
        lines += [f"Pair field response: slope {_fmt(slopes, 1, 2)} of the pair-force error on"
                  " the field force qE (0: pairs respond to a field as the DFT centres do; 0.5:"
                  " about twice too soft, polarizabilities about twice too large).", ""]
    if "dynamic" in r0:
        d0 = r0["dynamic"]
        lines += ["### Dynamic errors (electron pairs relaxed)", "",
                  "| | energy [meV/atom] | core forces [meV/Å] | dipole norm [D] |",
                  "|---|---|---|---|",
                  f"| intrinsic variability (MAE) | {1000 * d0['intrinsic']['energy']:.1f} |"
                  f" {1000 * d0['intrinsic']['forces']:.1f} | {d0['intrinsic']['dipole']:.3f} |"]
        for stat in ("mae", "median"):
            name = "MAE" if stat == "mae" else "median error"
            lines.append(
                f"| {name} | {_fmt([r['dynamic']['energy'][stat] for r in results], 1000, 1)}"
                f" | {_fmt([r['dynamic']['forces'][stat] for r in results], 1000, 1)}"
                f" | {_fmt([r['dynamic']['dipole'][stat] for r in results], 1, 3)} |")
        rates = [100 * r["dynamic"]["error_rate"] for r in results]
        lines += [f"| error rate | {_fmt(rates, 1, 1)} % | | |", "",
                  "A relaxation fails when it does not converge (max pair force 1e-4 eV/Å within"
                  " the iteration limit), two pairs come closer than 0.1 Å, a pair ends farther"
                  " than 2 Å from every core or more than 0.5 Å from its DFT centre, or the"
                  " pair Hessian has negative curvature at the result."]
        fails = [f for r in results for f in r["dynamic"]["failures"]]
        for f in fails[:10]:
            lines.append(f"- failed: {f['structure']}: {f['reason']}")
    return "\n".join(lines) + "\n"


def parity_plots(arrays: dict, path: str | Path, title: str = "") -> Path:
    """Energy, core-force and pair-force parity plots (static) as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    panels = (("e", "energy [eV/atom, relative]"), ("f", "core forces [eV/Å]"),
              ("p", "pair forces [eV/Å]"))
    for ax, (key, label) in zip(axes, panels, strict=True):
        t, p = arrays[f"{key}_true"], arrays[f"{key}_pred"]
        ax.scatter(t, p, s=4, alpha=0.5)
        if t.size:
            lo, hi = float(min(t.min(), p.min())), float(max(t.max(), p.max()))
            ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
            ax.set_title(f"{label}\nMAE {np.abs(p - t).mean():.4f}")
        ax.set_xlabel("DFT")
        ax.set_ylabel("eMLP")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    write_figure_atomic(path, fig, dpi=110)
    plt.close(fig)
    return path


def select_structures(structures: Sequence[Structure], meta: dict, data_path: str | Path,
                      subset: str) -> list[Structure]:
    """The ``subset`` (train/val/test/all) of ``structures`` using the checkpoint's split."""
    if subset == "all":
        return list(structures)
    split = meta.get("split")
    if not split or subset not in split:
        raise ValueError(f"the checkpoint holds no '{subset}' split; use --subset all")
    made_on = meta.get("data_path", "")
    index = [int(i) for i in split[subset]]
    if index and max(index) >= len(structures):
        n_made = meta.get("n_structures", "?")
        raise ValueError(f"the checkpoint's split was made on {made_on} ({n_made} structures),"
                         f" {data_path} holds {len(structures)}; use --subset all")
    if Path(made_on).resolve() != Path(data_path).resolve():
        log.warning("the split was made on %s; applying its indices to %s", made_on, data_path)
    return [structures[i] for i in index]


def evaluate_models(model_paths: Sequence[str | Path], data_path: str | Path,
                    output: str | Path, subset: str = "test",
                    dynamic: bool = True, max_structures: int | None = None,
                    progress: bool = True) -> tuple[str, dict]:
    """Evaluate one or more models (an ensemble) on ``data_path``; write Markdown, JSON, PNG."""
    from emlpack.data.dataset import load_data

    structures, _ = load_data(data_path)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    from emlpack.progress import progress as progress_bar

    results = []
    models = progress_bar(list(enumerate(model_paths)), desc="models", unit="model",
                          enabled=progress and len(model_paths) > 1)
    for k, path in models:
        model, reference, meta = load_for_evaluation(path)
        chosen = select_structures(structures, meta, data_path, subset)
        if max_structures:
            chosen = chosen[:max_structures]
        metrics, arrays = evaluate(model, reference, chosen, dynamic, progress)
        metrics["model"] = str(path)
        results.append(metrics)
        if k == 0:
            parity_plots(arrays, output / "parity.png", f"{Path(path).name}: {subset} set")
    table = markdown_table(results, f"{', '.join(str(p) for p in model_paths)} on {data_path}"
                                    f" ({subset})")
    write_text_atomic(output / "evaluation.md", table)
    write_text_atomic(output / "evaluation.json", json.dumps(results, indent=2))
    return table, {"models": results}
