"""A labeling campaign: a fixed molecule list and split, labeled into immutable shards.

``emlp campaign init FOLDER --smiles qm7_smiles.csv`` fixes the molecule list, its seed and the
split (``molecules.csv``) and the recipe (``campaign.yaml``) before any label exists.
``emlp campaign run FOLDER`` labels with :func:`emlpack.qm.labeling.run_labeling` into a working
store (``FOLDER/work/``, not committed) and moves the finished records every few minutes (once
there are enough of them) into a new shard ``FOLDER/shards/NNNN.h5``, written in one go in the
packed layout (:func:`emlpack.data.store.write_packed`; temporary file, then rename; never
rewritten), with the
prepared molecules in ``FOLDER/prepared/`` and the card ``FOLDER/README.md`` regenerated from
the shards. With ``commit=True`` each new shard is committed to git at once, so a session that
ends without warning loses at most the configurations in flight. A re-run on any machine
continues with the keys no shard holds yet (see :mod:`emlpack.data.shards` for the reader).

Molecule selection (the mini-eQM7 rules): QM7 rows 0-9 (the paper's validation molecules) are
never labeled, sulfur is out of scope, the paper's IR test molecules are forced into the test
split, every molecule with 2-5 heavy atoms comes first, then a seeded sample of 6-7 heavy atoms.
"""

from __future__ import annotations

import csv
import hashlib
import io
import logging
import os
import re
import socket
import time
from collections import Counter
from pathlib import Path

import numpy as np
import yaml

from emlpack._files import write_text_atomic
from emlpack.commits import git_commit
from emlpack.data.shards import (
    ACTIVE_LEARNING_DIR,
    ACTIVE_LEARNING_PART,
    CAMPAIGN_PART,
    MOLECULES_FILE,
    SHARD_DIR,
    SHARD_PARTS,
    SPLITS,
    ShardedData,
    finished_keys,
    read_molecule_table,
    read_shards,
    shard_paths,
    shards_size_text,
)
from emlpack.data.store import DatasetStore, StoreError, write_packed
from emlpack.interrupts import terminate_as_interrupt
from emlpack.optional import import_optional
from emlpack.qm.levels import PAPER, parse_level
from emlpack.qm.recipe import (
    LEGACY_FIELD_DISTRIBUTION,
    Configuration,
    default_recipe,
    rescale_counts,
    validate_recipe,
)
from emlpack.qm.sampling import SamplingError
from emlpack.structure import Structure

log = logging.getLogger(__name__)

CAMPAIGN_FILE = "campaign.yaml"
#: how new shards store positions and forces where campaign.yaml's ``storage`` says nothing
#: (``compress``: gzip where it makes a table smaller; uncompressed float64 records of small
#: molecules take ~2.3 kB each, over the project's 2 kB per configuration)
DEFAULT_STORAGE = {"precision": "float64", "compress": True}
#: fewest new records and failures that make a shard before a run stops (each shard costs
#: ~2.5 kB of HDF5 headers and attributes, and a commit)
SHARD_MIN_RECORDS = 10
#: hand-written measurements (e.g. the level choice) included in the card verbatim
NOTES_FILE = "notes.md"
#: a line of ``notes.md`` that the card replaces by a file (a table a script writes elsewhere,
#: e.g. the pretraining pilot's): ``<!-- include: PATH -->``, PATH relative to the folder
INCLUDE_RE = re.compile(r"^\s*<!--\s*include:\s*(\S+)\s*-->\s*$")
#: the card's words for each field distribution (:data:`emlpack.qm.sampling.FIELD_DISTRIBUTIONS`)
FIELD_TEXT = {"ball": "uniform in the ball, as the authors' data",
              "magnitude": "uniform direction, magnitude uniform in [0, max]"}
#: QM7 rows never labeled: 0-4 and 7 are the authors' own DFT data (a second test set), 5, 6, 8
#: and 9 (acetaldehyde, dimethyl ether, propane, propene) are reserved for an independent check
EXCLUDED_ROWS = {0: "paper validation (shared DFT data)", 1: "paper validation (shared DFT data)",
                 2: "paper validation (shared DFT data)", 3: "paper validation (shared DFT data)",
                 4: "paper validation (shared DFT data)", 5: "reserved", 6: "reserved",
                 7: "paper validation (shared DFT data)", 8: "reserved", 9: "reserved"}
#: the paper's IR test molecules (test split only): aziridine and 3-(methylamino)but-2-enal
IR_TEST_SMILES = {"aziridine": "C1CN1", "3-(methylamino)but-2-enal": "CNC(C)=CC=O"}


# ---------------------------------------------------------------------------------- selection
def canonical(smiles: str) -> str:
    """Canonical heavy-atom SMILES after QM7's radical brackets are restored (RDKit)."""
    import_optional("rdkit", "canonical SMILES (RDKit)")
    from rdkit import Chem, RDLogger

    from emlpack.qm.sampling import restore_closed_shell

    RDLogger.DisableLog("rdApp.*")
    mol = Chem.MolFromSmiles(smiles)
    if mol is None:
        raise SamplingError(f"RDKit cannot parse SMILES {smiles!r}")
    return Chem.MolToSmiles(Chem.RemoveHs(restore_closed_shell(mol)))


