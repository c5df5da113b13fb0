"""Pretrained eMLP ensembles shipped inside the package, loaded by name.

Each model is a folder ``emlpack/pretrained/NAME/`` with ``model-K.pt`` checkpoints (float32
weights; the training reference, elements and largest molecule in their metadata) and
``card.md`` (level of theory, data, measured errors on unseen molecules, domain, citation)::

    from emlpack import load_pretrained
    ensemble = load_pretrained("mini-eqm7")          # a ModelEnsemble
    atoms.calc = EMLPCalculator(model="mini-eqm7")   # the same, with uncertainty

Energies of these models are on the DFT scale (the DFT hydride energies added back, see
:mod:`emlpack.calculators.ensemble`), so they compare directly with a PySCF total energy at the
training level. Nothing here downloads anything: the files are part of the installed package.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from emlpack._files import write_text_atomic
from emlpack.errors import EmlpackError

if TYPE_CHECKING:
    import torch

PRETRAINED_DIR = Path(__file__).resolve().parent
#: the names emlpack knows, with what each one is (whether or not its files are installed)
KNOWN = {
    "mini-eqm7": "ensemble trained on the mini-eQM7 campaign data set (PBE0/aug-cc-pVTZ,"
                 " neutral closed-shell H/C/N/O molecules up to 7 heavy atoms)",
    "mini-eqm7-v1": "the first mini-eqm7 ensemble (issue 15's final study: four augmented"
                    " SchNet members), loadable by this name after a later one ships as"
                    " mini-eqm7",
}
#: names served by another name's folder while they have none of their own: ``mini-eqm7-v1``
#: is today's ``mini-eqm7`` (the same files) until v2 ships as ``mini-eqm7`` and the v1
#: members move to ``pretrained/mini-eqm7-v1/`` (examples/eqm7/v2/README.md); a name's own
#: folder, once installed, always wins over its alias
ALIASES = {"mini-eqm7-v1": "mini-eqm7"}


class PretrainedError(EmlpackError, ValueError):
    """An unknown pretrained name, or one whose files are not installed."""


def _members(folder: Path) -> list[Path]:
    return sorted(folder.glob("model-*.pt")) if folder.is_dir() else []


def folder_of(name: str, root: Path | None = None) -> Path:
    """The folder that serves pretrained ``name``: its own (``ROOT/NAME``) when it holds
    members, else its alias's (:data:`ALIASES`) when it has one, else its own (missing)."""
    root = root or PRETRAINED_DIR
    own = root / name
    if _members(own) or name not in ALIASES:
        return own
    return root / ALIASES[name]


def alias_of(name: str, root: Path | None = None) -> str | None:
    """The name whose files serve ``name`` (an alias without its own folder), else None."""
    folder = folder_of(name, root)
    return folder.name if folder.name != name else None


def model_files(name: str, root: Path | None = None) -> list[Path]:
    """The checkpoints of pretrained model ``name`` (empty when none are installed)."""
    return _members(folder_of(name, root))


def available(root: Path | None = None) -> list[str]:
    """Names of the pretrained models installed with this copy of emlpack (an alias whose
    target is installed among them)."""
    root = root or PRETRAINED_DIR
    if not root.is_dir():
        return []
    names = {p.name for p in root.iterdir() if p.is_dir() and _members(p)}
    return sorted(names | {a for a in ALIASES if model_files(a, root)})


def resolve_model(model: str | Path, root: Path | None = None) -> tuple[list[Path], str]:
    """Checkpoint files and a display name for a MODEL argument: a checkpoint file, a folder
    of ``*.pt`` checkpoints (an ensemble), or the name of a pretrained model."""
    path = Path(model)
    if path.is_file():
        return [path], str(path)
    if path.is_dir():
        files = sorted(path.glob("*.pt"))
        if not files:
            raise PretrainedError(f"{path}: folder holds no *.pt model checkpoints")
        return files, str(path)
    name = str(model)
    files = model_files(name, root)
    if files:
        return files, name
    if name in KNOWN:
        raise PretrainedError(
            f"pretrained model {name!r} ({KNOWN[name]}) is not installed with this copy of"
            f" emlpack (installed: {', '.join(available(root)) or 'none'})")
    raise PretrainedError(
        f"{name}: no such model file, folder or pretrained name (known names:"
        f" {', '.join(KNOWN)}; installed: {', '.join(available(root)) or 'none'})")


def model_card(name: str, root: Path | None = None) -> str:
    """The model card (Markdown) of pretrained model ``name``."""
    path = folder_of(name, root) / "card.md"
    if not path.is_file():
        raise PretrainedError(f"pretrained model {name!r} has no card installed")
    target = alias_of(name, root)
    if target:
        return (f"*{name}: the same files as {target} (emlpack.pretrained.ALIASES), whose card"
                " follows.*\n\n" + path.read_text())
    return path.read_text()


