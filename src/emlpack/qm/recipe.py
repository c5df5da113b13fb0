"""Sampling recipes (YAML) and the configurations they generate for one molecule.

The default is the paper's eQM7 recipe, per molecule: 100 NMS@600K, 100 NMS@800K,
150 NMS@800K + torsion and 150 NMS@800K + dimer, each with a random field up to 0.01 au
(uniform in the ball, as in the authors' data; a stored recipe without ``field_distribution``
was drawn with ``magnitude``, see :data:`emlpack.qm.sampling.FIELD_DISTRIBUTIONS`).
Every configuration has a stable key ``<molecule>/<kind>/<index>`` and its own random stream
(seeded by the recipe seed, the molecule name, the kind and the index), so a resumed run
regenerates exactly the configurations it skipped.
"""

from __future__ import annotations

import copy
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from emlpack.overrides import apply_overrides, load_yaml
from emlpack.qm.sampling import (
    FIELD_DISTRIBUTIONS,
    Molecule,
    SamplingError,
    dimer_sample,
    normal_mode_sample,
    normal_modes,
    random_field,
    torsion_sample,
)

#: the field distribution of a recipe that names none (recipes written before the key existed)
LEGACY_FIELD_DISTRIBUTION = "magnitude"

DEFAULT_RECIPE_YAML = """\
# emlp label recipe: the paper's eQM7 sampling (per molecule)
level: paper              # labeling level: preset (paper, quick, tiny) or xc/basis
prepare:
  level: null             # level of the optimisation and Hessian; null = the labeling level
  optimize: true          # optimise the RDKit geometry before the Hessian
  fmax: 0.01              # eV/Å
field_max_au: 0.01        # random homogeneous field of at most field_max_au (au)
field_distribution: ball  # uniform in that ball, as the authors' data (magnitude: |E| uniform)
dimer:
  probes: [CH4, NH3, H2O]
  d_min: 0.9              # Å, closest intermolecular distance
  d_max: 6.0
samples:
  - {kind: nms600, count: 100, temperature: 600}
  - {kind: nms800, count: 100, temperature: 800}
  - {kind: nms800-torsion, count: 150, temperature: 800, torsion: true}
  - {kind: nms800-dimer, count: 150, temperature: 800, dimer: true}
boys_starts: 3
hydrides: true            # label H2, CH4, NH3, H2O at the same level as references
seed: 0
"""


def default_recipe() -> dict:
    """The paper's recipe as a dict."""
    return yaml.safe_load(DEFAULT_RECIPE_YAML)