def select_molecules(csv_path: str | Path, seed: int = 0, n_large: int = 100,
                     fractions: tuple[float, float, float] = (0.9, 0.05, 0.05)) -> list[dict]:
    """The campaign's ordered molecule list with its split.

    Returns dicts with ``name`` (``qm7-ROW`` or ``extra-K``), ``source`` (CSV row or
    ``smiles``), ``smiles``, ``n_heavy`` and ``split``. Order: every sulfur-free molecule with
    2-5 heavy atoms (CSV order; open shells skipped), then the IR molecules missing from the
    CSV, then ``n_large`` molecules with 6-7 heavy atoms drawn with ``seed``. Split by
    molecule over the whole list: the IR molecules in test, the rest shuffled with ``seed``
    into ``fractions``.
    """
    import_optional("rdkit", "the campaign's molecule list (RDKit reads its SMILES)")
    from rdkit import Chem, RDLogger

    RDLogger.DisableLog("rdApp.*")
    csv_path = Path(csv_path)
    with csv_path.open() as fh:
        rows = list(csv.DictReader(fh))
    excluded = {canonical(rows[i]["smiles"]) for i in EXCLUDED_ROWS if i < len(rows)}
    ir_canon = {canonical(s): label for label, s in IR_TEST_SMILES.items()}
    small, large, seen = [], [], set()
    for i, row in enumerate(rows):
        if i in EXCLUDED_ROWS:
            continue
        mol = Chem.MolFromSmiles(row["smiles"])
        if mol is None or any(a.GetSymbol() not in ("H", "C", "N", "O") for a in mol.GetAtoms()):
            continue  # unparsable, sulfur (out of scope) or another element
        try:
            can = canonical(row["smiles"])
        except SamplingError:
            continue  # radical brackets that cannot be paired: open shell, out of scope
        if can in excluded or can in seen:
            continue
        seen.add(can)
        entry = {"name": f"qm7-{i:04d}", "source": f"row {i}", "smiles": row["smiles"],
                 "n_heavy": mol.GetNumHeavyAtoms(), "canonical": can}
        if 2 <= entry["n_heavy"] <= 5:
            small.append(entry)
        elif entry["n_heavy"] in (6, 7):
            large.append(entry)
    extra = []
    for can, label in ir_canon.items():
        if can not in seen:
            extra.append({"name": f"extra-{len(extra):04d}", "source": f"added: {label}",
                          "smiles": IR_TEST_SMILES[label],
                          "n_heavy": Chem.MolFromSmiles(can).GetNumHeavyAtoms(),
                          "canonical": can})
    rng = np.random.default_rng(seed)
    ir_in_large = [e for e in large if e["canonical"] in ir_canon]
    pool = [e for e in large if e["canonical"] not in ir_canon]
    picked = [pool[k] for k in rng.permutation(len(pool))[: max(0, n_large - len(ir_in_large))]]
    molecules = small + extra + ir_in_large + picked
    # split: IR molecules in test, the others shuffled into the fractions
    f = np.asarray(fractions, dtype=float) / np.sum(fractions)
    n = len(molecules)
    n_test, n_val = int(round(f[2] * n)), int(round(f[1] * n))
    forced = [m for m in molecules if m["canonical"] in ir_canon]
    others = [m for m in molecules if m["canonical"] not in ir_canon]
    order = rng.permutation(len(others))
    n_more_test = max(0, n_test - len(forced))
    for rank, k in enumerate(order):
        others[k]["split"] = ("test" if rank < n_more_test
                              else "val" if rank < n_more_test + n_val else "train")
    for m in forced:
        m["split"] = "test"
    return molecules


def graph_key(smiles: str) -> str:
    """The molecular graph of ``smiles`` as text: canonical heavy-atom SMILES without stereo
    (QM7's radical brackets restored), so stereoisomers and tautomer-free spellings of one
    graph compare equal."""
    import_optional("rdkit", "molecular graphs of SMILES (RDKit)")
    from rdkit import Chem

    return Chem.MolToSmiles(Chem.MolFromSmiles(canonical(smiles)), isomericSmiles=False)


def held_out_graphs(folders: list[str | Path]) -> dict[str, str]:
    """Graphs (:func:`graph_key`) that a pretraining set must not contain, with the reason:
    QM7 rows 0-9 come in through :func:`select_all_molecules`; here the validation and test
    molecules of the campaigns in ``folders`` and the IR molecules."""
    out = {graph_key(s): f"IR test molecule {label}" for label, s in IR_TEST_SMILES.items()}
    for folder in folders:
        for m in read_molecule_table(folder):
            if m["split"] != "train":
                out.setdefault(graph_key(m["smiles"]), f"{m['split']} molecule {m['name']}"
                               f" of {Path(folder).name}")
    return out


def excluded_graphs(folder: str | Path, smiles_csv: str | Path) -> dict[str, str]:
    """Graphs (:func:`graph_key`) that are never labeled for training in the campaign of
    ``folder``, with the reason: its validation and test molecules and the IR molecules
    (:func:`held_out_graphs`), and QM7 rows 0-9 of ``smiles_csv`` (:data:`EXCLUDED_ROWS`: the
    authors' molecules and the reserved ones)."""
    out = held_out_graphs([folder])
    with Path(smiles_csv).open() as fh:
        rows = list(csv.DictReader(fh))
    for i, why in EXCLUDED_ROWS.items():
        out.setdefault(graph_key(rows[i]["smiles"]), f"QM7 row {i} ({why})")
    return out


def select_all_molecules(csv_path: str | Path, exclude: list[str | Path] = (), seed: int = 0,
                         fractions: tuple[float, float, float] = (0.95, 0.05, 0.0),
                         ) -> list[dict]:
    """A pretraining set's molecule list: every sulfur-free closed-shell molecule of the CSV
    except rows 0-9 (:data:`EXCLUDED_ROWS`), the IR test molecules and the validation and test
    molecules of the campaigns in ``exclude`` (by molecular graph, :func:`graph_key`), in a
    seeded random order, split by molecule into ``fractions`` (train, val, test) by position
    in that order (:func:`campaign_order` interleaves the splits for labeling).

    Returns dicts as :func:`select_molecules` (``name`` ``qm7-ROW``, ``source``, ``smiles``,
    ``n_heavy``, ``split``, ``canonical``).
    """
    import_optional("rdkit", "the pretraining set's molecule list (RDKit reads its SMILES)")
    from rdkit import Chem, RDLogger

    RDLogger.DisableLog("rdApp.*")
    with Path(csv_path).open() as fh:
        rows = list(csv.DictReader(fh))
    banned = {graph_key(rows[i]["smiles"]): EXCLUDED_ROWS[i] for i in EXCLUDED_ROWS
              if i < len(rows)}
    banned.update(held_out_graphs(list(exclude)))
    out, seen = [], set()
    for i, row in enumerate(rows):
        if i in EXCLUDED_ROWS:
            continue
        mol = Chem.MolFromSmiles(row["smiles"])
        if mol is None or any(a.GetSymbol() not in ("H", "C", "N", "O") for a in mol.GetAtoms()):
            continue
        try:
            key = graph_key(row["smiles"])
        except SamplingError:
            continue  # an open shell
        if key in banned or key in seen:
            continue
        seen.add(key)
        out.append({"name": f"qm7-{i:04d}", "source": f"row {i}", "smiles": row["smiles"],
                    "n_heavy": mol.GetNumHeavyAtoms(), "canonical": canonical(row["smiles"])})
    rng = np.random.default_rng(seed)
    out = [out[k] for k in rng.permutation(len(out))]
    f = np.asarray(fractions, dtype=float) / np.sum(fractions)
    n_val, n_test = int(round(f[1] * len(out))), int(round(f[2] * len(out)))
    for rank, m in enumerate(out):  # already shuffled: the split by position
        m["split"] = "val" if rank < n_val else "test" if rank < n_val + n_test else "train"
    return out


