"""Trained models as users load them: one checkpoint or an ensemble, on the DFT energy scale.

A checkpoint written by the trainer holds the model and, in its metadata, the reference it was
trained against (:mod:`emlpack.data.references`) and the elements of its training set. A model
trained with the hydride reference predicts energies relative to its *own* hydrides,

    E_rel(s) = U(s) - sum_i c_i(s) U_i        (U_i: the model's hydride energies)

and the DFT-scale energy a user compares with a PySCF number adds the DFT hydride energies back:

    E(s) = E_rel(s) + sum_i c_i(s) E_i^DFT = U(s) + c(s) . (E^DFT - U_hyd)

with ``U_hyd`` evaluated at the stored hydride cores and centres, exactly as in training and in
the evaluation tables. For a fixed composition this is a constant shift: forces, dipoles and
every response are unchanged. :class:`ModelEnsemble` holds one or more such members; with
several, properties are averaged and their spread across members is the uncertainty, and
:class:`SpreadThresholds` say when that spread is large: calibrated on held-out molecules when
the members carry a calibration (:mod:`emlpack.calculators.calibration`, stored by
:func:`emlpack.pretrained.export_pretrained`), heuristic otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from emlpack.data.references import (
    HydrideReference,
    hydride_coefficients,
    reference_from_metadata,
)
from emlpack.errors import BrokenResultError, EmlpackError
from emlpack.nn.checkpoint import load_model, read_checkpoint
from emlpack.nn.potential import EMLP, for_evaluation

_T = TypeVar("_T")

#: heuristic thresholds of the ensemble spread, for ensembles without a calibration
ENERGY_SPREAD_WARNING = 0.02  # eV/atom
FORCE_SPREAD_WARNING = 0.5  # eV/Å, largest component


class EnsembleError(EmlpackError, ValueError):
    """Models that cannot form an ensemble, or a structure outside what they can describe."""


@dataclass
class ModelMember:
    """One trained model.

    Attributes:
        model: the network (evaluation mode).
        reference: the training reference, or None (e.g. a converted or untrained model).
        elements: atomic numbers of the cores in the training set, or None when unknown.
        source: where it was loaded from.
        notice: what every calculation with this model should say, from its metadata (e.g. a
            preliminary pretrained model's measured errors), or None.
        max_heavy_atoms: heavy atoms of the largest molecule in the training set
            (:func:`emlpack.data.dataset.training_domain`), or None when unknown.
        spread_calibration: the spread thresholds of the ensemble this model was shipped in
            (:func:`emlpack.calculators.calibration.calibrate_spread`), or None.
    """

    model: EMLP
    reference: object | None = None
    elements: tuple[int, ...] | None = None
    source: str = "<memory>"
    notice: str | None = None
    max_heavy_atoms: int | None = None
    spread_calibration: dict | None = None
    _hydride_delta: np.ndarray | None = field(default=None, repr=False)

    def hydride_delta(self) -> np.ndarray | None:
        """``E^DFT - U_hyd`` (eV) per hydride, or None without a hydride reference."""
        if not isinstance(self.reference, HydrideReference):
            return None
        if self._hydride_delta is None:
            dtype = next(self.model.parameters()).dtype
            u = np.array([float(self.model.evaluate(s, dtype=dtype)["energy"])
                          for s in self.reference.structures])
            self._hydride_delta = self.reference.energies - u
        return self._hydride_delta

    def dft_shift(self, numbers: np.ndarray | Sequence[int], charge: float = 0.0) -> float:
        """Energy (eV) added to the model energy to put it on the DFT scale (0 without one)."""
        delta = self.hydride_delta()
        if delta is None:
            return 0.0
        return float(hydride_coefficients(np.asarray(numbers), self.source, charge) @ delta)

    def relative_shift(self, numbers: np.ndarray | Sequence[int],
                       charge: float = 0.0) -> float:
        """Energy (eV) added to the model energy to give the trained (relative) scale."""
        delta = self.hydride_delta()
        if delta is None:
            return 0.0
        c = hydride_coefficients(np.asarray(numbers), self.source, charge)
        return float(c @ (delta - self.reference.energies))


def load_member(path: str | Path, dtype: torch.dtype = torch.float64) -> ModelMember:
    """A checkpoint as a :class:`ModelMember` (reference, elements and largest training
    molecule from its metadata)."""
    meta = read_checkpoint(path).get("metadata", {}) or {}
    model = load_model(path, dtype).eval()
    reference = reference_from_metadata(meta["reference"]) if "reference" in meta else None
    elements = meta.get("elements")
    if elements is None and isinstance(reference, HydrideReference):
        elements = (1, 6, 7, 8)
    size = meta.get("max_heavy_atoms")
    return ModelMember(model, reference, None if elements is None else tuple(map(int, elements)),
                       str(path), meta.get("notice") or None,
                       None if size is None else int(size), meta.get("spread_calibration"))


@dataclass(frozen=True)
class SpreadThresholds:
    """When the spread across an ensemble's members is large enough to warn.

    Attributes:
        energy: energy spread (population std over members) per atom, eV/atom.
        forces: largest spread of a force component, eV/Å.
        basis: how they were set (the calibration's set and quantile, or "heuristic").
    """

    energy: float = ENERGY_SPREAD_WARNING
    forces: float = FORCE_SPREAD_WARNING
    basis: str = "heuristic"

    @classmethod
    def calibrated(cls, calibration: dict, n_members: int) -> SpreadThresholds:
        """The thresholds of a calibration record
        (:func:`emlpack.calculators.calibration.calibrate_spread`) for ``n_members`` members:
        with n members of an ensemble calibrated with N (some left out) they scale as the
        expected population spread, by sqrt(((n-1)/n) / ((N-1)/N))."""
        n, size = int(n_members), int(calibration["members"])
        scale = float(np.sqrt(((n - 1) / n) / ((size - 1) / size)))
        basis = (f"calibrated: exceeded on {1 - calibration['quantile']:.0%} of"
                 f" {calibration['configurations']} configurations of {calibration['set']}"
                 + (f", scaled to {n} of {size} members" if n != size else ""))
        return cls(scale * float(calibration["energy_eV_per_atom"]),
                   scale * float(calibration["forces_eV_per_A"]), basis)

    def warnings(self, n_atoms: int, energy_std: float,
                 forces_std: np.ndarray | None = None) -> list[str]:
        """The warnings for an ensemble result: ``energy_std`` (eV, whole structure),
        ``forces_std`` (eV/Å, any shape; None: not checked)."""
        out = []
        per_atom = float(energy_std) / max(n_atoms, 1)
        if per_atom > self.energy:
            out.append(f"ensemble energy spread {per_atom:.3f} eV/atom exceeds"
                       f" {self.energy:.3g} eV/atom ({self.basis}): outside the models'"
                       " domain?")
        if forces_std is not None:
            largest = float(np.max(forces_std, initial=0.0))
            if largest > self.forces:
                out.append(f"ensemble force spread {largest:.3f} eV/Å exceeds"
                           f" {self.forces:.3g} eV/Å ({self.basis}): outside the models'"
                           " domain?")
        return out


def spread_thresholds(members: Sequence[ModelMember]) -> SpreadThresholds:
    """The members' calibrated thresholds when they all carry the same calibration (an
    ensemble shipped together; :meth:`SpreadThresholds.calibrated`), else the heuristic ones."""
    calibrations = [m.spread_calibration for m in members]
    first = calibrations[0]
    if not first or len(members) < 2 or any(c != first for c in calibrations[1:]):
        return SpreadThresholds()
    return SpreadThresholds.calibrated(first, len(members))


class ModelEnsemble:
    """One or more :class:`ModelMember` of the same kind (all with a hydride reference, or
    all without); the DFT scale is used when every member has one."""

    def __init__(self, members: Sequence[ModelMember], name: str = "") -> None:
        members = list(members)
        if not members:
            raise EnsembleError("an ensemble needs at least one model")
        kinds = {isinstance(m.reference, HydrideReference) for m in members}
        if len(kinds) > 1:
            raise EnsembleError(
                "ensemble members disagree: some were trained with the hydride reference and"
                " some not (" + ", ".join(m.source for m in members) + ")")
        self.members = members
        self.name = name or (members[0].source if len(members) == 1 else "ensemble")

    def __len__(self) -> int:
        return len(self.members)

    @property
    def dft_scale(self) -> bool:
        """True when energies are reported on the DFT scale (hydride references known)."""
        return isinstance(self.members[0].reference, HydrideReference)

    @property
    def elements(self) -> set[int] | None:
        """Elements every member was trained on (None when unknown)."""
        sets = [set(m.elements) for m in self.members if m.elements is not None]
        return set.intersection(*sets) if sets else None

    @property
    def notices(self) -> list[str]:
        """The members' notices (e.g. a preliminary model's measured errors), each once."""
        return list(dict.fromkeys(m.notice for m in self.members if m.notice))

    @property
    def max_heavy_atoms(self) -> int | None:
        """The largest training molecule (heavy atoms) that every member has seen, or None
        when no member records it."""
        sizes = [m.max_heavy_atoms for m in self.members if m.max_heavy_atoms is not None]
        return min(sizes) if sizes else None

    @property
    def spread_thresholds(self) -> SpreadThresholds:
        """When the members' spread is large (:func:`spread_thresholds`)."""
        return spread_thresholds(self.members)

    def domain_warnings(self, numbers: np.ndarray | Sequence[int], positions: np.ndarray,
                        periodic: bool = False) -> list[str]:
        """Warnings for a structure (atomic numbers, core positions in Å) outside what the
        members were trained on: elements outside the training set, and a molecule with more
        heavy atoms than the largest training molecule (:func:`emlpack.bonding.
        largest_molecule`; molecules only). Empty when inside, or when unrecorded."""
        from emlpack.bonding import largest_molecule

        out = []
        unknown = self.unknown_elements(numbers)
        if unknown:
            out.append(f"element(s) Z={unknown} are outside the models' training set"
                       f" (Z={sorted(self.elements)})")
        limit = self.max_heavy_atoms
        if limit is not None and not periodic:
            size = largest_molecule(numbers, positions)
            if size > limit:
                out.append(f"a molecule of {size} heavy atoms: the models' training molecules"
                           f" have at most {limit}, so expect larger errors than measured on"
                           " them")
        return out

    def unknown_elements(self, numbers: np.ndarray | Sequence[int]) -> list[int]:
        """Atomic numbers in ``numbers`` outside the training set (empty when unknown)."""
        known = self.elements
        if known is None:
            return []
        return sorted(set(np.asarray(numbers).tolist()) - known)

    def to(self, dtype: torch.dtype) -> ModelEnsemble:
        """A copy with every model in ``dtype`` and evaluation mode (the members given are not
        changed)."""
        out = [replace(m, model=for_evaluation(m.model, dtype)) for m in self.members]
        return ModelEnsemble(out, self.name)