def load_recipe(path: str | Path | None = None, overrides: list[str] | None = None,
                samples_per_molecule: int | None = None) -> dict:
    """Recipe from YAML (missing keys from the default), with ``key=value`` overrides.

    Overrides use dotted keys and YAML values, e.g. ``level=tiny``, ``prepare.optimize=false``.
    ``samples_per_molecule`` rescales the counts proportionally (largest remainders).
    """
    recipe = default_recipe()
    if path is not None:
        path = Path(path)
        try:
            user = load_yaml(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise SamplingError(f"{path}: cannot read recipe: {exc}") from None
        if not isinstance(user, dict):
            raise SamplingError(f"{path}: a recipe must be a YAML mapping")
        _merge(recipe, user)
    apply_overrides(recipe, overrides or [])
    if samples_per_molecule is not None:
        recipe["samples"] = rescale_counts(recipe["samples"], samples_per_molecule)
    validate_recipe(recipe)
    return recipe


def _merge(base: dict, extra: dict) -> None:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = copy.deepcopy(value)


def rescale_counts(samples: list[dict], total: int) -> list[dict]:
    """Scale the sample counts to sum to ``total`` (largest-remainder rounding)."""
    counts = np.array([s["count"] for s in samples], dtype=float)
    exact = counts / counts.sum() * total
    out = np.floor(exact).astype(int)
    for i in np.argsort(-(exact - out), kind="stable")[: total - out.sum()]:
        out[i] += 1
    return [dict(s, count=int(c)) for s, c in zip(samples, out, strict=True)]


def validate_recipe(recipe: dict) -> None:
    """Refuse (:class:`SamplingError`) a sample without ``kind`` and ``count``, a duplicate kind or
    one containing ``/``, a negative count or temperature, ``field_max_au`` outside
    [0, 0.05] au, or an unknown ``field_distribution``."""
    kinds = set()
    for s in recipe.get("samples", []):
        if "kind" not in s or "count" not in s:
            raise SamplingError(f"recipe sample {s}: needs 'kind' and 'count'")
        if s["kind"] in kinds or "/" in s["kind"]:
            raise SamplingError(f"recipe sample kind {s['kind']!r}: duplicate or contains '/'")
        kinds.add(s["kind"])
        if s.get("temperature", 0) < 0 or s["count"] < 0:
            raise SamplingError(f"recipe sample {s}: negative count or temperature")
    if not 0 <= float(recipe.get("field_max_au", 0.0)) <= 0.05:
        raise SamplingError("field_max_au must be in [0, 0.05] au")
    if recipe.get("field_distribution", LEGACY_FIELD_DISTRIBUTION) not in FIELD_DISTRIBUTIONS:
        raise SamplingError(f"field_distribution must be one of {', '.join(FIELD_DISTRIBUTIONS)}")


@dataclass
class Configuration:
    """One configuration to label: key, molecule, kind, nuclei (Å), field (V/Å)."""

    key: str
    molecule_id: str
    kind: str
    numbers: np.ndarray
    positions: np.ndarray
    field: np.ndarray
    charge: float = 0.0


def sample_rng(seed: int, molecule: str, kind: str, index: int) -> np.random.Generator:
    """The random stream of one configuration (independent of run order)."""
    return np.random.default_rng(
        [int(seed), zlib.crc32(molecule.encode()), zlib.crc32(kind.encode()), int(index)]
    )


def configurations(molecule: Molecule, recipe: dict, probes: dict[str, Molecule] | None = None,
                   skip: set[str] | None = None) -> list[Configuration]:
    """All configurations of ``recipe`` for a prepared molecule, except keys in ``skip``."""
    if molecule.hessian is None:
        raise SamplingError(f"{molecule.name}: not prepared (no Hessian)")
    skip = skip or set()
    modes = normal_modes(molecule.numbers, molecule.positions, molecule.hessian)
    probe_modes = {
        name: normal_modes(p.numbers, p.positions, p.hessian) for name, p in (probes or {}).items()
    }
    dimer = recipe.get("dimer", {})
    out = []
    for spec in recipe["samples"]:
        kind = spec["kind"]
        for i in range(int(spec["count"])):
            key = f"{molecule.name}/{kind}/{i:04d}"
            if key in skip:
                continue
            rng = sample_rng(recipe.get("seed", 0), molecule.name, kind, i)
            t = float(spec.get("temperature", 0.0))
            pos = molecule.positions.copy()
            if t > 0:
                pos = normal_mode_sample(molecule.numbers, molecule.positions, molecule.hessian,
                                         t, rng, modes=modes).positions
            if spec.get("torsion"):
                pos, _ = torsion_sample(molecule, pos, rng)
            numbers = molecule.numbers
            if spec.get("dimer"):
                if not probes:
                    raise SamplingError(f"recipe kind {kind!r} needs dimer probes")
                names = [n for n in dimer.get("probes", list(probes)) if n in probes]
                probe = probes[names[int(rng.integers(len(names)))]]
                ppos = probe.positions
                if t > 0:
                    ppos = normal_mode_sample(probe.numbers, probe.positions, probe.hessian, t,
                                              rng, modes=probe_modes[probe.name]).positions
                placed, _ = dimer_sample(pos, ppos, rng, float(dimer.get("d_min", 0.9)),
                                         float(dimer.get("d_max", 6.0)))
                pos = np.concatenate([pos, placed])
                numbers = np.concatenate([numbers, probe.numbers])
            field = random_field(rng, float(recipe.get("field_max_au", 0.01)),
                                 recipe.get("field_distribution", LEGACY_FIELD_DISTRIBUTION))
            out.append(Configuration(key, molecule.name, kind, numbers, pos, field))
    return out