def labeling_order(molecules: list[dict]) -> list[dict]:
    """The order in which the campaign labels ``molecules`` (the list's order otherwise).

    Within each block (QM7 molecules with 2-5 heavy atoms; the rest: the IR molecules missing
    from QM7 and the drawn 6-7 heavy-atom molecules) the validation and test molecules come
    first, so that a model trained on the first shards can already be judged on molecules it
    never saw, and a campaign that stops at its target (fewer molecules than listed) has its
    whole validation and test split; the split itself is fixed by the list and never depends
    on this. (Until shard 0114 of mini-eqm7 the second block was labeled in list order.)
    """
    def key(m: dict) -> tuple[int, int]:
        first_block = int(m["n_heavy"]) <= 5 and m["name"].startswith("qm7-")
        return (int(not first_block), int(m["split"] == "train"))

    return sorted(molecules, key=key)  # stable: the list's order within each group


def interleaved_order(molecules: list[dict]) -> list[dict]:
    """The molecules with each split spread evenly over the order: the k-th of a split's n
    molecules (in list order) at the quantile (k + 1/2) / n, ties by the list's order.

    A pretraining set's list is shuffled and then split by position (its validation molecules
    are the list's first 5 %): in list order a pilot's first shards would hold validation
    molecules only. Interleaved, every prefix holds each split at its share."""
    by_split: dict[str, list[int]] = {}
    for index, m in enumerate(molecules):
        by_split.setdefault(m["split"], []).append(index)
    rank = {}
    for indices in by_split.values():
        for k, index in enumerate(indices):
            rank[index] = ((k + 0.5) / len(indices), index)
    return [molecules[i] for i in sorted(range(len(molecules)), key=rank.__getitem__)]


def campaign_order(settings: dict, molecules: list[dict]) -> list[dict]:
    """The labeling order of a campaign: a pretraining set (``selection: all``) takes its
    list's seeded random order with the splits interleaved (:func:`interleaved_order`: every
    prefix a sample of the whole, each split at its share); otherwise :func:`labeling_order`."""
    if settings.get("selection") == "all":
        return interleaved_order(molecules)
    return labeling_order(molecules)


def samples_per_molecule(recipe: dict) -> int:
    """Configurations the recipe draws per molecule."""
    return sum(int(s["count"]) for s in recipe.get("samples", []))


def target_prefix(order: list[dict], target: dict | None, per_molecule: int,
                  labeled: Counter, done: Counter) -> tuple[list[dict], dict]:
    """The molecules of ``order`` that a campaign labels to meet its ``target``.

    ``target`` (``campaign.yaml``): ``{"configurations": C, "molecules": M}`` (either may be
    missing; None: no target). The prefix is the shortest one of ``order`` that reaches both,
    counting each molecule whose keys are all finished (``done``: records and failures) with
    its labeled configurations (``labeled``) and every other one with ``per_molecule``: a run
    labels exactly what the target needs when nothing fails, and the next run extends the
    prefix by as many molecules as failures cost. Returns the prefix and a summary (the target,
    ``reached``: every prefix molecule finished and both counts met; the counts so far).
    """
    want_c = int((target or {}).get("configurations", 0))
    want_m = int((target or {}).get("molecules", 0))
    n_labeled = sum(labeled[m["name"]] for m in order)
    n_molecules = sum(1 for m in order if labeled[m["name"]])
    info = {"configurations": want_c, "molecules": want_m, "labeled": n_labeled,
            "labeled_molecules": n_molecules}
    if not target:
        return order, dict(info, reached=False, prefix=len(order))
    configs = mols = 0
    prefix = order
    for k, m in enumerate(order):
        finished = done[m["name"]] >= per_molecule
        expected = labeled[m["name"]] if finished else per_molecule
        configs += expected
        mols += expected > 0
        if configs >= want_c and mols >= want_m:
            prefix = order[:k + 1]
            break
    reached = (all(done[m["name"]] >= per_molecule for m in prefix)
               and n_labeled >= want_c and n_molecules >= want_m)
    return prefix, dict(info, reached=reached, prefix=len(prefix))


def campaign_target(folder: str | Path, settings: dict | None = None,
                    molecules: list[dict] | None = None) -> tuple[list[dict], dict]:
    """:func:`target_prefix` of a campaign folder, from its settings and shards."""
    settings = settings or load_settings(folder)
    molecules = molecules if molecules is not None else read_molecule_table(folder)
    # the campaign's own labels (active learning's are not the target's)
    labeled = Counter(k.split("/")[0] for k in finished_keys(folder, False, CAMPAIGN_PART))
    done = Counter(k.split("/")[0] for k in finished_keys(folder, True, CAMPAIGN_PART))
    return target_prefix(campaign_order(settings, molecules), settings.get("target"),
                         samples_per_molecule(settings["recipe"]), labeled, done)


def campaign_recipe(samples_per_molecule: int = 6, prepare_level: str = "gfn2-xtb") -> dict:
    """The paper's recipe and level with ``samples_per_molecule`` configurations in the paper's
    proportions (NMS 600 K : 800 K : 800 K + torsion : 800 K + dimer = 1 : 1 : 1.5 : 1.5),
    prepared (geometry, Hessian for the normal modes) at the cheap ``prepare_level``."""
    recipe = default_recipe()
    recipe["samples"] = rescale_counts(recipe["samples"], samples_per_molecule)
    recipe["prepare"]["level"] = prepare_level
    validate_recipe(recipe)
    return recipe