def lineage_lines(lineage: list[dict] | None) -> list[str]:
    """A checkpoint's lineage (``metadata["lineage"]``, written by the trainer: the earlier
    stages, e.g. a pretraining at a cheap level, then the last run) as readable lines."""
    if not lineage:
        return ["lineage: not recorded (trained before lineage was recorded, or not by"
                " `emlp train`)"]
    out = []
    for k, s in enumerate(lineage):
        what = "trained" if k == 0 and not s.get("init_weights") else "fine-tuned"
        frozen = f", frozen {', '.join(s['freeze'])}" if s.get("freeze") else ""
        steps = "" if s.get("step") is None else f", {s['step']} steps"
        shards = s.get("shards")
        part = (f" shards {shards[0]}-{shards[-1]} ({len(shards)})" if shards and len(shards) > 1
                else f" shard {shards[0]}" if shards else "")
        out.append(f"stage {k + 1}: {what} on {s.get('data_path')}{part} ({s.get('n_train')}"
                   " training"
                   f" configurations, level {', '.join(s.get('levels') or ['unknown'])},"
                   f" reference {s.get('reference', 'unknown')}), {s.get('epoch')} epochs"
                   f"{steps}{frozen}")
    return out


#: the heading of the lineage section that :func:`export_pretrained` adds to a card
LINEAGE_HEADING = "## Lineage"


def lineage_section(lineages: list[list[dict] | None]) -> list[str]:
    """The model card's lineage section (Markdown lines) from the members' lineages: each
    member's stages (:func:`lineage_lines`), e.g. pretrained at a cheap level, then
    fine-tuned at the paper's."""
    lines = [LINEAGE_HEADING, "",
             "What each member was trained on, stage by stage (from its checkpoint's"
             " `lineage`):", ""]
    for k, lineage in enumerate(lineages):
        lines += [f"- member {k}:", *(f"  - {line}" for line in lineage_lines(lineage))]
    return [*lines, ""]


def export_pretrained(checkpoints: list[str | Path], folder: str | Path, card: str,
                      dtype: torch.dtype | None = None, notice: str | None = None,
                      data_path: str | None = None, domain: dict | None = None,
                      spread_calibration: dict | None = None) -> list[Path]:
    """Write trained checkpoints as a shippable pretrained model: ``folder/model-K.pt`` with
    weights in ``dtype`` (default float32), only the metadata a user needs (reference,
    elements, model config, data path and split), and ``folder/card.md``. ``notice``: a line
    every calculation with these models reports among its warnings (e.g. that the ensemble is
    preliminary, with its measured errors); ``data_path``: how the metadata names the training
    data (default: the checkpoint's own, which may be a local path); ``domain``: the
    training domain (:func:`emlpack.data.dataset.training_domain`) for checkpoints whose
    metadata lacks it (written before it was recorded); ``spread_calibration``: the
    ensemble's spread thresholds (:func:`emlpack.calculators.calibration.calibrate_spread`
    of these checkpoints at ``dtype``), stored in every member. The card gets the members'
    lineage (:func:`lineage_section`) at its end when their checkpoints record one and the
    card has no such section. The folder's earlier members are replaced: a ``model-K.pt``
    beyond the new ensemble's size is removed. Returns the written files."""
    import torch

    from emlpack.nn.checkpoint import load_model, read_checkpoint, save_model

    dtype = dtype or torch.float32

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    keep = ("reference", "elements", "max_heavy_atoms", "data_path", "split", "epoch", "val",
            "lineage")
    written, lineages = [], []
    for k, path in enumerate(checkpoints):
        meta = read_checkpoint(path).get("metadata", {}) or {}
        lineages.append(meta.get("lineage"))
        if "reference" not in meta:
            raise PretrainedError(f"{path}: no training reference in the metadata (not a"
                                  " checkpoint written by `emlp train`)")
        model = load_model(path, dtype)
        out = {key: meta[key] for key in keep if key in meta}
        for key, value in (domain or {}).items():
            out.setdefault(key, value)
        out["source_checkpoint"] = Path(path).name
        if notice:
            out["notice"] = notice
        if spread_calibration:
            out["spread_calibration"] = spread_calibration
        if data_path:
            out["data_path"] = data_path
        written.append(save_model(model, folder / f"model-{k}.pt", out))
    for stale in set(folder.glob("model-*.pt")) - set(written):
        stale.unlink()  # a member of a larger earlier ensemble
    if any(lineages) and LINEAGE_HEADING not in card:
        card = card.rstrip("\n") + "\n\n" + "\n".join(lineage_section(lineages))
    card_path = folder / "card.md"
    write_text_atomic(card_path, card)
    return [*written, card_path]