def as_ensemble(
    model: EMLP | ModelMember | ModelEnsemble | str | Path
    | Sequence[EMLP | ModelMember | ModelEnsemble | str | Path],
    dtype: torch.dtype = torch.float64,
) -> ModelEnsemble:
    """An :class:`EMLP`, checkpoint path, pretrained name, folder, list of those, or an
    ensemble, as a :class:`ModelEnsemble` in ``dtype``."""
    if isinstance(model, ModelEnsemble):
        return model.to(dtype)
    if isinstance(model, EMLP):
        return ModelEnsemble([ModelMember(model)]).to(dtype)
    if isinstance(model, ModelMember):
        return ModelEnsemble([model]).to(dtype)
    if isinstance(model, (str, Path)):
        from emlpack.pretrained import resolve_model

        paths, name = resolve_model(model)
        return ModelEnsemble([load_member(p, dtype) for p in paths], name)
    if isinstance(model, Sequence):
        members = []
        for item in model:
            members.extend(as_ensemble(item, dtype).members)
        return ModelEnsemble(members)
    raise EnsembleError(f"cannot use {type(model).__name__} as a model")


def load_pretrained(name: str, dtype: torch.dtype = torch.float64,
                    root: Path | None = None) -> ModelEnsemble:
    """The pretrained ensemble ``name`` (see :mod:`emlpack.pretrained`) as a
    :class:`ModelEnsemble` in ``dtype``."""
    from emlpack.pretrained import resolve_model

    files, label = resolve_model(name, root)
    return ModelEnsemble([load_member(p, dtype) for p in files], label)