def init_campaign(folder: str | Path, smiles_csv: str | Path, seed: int = 0,
                  n_large: int = 100, samples_per_molecule: int = 6,
                  prepare_level: str = "gfn2-xtb", name: str | None = None,
                  level: str = "paper", exclude: list[str | Path] | None = None,
                  target: dict | None = None, storage: dict | None = None) -> list[dict]:
    """Write ``molecules.csv`` (list and split) and ``campaign.yaml`` (recipe); refuse to
    overwrite an existing campaign, whose split must never change.

    ``exclude`` (campaign folders) makes a pretraining set instead (:func:`select_all_molecules`:
    every allowed molecule, without those campaigns' validation and test molecules, split
    95/5 into train and val); ``level`` is the labeling level; ``target`` and ``storage``
    (:func:`export_shard`) go into campaign.yaml as given."""
    folder = Path(folder)
    if (folder / MOLECULES_FILE).exists():
        raise StoreError(f"{folder}: a campaign exists already ({MOLECULES_FILE}); its list"
                         " and split are fixed")
    recipe = campaign_recipe(samples_per_molecule, prepare_level)
    recipe["level"] = level
    if exclude is None:
        molecules = select_molecules(smiles_csv, seed=seed, n_large=n_large)
        selection = {"n_large": n_large, "fractions": [0.9, 0.05, 0.05]}
    else:
        fractions = (0.95, 0.05, 0.0)
        molecules = select_all_molecules(smiles_csv, exclude, seed=seed, fractions=fractions)
        selection = {"selection": "all", "exclude": [str(p) for p in exclude],
                     "fractions": list(fractions)}
    folder.mkdir(parents=True, exist_ok=True)
    settings = {
        "name": name or folder.name,
        "source": Path(smiles_csv).name,
        "seed": seed,
        **selection,
        **({"target": target} if target else {}),
        **({"storage": storage} if storage else {}),
        "recipe": recipe,
    }
    write_text_atomic(folder / CAMPAIGN_FILE, yaml.safe_dump(settings, sort_keys=False))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=["name", "source", "smiles", "n_heavy", "split"],
                            extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(molecules)
    write_text_atomic(folder / MOLECULES_FILE, buf.getvalue())
    write_card(folder)
    return molecules


def work_store_path(folder: str | Path, recipe: dict) -> Path:
    """This host's working store for ``recipe`` (``work/labels-HOST-HASH.h5``, not committed):
    a changed recipe starts a new store (a store refuses a recipe it was not labeled with)."""
    digest = hashlib.sha1(yaml.safe_dump(recipe, sort_keys=True).encode()).hexdigest()[:8]
    return Path(folder) / "work" / f"labels-{socket.gethostname()}-{digest}.h5"


def load_settings(folder: str | Path) -> dict:
    """The campaign's settings: ``campaign.yaml`` of ``folder`` (``emlp campaign init``)."""
    path = Path(folder) / CAMPAIGN_FILE
    if not path.is_file():
        raise StoreError(f"{folder}: no {CAMPAIGN_FILE} (run `emlp campaign init` first)")
    return yaml.safe_load(path.read_text())


# ---------------------------------------------------------------------------------- shards
def shard_storage(storage: dict | None, folder: str | Path = "") -> dict:
    """``precision`` and ``compress`` of new shards: campaign.yaml's ``storage`` over
    :data:`DEFAULT_STORAGE`; unknown settings raise :class:`StoreError` naming ``folder``."""
    storage = dict(storage or {})
    unknown = set(storage) - set(DEFAULT_STORAGE)
    if unknown:
        raise StoreError(f"{folder}: unknown storage settings {sorted(unknown)}"
                         f" ({', '.join(DEFAULT_STORAGE)})")
    return {**DEFAULT_STORAGE, **storage}


def unexported(folder: str | Path, store: DatasetStore) -> tuple[list[int], list[dict]]:
    """What of ``store`` no shard of ``folder`` holds: the indices of its records, and its
    failures that no shard records and no record of ``store`` resolves."""
    labeled: set[str] = set()
    failed: set[str] = set()
    for path in shard_paths(folder):
        with DatasetStore(path, "r") as shard:
            labeled |= set(shard.keys())  # a retried failure's label is new
            failed |= {f["key"] for f in shard.failures()}
    keys = store.keys()
    stored = set(keys)
    new_idx = [i for i, k in enumerate(keys) if k not in labeled]
    new_fail = [f for f in store.failures()
                if f["key"] not in labeled and f["key"] not in failed and f["key"] not in stored]
    return new_idx, new_fail


def export_shard(folder: str | Path, store: DatasetStore, run_info: dict,
                 storage: dict | None = None, part: str = CAMPAIGN_PART) -> Path | None:
    """Move the records and failures of ``store`` that no shard holds into a new shard.

    Returns the new shard's path (``None`` when there is nothing new): the next number of
    ``part`` (:data:`~emlpack.data.shards.SHARD_PARTS`: ``shards/NNNN.h5`` for the campaign,
    ``shards/al-NNNN.h5`` for active learning). The shard is written in one go in the packed
    layout (:func:`~emlpack.data.store.write_packed`) under a temporary name and renamed, so a
    shard file is always complete. ``storage``: ``precision`` (``float64``, ``float32``) and
    ``compress`` of the shard file (campaign.yaml's ``storage``, over
    :data:`DEFAULT_STORAGE`).
    """
    storage = shard_storage(storage, folder)
    folder = Path(folder)
    new_idx, new_fail = unexported(folder, store)
    if not new_idx and not new_fail:
        return None
    paths = shard_paths(folder, part)
    number = int(paths[-1].stem[len(part):]) + 1 if paths else 0
    final = folder / SHARD_DIR / f"{part}{number:04d}.h5"
    refs = store.references()
    structures = [store.structure(i) for i in new_idx]
    references = {s.info["molecule_id"]: refs[s.info["molecule_id"]] for s in structures
                  if s.info.get("kind") == "hydride" and s.info["molecule_id"] in refs}
    metadata = {**{f"run_{k}": v for k, v in run_info.items()},
                "recipe": store.metadata.get("recipe", "")}
    return write_packed(final, structures, new_fail, references, metadata, **storage)


class ShardExports:
    """A labeling run's shards: the finished labels of its working store become a new shard
    of ``part`` (:func:`export_shard`) when :meth:`on_stored` finds ``shard_minutes`` passed
    and at least ``shard_min_records`` new records and failures (or the ``hours`` limit
    reached), and at every :meth:`flush` (the run's end, also on Ctrl-C or SIGTERM); each
    with the card regenerated and, with ``commit``, committed with ``commit_paths``."""

    def __init__(self, folder: Path, settings: dict, workers: int, threads: int | None, *,
                 hours: float | None, shard_minutes: float, shard_min_records: int,
                 commit: bool, commit_paths: list[Path] = (), part: str = CAMPAIGN_PART,
                 info: dict | None = None) -> None:
        self.folder, self.settings, self.part = folder, settings, part
        self.hours, self.shard_minutes = hours, shard_minutes
        self.shard_min_records, self.commit = shard_min_records, commit
        self.commit_paths = [folder / SHARD_DIR, folder / "README.md", *commit_paths]
        cpus = os.cpu_count() or 1
        self.run = {"host": socket.gethostname(), "cpus": cpus, "workers": workers,
                    "threads": threads or max(1, cpus // max(workers, 1)), **(info or {})}
        self.t0, self.last, self.since = time.time(), time.monotonic(), time.time()
        self.shards: list[Path] = []
        for tmp in (folder / SHARD_DIR).glob(".*.tmp*"):
            if time.time() - tmp.stat().st_mtime > 3600:
                tmp.unlink()  # left by a run killed while writing (never a finished file)

    def flush(self, store: DatasetStore) -> None:
        """The store's unexported labels into a new shard (nothing when there are none)."""
        now = time.time()
        info = dict(self.run, started=self.since, ended=now, wall_s=now - self.since)
        shard = export_shard(self.folder, store, info, self.settings.get("storage"),
                             part=self.part)
        if shard is None:
            return
        self.since = now  # the next shard accounts the wall time from here
        self.shards.append(shard)
        write_card(self.folder)
        log.info("%s: wrote %s", self.folder, shard)
        if self.commit:  # the folders: a shard renamed but not committed by a killed run, too
            git_commit(self.commit_paths,
                       f"{self.settings.get('name', self.folder.name)}: shard {shard.stem}")

    def on_stored(self, store: DatasetStore) -> bool:
        """After each stored label: a shard when one is due; True once ``hours`` passed."""
        over = self.hours is not None and time.time() - self.t0 > self.hours * 3600.0
        due = time.monotonic() - self.last > self.shard_minutes * 60.0
        if over or (due and sum(map(len, unexported(self.folder, store)))
                    >= self.shard_min_records):
            self.last = time.monotonic()
            self.flush(store)
        return over


def run_campaign(folder: str | Path, workers: int = 2, threads: int | None = None,
                 hours: float | None = None, shard_minutes: float = 20.0,
                 shard_min_records: int = SHARD_MIN_RECORDS,
                 commit: bool = False, progress: bool = True,
                 retry_failed: bool = False, past_target: bool = False) -> dict:
    """Label the campaign's molecules in order, into new shards every ``shard_minutes``,
    up to the ``target`` of ``campaign.yaml`` (:func:`target_prefix`) unless ``past_target``.

    Args:
        workers: labeling processes (0: in this process).
        threads: OpenMP threads per process (default: CPU count / workers).
        hours: stop after this wall time (finished labels are kept); None: until done.
        shard_minutes: how often finished labels become a shard (and a commit), once there
            are ``shard_min_records`` new records and failures; when the run stops (``hours``,
            the end of the list, Ctrl-C, SIGTERM) whatever is left becomes a last shard.
        shard_min_records: fewest new records and failures that make a shard before then
            (fewer, larger shards: each costs ~2.5 kB of HDF5 headers and a commit).
        commit: commit each new shard, the prepared molecules and the card to git.
        retry_failed: label the keys of recorded failures again (their failure records stay
            in their shards; a key that fails again is not recorded twice, one labeled now
            counts as resolved on the card).
        past_target: label every listed molecule, past the target.
    Returns a summary dict (new records, failures, shards written, wall time, ``target``).
    """
    from emlpack.qm.labeling import check_labeling_dependencies, run_labeling

    folder = Path(folder)
    settings = load_settings(folder)
    molecules = read_molecule_table(folder)
    recipe = settings["recipe"]
    check_labeling_dependencies(recipe, workers)
    for tmp in (folder / "prepared").glob(".*.tmp*"):
        if time.time() - tmp.stat().st_mtime > 3600:
            tmp.unlink()  # left by a run killed while writing (never a finished file)
    exports = ShardExports(folder, settings, workers, threads, hours=hours,
                           shard_minutes=shard_minutes, shard_min_records=shard_min_records,
                           commit=commit, commit_paths=[folder / "prepared"])
    work = work_store_path(folder, recipe)
    host = socket.gethostname()
    earlier = [folder / "work" / f"labels-{host}.h5",
               *sorted((folder / "work").glob(f"labels-{host}-*.h5"))]
    for other in (p for p in earlier if p.exists()):
        if other != work:  # labels of a run with an earlier recipe: keep the finished ones
            with DatasetStore(other, "a") as store:
                shard = export_shard(folder, store, {"host": host}, settings.get("storage"))
            if shard is not None:
                log.info("campaign %s: %s (earlier recipe) -> %s", folder, other, shard)
                if commit:
                    git_commit([folder / SHARD_DIR],
                               f"{settings.get('name', folder.name)}: shard {shard.stem}")
    done = finished_keys(folder, failures=not retry_failed)
    log.info("campaign %s: %d molecules, %d keys finished in shards; %s; hours %s, shards every"
             " %g min of at least %d records, commit %s; level %s", folder, len(molecules),
             len(done), exports.run, hours, shard_minutes, shard_min_records, commit,
             recipe.get("level"))

    order, target = campaign_target(folder, settings, molecules)
    if past_target:
        order = campaign_order(settings, molecules)
    elif settings.get("target"):
        log.info("campaign %s: target %d configurations of %d molecules: %s (the first %d"
                 " molecules of the order; --past-target labels all %d)", folder,
                 target["configurations"], target["molecules"],
                 "reached" if target["reached"] else
                 f"{target['labeled']} configurations of {target['labeled_molecules']}"
                 " molecules so far", target["prefix"], len(molecules))
    if target["reached"] and not past_target and not retry_failed:
        return {"new_records": 0, "new_failures": 0, "shards": [], "wall_s": 0.0,
                "target": target}
    sources = [(m["name"], m["smiles"]) for m in order]
    with terminate_as_interrupt():
        try:
            summary = run_labeling(sources, work, recipe, workers=workers, progress=progress,
                                   threads=threads, prep_dir=folder / "prepared",
                                   exclude_keys=done, on_stored=exports.on_stored,
                                   retry_failed=retry_failed)
        finally:  # also on Ctrl-C or SIGTERM: the finished labels become a last shard
            with DatasetStore(work, "a") as store:
                exports.flush(store)
    return {"new_records": summary.n_new, "new_failures": summary.n_failed_new,
            "shards": [str(p) for p in exports.shards], "wall_s": time.time() - exports.t0,
            "target": campaign_target(folder, settings, molecules)[1]}


def label_part(folder: str | Path, configs: list[Configuration], part: str,
               source: str, workers: int = 0, threads: int | None = None,
               hours: float | None = None, shard_minutes: float = 20.0,
               shard_min_records: int = SHARD_MIN_RECORDS, commit: bool = False,
               commit_paths: list[Path] = (), progress: bool = True) -> dict:
    """Label given configurations into a part of the campaign's data set: shards
    ``shards/PARTNNNN.h5`` (:func:`export_shard`) at the campaign's level and Foster-Boys
    starts (``campaign.yaml``'s recipe), with the card regenerated.

    Each configuration's key is ``MOLECULE/KIND/NNNN``, its molecule a row of
    ``molecules.csv``. Labels go into a working store ``work/PART-HOST-HASH.h5`` (not
    committed) through :func:`emlpack.qm.labeling.label_configurations` and become a new shard
    every ``shard_minutes`` once there are ``shard_min_records`` new records and failures, and
    at the end (also on Ctrl-C or SIGTERM), as :func:`run_campaign`'s; each committed with
    ``commit`` (with ``commit_paths``, e.g. the selection the configurations come from); keys
    that a shard of any part holds are skipped, so a re-run on any machine resumes. ``source``
    (e.g. the selection files) is stored in the shards' metadata. ``hours``: stop after this
    wall time (finished labels kept). Returns a summary (new records, failures, shards, wall
    time).
    """
    from emlpack.qm.labeling import label_configurations

    folder = Path(folder)
    if part not in SHARD_PARTS or part == CAMPAIGN_PART:
        raise StoreError(f"{folder}: shard part {part!r}: one of {SHARD_PARTS[1:]} (the"
                         " campaign labels its own)")
    settings = load_settings(folder)
    names = {m["name"] for m in read_molecule_table(folder)}
    unknown = sorted({c.molecule_id for c in configs} - names)
    if unknown:
        raise StoreError(f"{folder}: molecules {unknown[:5]} are not in {MOLECULES_FILE}")
    recipe = settings["recipe"]
    label = {"level": parse_level(recipe["level"]).name,
             "boys_starts": int(recipe.get("boys_starts", 3)), "seed": int(recipe.get("seed", 0))}
    digest = hashlib.sha1(yaml.safe_dump(dict(label, part=part), sort_keys=True).encode()
                          ).hexdigest()[:8]
    work = folder / "work" / f"{part}{socket.gethostname()}-{digest}.h5"
    work.parent.mkdir(parents=True, exist_ok=True)
    exports = ShardExports(folder, settings, workers, threads, hours=hours,
                           shard_minutes=shard_minutes, shard_min_records=shard_min_records,
                           commit=commit, commit_paths=list(commit_paths), part=part,
                           info={"source": source})

    with terminate_as_interrupt():
        try:
            summary = label_configurations(
                configs, work, label["level"], label["boys_starts"], label["seed"],
                workers=workers, threads=threads, progress=progress,
                exclude_keys=finished_keys(folder), on_stored=exports.on_stored,
                metadata={"recipe": yaml.safe_dump(dict(label, part=part, source=source),
                                                   sort_keys=True)})
        finally:  # also on Ctrl-C or SIGTERM: the finished labels become a last shard
            with DatasetStore(work, "a") as store:
                exports.flush(store)
    return {"new_records": summary.n_new, "new_failures": summary.n_failed_new,
            "skipped_done": summary.n_skipped_done,
            "shards": [str(p) for p in exports.shards], "wall_s": time.time() - exports.t0}


# ---------------------------------------------------------------------------------- card
def campaign_statistics(folder: str | Path) -> dict:
    """Counts, failures, wall time and throughput measured from the shards: the campaign's
    own (:data:`~emlpack.data.shards.CAMPAIGN_PART`), and under ``active_learning`` (None
    without) those of the active-learning part."""
    data = read_shards(folder)
    settings = load_settings(folder)
    per_molecule = samples_per_molecule(settings["recipe"])
    own = {str(p) for p in shard_paths(folder, CAMPAIGN_PART)}
    structures = [s for s in data.structures if s.source.rsplit(",", 1)[0] in own]
    extra = [s for s in data.structures if s.source.rsplit(",", 1)[0] not in own]
    shard_meta = [(p, m) for p, m in zip(data.shards, data.metadata, strict=True)
                  if str(p) in own]
    counts = {k: 0 for k in SPLITS}
    configs_of: dict[str, int] = {}
    for s in structures:
        name = str(s.info["molecule_id"])
        configs_of[name] = configs_of.get(name, 0) + 1
        counts[data.split_of.get(name, "train")] += 1
    mols = {k: sum(1 for m in data.molecules if m["split"] == k and m["name"] in configs_of)
            for k in SPLITS}
    complete = sum(1 for v in configs_of.values() if v == per_molecule)
    wall = sum(float(m.get("run_wall_s", 0.0)) for _, m in shard_meta)
    # per-configuration cost by size (atoms including the dimer probe)
    by_size: dict[str, list[float]] = {}
    for s in structures:
        n = len(s.numbers)
        bucket = f"{(n - 1) // 5 * 5 + 1}-{(n - 1) // 5 * 5 + 5}"
        by_size.setdefault(bucket, []).append(float(s.info.get("wall_time", np.nan)))
    fields: dict[str, dict] = {}
    per_shard = Counter(s.source.rsplit(",", 1)[0] for s in structures)
    for path, meta in shard_meta:
        stored = yaml.safe_load(str(meta.get("recipe") or "")) or {}
        name = stored.get("field_distribution", LEGACY_FIELD_DISTRIBUTION)
        entry = fields.setdefault(name, {"configurations": 0, "shards": []})
        entry["configurations"] += per_shard.get(str(path), 0)
        entry["shards"].append(path.stem)
    labeled = {str(s.info.get("key", "")) for s in data.structures}
    labeled |= {str(h.info.get("key", "")) for h in (data.hydrides or {}).get("structures", [])}
    extra_keys = finished_keys(folder, True, ACTIVE_LEARNING_PART)
    failures = [f for f in data.failures if f["key"] not in extra_keys]
    unresolved = [f for f in failures if f["key"] not in labeled]
    reasons: dict[str, int] = {}
    for f in unresolved:
        reason = f["reason"].split(":")[0][:80]
        reasons[reason] = reasons.get(reason, 0) + 1
    return {
        "n_configurations": len(structures),
        "configurations_by_split": counts,
        "molecules_by_split": mols,
        "molecules_labeled": len(configs_of),
        "molecules_complete": complete,
        "molecules_listed": len(data.molecules),
        "hydrides": sorted(h.info["molecule_id"] for h in data.hydrides["structures"])
        if data.hydrides else [],
        "n_failures": len(unresolved),
        "n_failures_resolved": len(failures) - len(unresolved),
        "failure_reasons": reasons,
        "field_distributions": fields,
        "n_shards": len(shard_meta),
        "wall_hours": wall / 3600.0,
        "configurations_per_hour": len(structures) / (wall / 3600.0) if wall > 0 else None,
        "seconds_per_configuration_by_atoms": {
            k: {"n": len(v), "median": float(np.nanmedian(v)) if np.isfinite(v).any()
                else float("nan")}
            for k, v in sorted(by_size.items(), key=lambda kv: int(kv[0].split("-")[0]))
        },
        "layouts": sorted({f"{m.get('run_workers')} workers x {m.get('run_threads')} threads"
                           f" on {m.get('run_cpus')} CPUs" for _, m in shard_meta}),
        "active_learning": part_statistics(folder, data, ACTIVE_LEARNING_PART, extra,
                                           [f for f in data.failures if f["key"] in extra_keys]),
    }


def part_statistics(folder: str | Path, data: ShardedData, part: str,
                    structures: list[Structure], failures: list[dict]) -> dict | None:
    """The card's counts of one extra shard part (None when it has no shard): its
    configurations and molecules by split, shards, unresolved failures, labeling wall time,
    and the selection files in ``FOLDER/active-learning/``."""
    paths = shard_paths(folder, part)
    if not paths:
        return None
    names = {str(p) for p in paths}
    meta = [m for p, m in zip(data.shards, data.metadata, strict=True) if str(p) in names]
    by_split = {k: 0 for k in SPLITS}
    molecules: set[str] = set()
    for s in structures:
        name = str(s.info["molecule_id"])
        molecules.add(name)
        by_split[data.split_of.get(name, "train")] += 1
    labeled = {str(s.info.get("key", "")) for s in structures}
    return {
        "n_configurations": len(structures), "molecules": len(molecules),
        "configurations_by_split": by_split, "shards": [p.name for p in paths],
        "n_failures": sum(1 for f in failures if f["key"] not in labeled),
        "wall_hours": sum(float(m.get("run_wall_s", 0.0)) for m in meta) / 3600.0,
        "selections": sorted(p.name for p in (Path(folder) / ACTIVE_LEARNING_DIR).glob("*.xyz")),
    }


def active_learning_lines(stats: dict | None) -> list[str]:
    """The card's line on the active-learning part (none without one)."""
    if not stats:
        return []
    held_out = stats["configurations_by_split"]["val"] + stats["configurations_by_split"]["test"]
    shards = stats["shards"]
    return [f"- active learning: {stats['n_configurations']} configurations of"
            f" {stats['molecules']} training molecules"
            + (f" (and {held_out} of validation or test molecules: an error)" if held_out
               else "")
            + f" in {len(shards)} shards (`{SHARD_DIR}/{shards[0]}`-`{shards[-1]}`), picked"
            " from MD of the models by ensemble spread and by the MD watchdog's failures"
            f" ({', '.join(f'`{ACTIVE_LEARNING_DIR}/{s}`' for s in stats['selections'])}:"
            " each configuration's molecule, temperature, field, time, spread and reason),"
            f" labeled at the same level; failures: {stats['n_failures']}; labeling wall time"
            f" {stats['wall_hours']:.2f} h; not in the counts above;"]


def target_lines(folder: str | Path, settings: dict, molecules: list[dict]) -> list[str]:
    """The card's line on the target of ``campaign.yaml`` (none without one)."""
    if not settings.get("target"):
        return []
    _, t = campaign_target(folder, settings, molecules)
    state = ("reached" if t["reached"] else
             f"not reached yet ({t['labeled']} configurations of {t['labeled_molecules']}"
             " molecules)")
    return [f"- target ({CAMPAIGN_FILE}): {t['configurations']} configurations of"
            f" {t['molecules']} molecules, {state}; `emlp campaign run` labels the first"
            f" {t['prefix']} molecules of the order and stops there (`--past-target`: all"
            f" {len(molecules)});"]


def level_lines(recipe: dict) -> list[str]:
    """The card's lines on the labeling level: the paper's, or a cheap one named as such."""
    level = parse_level(recipe["level"])
    boys = (f"field, Foster-Boys centres (lowest spread of {recipe.get('boys_starts', 3)}"
            " stabilised starts);")
    if level == PAPER:
        return [f"- labels: {recipe['level']} level = PBE0/aug-cc-pVTZ with density fitting",
                "  (aug-cc-pVTZ-JKFIT), restricted Kohn-Sham, PySCF; energy, analytic forces"
                " under the", f"  {boys}"]
    return [f"- labels: **{level.name}** (DFT grid level {level.grid_level}, SCF tolerance"
            f" {level.conv_tol:g} Eh), a cheap level for pretraining, preparation and tests:"
            " **not the paper's level** (PBE0/aug-cc-pVTZ); restricted Kohn-Sham, PySCF"
            " with density fitting; energy, analytic forces under the", f"  {boys}"]


def order_lines(settings: dict, n_split: dict, test: list[str]) -> list[str]:
    """The card's lines on the molecule order and split."""
    counts = (f"- split by molecule (fixed before labeling, `{MOLECULES_FILE}`):"
              f" {n_split['train']} train, {n_split['val']} validation, {n_split['test']} test")
    if settings.get("selection") == "all":
        exclude = ", ".join(f"`{e}`" for e in settings.get("exclude", []))
        return [f"- molecules: every sulfur-free closed-shell molecule of the source except"
                f" rows 0-9, the IR test molecules and the validation and test molecules of"
                f" {exclude}, compared by molecular graph (canonical SMILES without stereo),"
                f" in a random order drawn with seed {settings['seed']}, labeled in that"
                " order with the splits interleaved at their shares (any prefix is a sample of"
                " the whole);", counts + ";"]
    return ["- order: every molecule with 2-5 heavy atoms, then the IR test molecules missing"
            f" from the source, then {settings['n_large']} molecules with 6-7 heavy atoms drawn"
            f" with seed {settings['seed']}; labeled in this order, except that the validation"
            " and test molecules of each block (2-5 heavy atoms; the rest) are labeled before"
            " that block's training ones (in the second block since 2026-11-26, after shard"
            " 0114; the molecules labeled before that are in list order);",
            counts + "; the IR molecules aziridine and 3-(methylamino)but-2-enal are in test;",
            f"- test molecules: {', '.join(test)}."]


def notes_text(folder: str | Path) -> str:
    """``FOLDER/notes.md`` as the card shows it: each ``<!-- include: PATH -->`` line
    (:data:`INCLUDE_RE`, PATH relative to the folder) replaced by that file's text, or by a
    line saying it is not written yet."""
    folder = Path(folder)
    out = []
    for line in (folder / NOTES_FILE).read_text().strip().splitlines():
        match = INCLUDE_RE.match(line)
        if match is None:
            out.append(line)
            continue
        path = folder / match.group(1)
        out.append(path.read_text().strip() if path.is_file()
                   else f"*(`{match.group(1)}`: not written yet)*")
    return "\n".join(out)


def write_card(folder: str | Path) -> Path:
    """Regenerate ``FOLDER/README.md`` from ``campaign.yaml``, ``molecules.csv`` and shards."""
    folder = Path(folder)
    settings = load_settings(folder)
    molecules = read_molecule_table(folder)
    stats = campaign_statistics(folder)
    recipe = settings["recipe"]
    n_split = {k: sum(1 for m in molecules if m["split"] == k) for k in SPLITS}
    samples = ", ".join(f"{s['count']} × {s['kind']}" for s in recipe["samples"])
    test = [f"{m['name']} ({m['smiles']})" for m in molecules if m["split"] == "test"]
    lines = [
        f"# {settings.get('name', folder.name)}: a labeled data set of QM7 molecules",
        "",
        "Generated by `emlp campaign` (`emlpack.qm.campaign`); do not edit by hand.",
        "Read it with `emlpack.data.shards.read_shards(folder)` or train on the folder",
        "(`emlp train CONFIG data.path=FOLDER`; the split below is used by molecule).",
        "",
        "## Level and recipe",
        "",
        *level_lines(recipe),
        f"- preparation (geometry and Hessian for the normal modes only, never labels):"
        f" {recipe['prepare']['level']} (tblite), BFGS to {recipe['prepare']['fmax']} eV/Å;",
        f"- per molecule: {samples} (the paper's 100 : 100 : 150 : 150 proportions), each"
        f" with a random field of up to {recipe['field_max_au']} au"
        f" ({FIELD_TEXT[recipe.get('field_distribution', LEGACY_FIELD_DISTRIBUTION)]});"
        f" recipe seed {recipe.get('seed', 0)};",
        "- hydride references H2, CH4, NH3, H2O at the labeling level (kind `hydride`).",
        "",
        "## Molecules and split",
        "",
        f"- source: `{settings['source']}` (QM7 SMILES), sulfur-free; rows 0-9 never labeled"
        " (0-4 and 7: the authors' DFT data, a second test set; 5, 6, 8, 9: reserved for an"
        " independent check);",
        *order_lines(settings, n_split, test),
        "",
        "## Counts (measured from the shards)",
        "",
        f"- {stats['n_configurations']} configurations of {stats['molecules_labeled']}"
        f" molecules ({stats['molecules_complete']} complete) out of"
        f" {stats['molecules_listed']} listed, in {stats['n_shards']} shards;",
        "- by split: " + ", ".join(
            f"{k} {stats['configurations_by_split'][k]} configurations /"
            f" {stats['molecules_by_split'][k]} molecules" for k in SPLITS) + ";",
        *target_lines(folder, settings, molecules),
        *active_learning_lines(stats["active_learning"]),
        f"- hydride references: {', '.join(stats['hydrides']) or 'none yet'};",
        *([f"- fields: {v['configurations']} configurations {FIELD_TEXT[k]} (shards"
           f" {v['shards'][0]}-{v['shards'][-1]})" + ("" if k == "ball" else
           ", the recipes before 2026-11-25; the authors' data, and emlpack since, draw"
           " uniformly in the ball") + ";"
           for k, v in stats["field_distributions"].items()]
          if len(stats["field_distributions"]) > 1 else []),
        f"- failures: {stats['n_failures']}"
        + ("" if not stats["failure_reasons"] else " (" + "; ".join(
            f"{v} × {k}" for k, v in stats["failure_reasons"].items()) + ")")
        + (f"; {stats['n_failures_resolved']} earlier failures labeled on a retry"
           " (`--retry-failed`)" if stats["n_failures_resolved"] else "") + ";",
        f"- labeling wall time: {stats['wall_hours']:.2f} h"
        + (f", {stats['configurations_per_hour']:.1f} configurations per hour"
           if stats["configurations_per_hour"] else "")
        + (f" ({'; '.join(stats['layouts'])})" if stats["layouts"] else "") + ".",
        "",
        "Seconds per configuration (one labeling process) by number of atoms (with the probe):",
        "",
        "| atoms | configurations | median s |",
        "|---|---|---|",
    ]
    for k, v in stats["seconds_per_configuration_by_atoms"].items():
        lines.append(f"| {k} | {v['n']} | {v['median']:.0f} |")
    storage = shard_storage(settings.get("storage"), folder)
    notes = folder / NOTES_FILE
    if notes.is_file():  # measurements written by hand (level choice, pilot), kept verbatim
        lines += ["", notes_text(folder)]
    lines += ["", "## Files", "",
              f"`{CAMPAIGN_FILE}` settings and recipe; `{MOLECULES_FILE}` the list and split;",
              f"`{SHARD_DIR}/NNNN.h5` labels (emlpack HDF5 stores, never rewritten;"
              f" {shards_size_text(folder)}; new shards: {storage['precision']} positions and"
              f" forces{', gzip' if storage['compress'] else ''}, packed layout);",
              *([f"`{SHARD_DIR}/{ACTIVE_LEARNING_PART}NNNN.h5` the active-learning labels and"
                 f" `{ACTIVE_LEARNING_DIR}/*.xyz` the selections they were labeled from (never"
                 " rewritten);"] if stats["active_learning"] else []),
              "`prepared/NAME.npz` the prepared geometry and Hessian of each molecule"
              + (f"; `{NOTES_FILE}` the notes above." if notes.is_file() else "."), ""]
    path = folder / "README.md"
    write_text_atomic(path, "\n".join(lines))
    return path