# ------------------------------------------------------------------ statistics over members
#: the fewest sound members of an ensemble whose mean and spread are reported
MIN_SOUND_MEMBERS = 2


def sound_members(problems: Sequence[str], labels: Sequence[str], where: str = "") -> list[int]:
    """Indices of the members whose result is sound (``problems[k]`` empty: e.g. a relaxation
    that converged to a minimum) and so enter a reported mean; the others are left out, as a
    failed relaxation is. Raises :class:`~emlpack.errors.BrokenResultError` naming each
    problem when the single model's result is broken, or fewer than
    :data:`MIN_SOUND_MEMBERS` of an ensemble's are sound (a mean of one is no ensemble
    result, and most members failing says the structure is outside the models' reach)."""
    keep = [k for k, p in enumerate(problems) if not p]
    if len(keep) == len(problems):
        return keep
    prefix = f"{where}: " if where else ""
    if len(problems) == 1:
        raise BrokenResultError(f"{prefix}no result to report: {problems[0]}")
    if len(keep) < MIN_SOUND_MEMBERS:
        broken = "; ".join(f"{labels[k]}: {p}" for k, p in enumerate(problems) if p)
        raise BrokenResultError(
            f"{prefix}no result to report: {len(keep)} of {len(problems)} models sound, at"
            f" least {MIN_SOUND_MEMBERS} needed ({broken})")
    return keep

def member_mean(objects: Sequence[_T]) -> _T:
    """The field-wise mean of dataclass results of the members (arrays and floats averaged,
    ``None`` kept), an object of the same type: e.g. the ensemble's polarizability tensor."""
    import dataclasses

    first = objects[0]
    values = {}
    for f in dataclasses.fields(first):
        items = [getattr(o, f.name) for o in objects]
        values[f.name] = None if items[0] is None else np.mean(np.asarray(items, float), axis=0)
        if isinstance(items[0], float):
            values[f.name] = float(values[f.name])
    return type(first)(**values)


def member_spread(records: Sequence[dict]) -> dict:
    """``KEY_std``: the standard deviation across members (as ``EMLPCalculator``'s
    ``*_std``) of every numeric entry of the members' result dicts that has one shape in all."""
    out = {}
    for key in records[0]:
        try:
            values = np.asarray([r[key] for r in records], dtype=float)
        except (KeyError, TypeError, ValueError):
            continue  # text, None, ragged or missing in a member: no spread
        out[f"{key}_std"] = np.std(values, axis=0).tolist()
    return out
