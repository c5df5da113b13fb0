"""Structures, models and numerical-derivative helpers shared by the physics tests."""

from __future__ import annotations

import json
import math

import numpy as np
import torch
from scipy.special import erfc
from torch import nn

from emlpack.nn import EMLP, ModelConfig
from emlpack.nn.neighbors import half_neighbor_list
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range import families, register_family
from emlpack.nn.short_range.common import cosine_cutoff, edge_lengths, shifted_softplus
from emlpack.structure import PAIR_NUMBER, Structure
from emlpack.units import COULOMB_EV_A, FIELD_AU_IN_V_PER_A, SQRT_PI
from tests.conftest import shared_path

FIXTURES = "fixtures/reference_tf"

#: a small model: fast, but every part of the network is exercised
SMALL = {"n_features": 16, "n_filters": 8, "n_rbf": 8, "n_interactions": 2}

# 4th-order central difference: f'(0) ~ sum_k w_k f(o_k h) / h
STENCIL_OFFSETS = np.array([-2.0, -1.0, 1.0, 2.0])
STENCIL_WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0]) / 12.0


# ---------------------------------------------------------------------- a test-only family
class RadialPairs(nn.Module):
    """Short-range family ``"radial"`` for the tests: a pair-density network with none of
    SchNet's capabilities (no held edges, no table, no edge-length Hessian), so that every
    generic path of the package runs with it.

    Per particle a scalar density ``rho_i = sum_j g(r_ij) * W[Z_j] / J`` and a vector density
    ``v_i = sum_j d_ij g(r_ij) * U[Z_j] / J`` (``d_ij = r_j - r_i``, K channels, ``g``: K
    Gaussians times the cosine cutoff, ``J = norm``); ``E_i = e[Z_i] + MLP([rho_i,
    |v_i|^2])``. Invariant
    under rotations (the vector density enters through its norm) and smooth at d = 0."""

    def __init__(self, cutoff: float, cutoff_transition: float, n_features: int = 8,
                 n_hidden: int = 16, norm: float = 10.0) -> None:
        super().__init__()
        self.norm = norm
        self.cutoff, self.cutoff_transition = cutoff, cutoff_transition
        k = n_features
        self.register_buffer("centers", torch.linspace(0.0, cutoff, k, dtype=torch.float64),
                             persistent=False)
        self.width = cutoff / k
        self.scalar = nn.Embedding(PAIR_NUMBER + 1, k)
        self.vector = nn.Embedding(PAIR_NUMBER + 1, k)
        self.offset = nn.Embedding(PAIR_NUMBER + 1, 1)
        self.hidden = nn.Linear(2 * k, n_hidden)
        self.out = nn.Linear(n_hidden, 1)

    def forward(self, numbers, vectors, i, j):
        """Atomic energies (N,) (eV) from the half-list edge vectors (E, 3) (Å)."""
        r = edge_lengths(vectors)
        g = torch.exp(-0.5 * ((r[:, None] - self.centers.to(r.dtype)) / self.width) ** 2)
        g = g * cosine_cutoff(r, self.cutoff, self.cutoff_transition)[:, None]  # (E, K)
        n = numbers.numel()
        w = self.scalar(numbers).to(r.dtype) / self.norm
        u = self.vector(numbers).to(r.dtype) / self.norm
        rho = segment_sum(torch.cat([g * w[j], g * w[i]]), torch.cat([i, j]), n)
        gu = torch.cat([g * u[j], g * u[i]])  # (2E, K)
        d = torch.cat([vectors, -vectors])  # from each particle to its neighbour
        v = segment_sum(gu[:, :, None] * d[:, None, :], torch.cat([i, j]), n)  # (N, K, 3)
        h = torch.cat([rho, (v * v).sum(-1)], 1)
        e = self.out(shifted_softplus(self.hidden(h))).squeeze(-1)
        return e + self.offset(numbers).to(r.dtype).squeeze(-1)


register_family("radial", RadialPairs)

#: every registered family, the test-only ``radial`` included (physics tests run over these)
FAMILIES = families()

#: small parameters per family (fast, every part exercised); a family without an entry is
#: tested with its defaults
#: the weights' standard deviation times sqrt(fan_in), by family (default 2): PaiNN's gated
#: vector products grow without bound at 2 (forces ~1e3 eV/Å at 1, ~1 at 0.7)
WEIGHT_SCALE = {"painn": 0.7}
#: added to the seed, by family: PaiNN's seed-0 weights (at 0.7) merge water's lone pairs (no
#: separate minimum to relax to, so the relaxation and response tests would test nothing)
SEED_OFFSET = {"painn": 1}
FAMILY_PARAMS = {"schnet": SMALL, "radial": {"n_features": 6, "n_hidden": 12},
                 "painn": {"n_features": 8, "n_interactions": 2, "n_rbf": 8}}


def random_model(seed: int = 0, dtype=torch.float64, family: str = "schnet",
                 **config) -> EMLP:
    """Small EMLP of ``family`` with seeded random weights and N(0, 0.1^2) biases (so biases
    matter); ``config``: other :class:`ModelConfig` fields.

    Dense weights are N(0, 4/fan_in) (PaiNN: :data:`WEIGHT_SCALE`): with torch's default
    initialisation (or the reference fixture's weights) the SchNet forces are only ~1e-3 eV/Å,
    too small next to the electrostatic forces for the tests to be sensitive; here they are
    ~1 eV/Å.
    """
    torch.manual_seed(seed + SEED_OFFSET.get(family, 0))
    params = FAMILY_PARAMS.get(family, {})
    model = EMLP(ModelConfig(family=family, short_range=params, **config))
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("bias"):
                p.normal_(0.0, 0.1)
            elif p.ndim == 2 and not name.startswith("short_range.embedding"):
                p.normal_(0.0, WEIGHT_SCALE.get(family, 2.0) / math.sqrt(p.shape[1]))
    return model.to(dtype)


def as_format_1(path):
    """Rewrite the SchNet checkpoint ``path`` as emlpack wrote it before the short-range
    families (format 1: flat model config, ``schnet.*`` weights; a training config in the
    metadata with a flat model section too); returns ``path``."""
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert payload["config"]["family"] == "schnet"

    def flat(config: dict) -> dict:
        config = dict(config)
        family, params = config.pop("family"), config.pop("short_range")
        assert family == "schnet"
        return {**params, **config}

    payload["format_version"] = 1
    payload["config"] = flat(payload["config"])
    payload["state_dict"] = {"schnet." + k.removeprefix("short_range."): v
                             for k, v in payload["state_dict"].items()}
    meta = payload.get("metadata") or {}
    if isinstance(meta.get("config"), dict) and "model" in meta["config"]:
        meta["config"] = {**meta["config"], "model": flat(meta["config"]["model"])}
    torch.save(payload, path)
    return path


def zero_short_range(model: EMLP) -> EMLP:
    """The same model with every short-range parameter zero: for SchNet (and the test
    family) the atomic energies then vanish identically."""
    with torch.no_grad():
        for p in model.short_range.parameters():
            p.zero_()
    return model


def reference_model() -> EMLP:
    """The fixture's small reference model (32 features, 2 layers), float64."""
    from emlpack.legacy.reference_weights import model_from_reference

    weights = dict(np.load(shared_path(f"{FIXTURES}/weights_small.npz")))
    hparams = json.loads(shared_path(f"{FIXTURES}/hparams_small.json").read_text())
    return model_from_reference(weights, hparams["constructor_kwargs"])


# ---------------------------------------------------------------------- structures
def _rng_jitter(positions: np.ndarray, seed: int, scale: float = 0.05) -> np.ndarray:
    return positions + np.random.default_rng(seed).uniform(-scale, scale, positions.shape)


def water(center=(0.0, 0.0, 0.0), rotation=None, seed: int = 1):
    """(numbers, core positions, pair positions) of a slightly distorted water molecule."""
    cores = np.array([[0.0, 0.0, 0.0], [0.757, 0.586, 0.0], [-0.757, 0.586, 0.0]])
    pairs = np.array(
        [[0.38, 0.30, 0.02], [-0.37, 0.31, -0.01], [0.0, -0.25, 0.30], [0.02, -0.24, -0.31]]
    )
    rot = np.eye(3) if rotation is None else rotation
    cores = _rng_jitter(cores, seed) @ rot.T + np.asarray(center)
    pairs = _rng_jitter(pairs, seed + 100) @ rot.T + np.asarray(center)
    return [8, 1, 1], cores, pairs


def _tetrahedral(center_z: int, charge: float, bond: float, pair_frac: float, seed: int):
    t = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / math.sqrt(3.0)
    cores = _rng_jitter(np.vstack([[0.0, 0.0, 0.0], bond * t]), seed)
    pairs = _rng_jitter(pair_frac * bond * t, seed + 1)
    return Structure([center_z, 1, 1, 1, 1], cores, pairs, charge=charge)


def methane(field=(0.0, 0.0, 0.0), seed: int = 3) -> Structure:
    s = _tetrahedral(6, 0.0, 1.09, 0.55, seed)
    return s.copy(field=np.asarray(field, float))


def ammonium(field=(0.0, 0.0, 0.0), seed: int = 5) -> Structure:
    """NH4+ (total charge +1)."""
    s = _tetrahedral(7, 1.0, 1.02, 0.5, seed)
    return s.copy(field=np.asarray(field, float))


def hydroxide(field=(0.0, 0.0, 0.0), seed: int = 7) -> Structure:
    """OH- (total charge -1)."""
    cores = _rng_jitter(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.97]]), seed)
    pairs = _rng_jitter(
        np.array([[0.0, 0.0, 0.5], [0.3, 0.0, -0.15], [-0.15, 0.26, -0.15], [-0.15, -0.26, -0.15]]),
        seed + 1,
    )
    return Structure([8, 1], cores, pairs, charge=-1.0, field=np.asarray(field, float))


def water_molecule(field=(0.0, 0.0, 0.0)) -> Structure:
    z, c, p = water(seed=11)
    return Structure(z, c, p, field=np.asarray(field, float))


#: a triclinic cell (rows = lattice vectors, Å)
WATER_CELL = np.array([[4.6, 0.0, 0.0], [0.9, 4.9, 0.0], [-0.7, 0.6, 5.3]])


def _rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def random_rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q * np.linalg.det(q)  # proper rotation


def water_crystal(field=(0.0, 0.0, 0.0)) -> Structure:
    """Two water molecules in a small triclinic cell (14 particles, neutral)."""
    z1, c1, p1 = water(np.array([0.25, 0.3, 0.2]) @ WATER_CELL, _rotation([1, 2, 0], 0.7), 21)
    z2, c2, p2 = water(np.array([0.7, 0.75, 0.65]) @ WATER_CELL, _rotation([0, 1, 3], 2.1), 31)
    return Structure(
        z1 + z2,
        np.vstack([c1, c2]),
        np.vstack([p1, p2]),
        cell=WATER_CELL,
        pbc=True,
        field=np.asarray(field, float),
        source="water crystal",
    )


def glycine(config: str = "p1") -> Structure:
    """beta-glycine (20 cores, 30 pairs) from the reference fixture: p1 perturbed, p3 field."""
    d = np.load(shared_path(f"{FIXTURES}/periodic_small.npz"))
    p = f"{config}_"
    return Structure(
        d[p + "core_numbers"],
        d[p + "core_positions"],
        d[p + "pair_positions"],
        cell=d[p + "rvec"],
        pbc=True,
        field=d[p + "efield"] * FIELD_AU_IN_V_PER_A,
        source=f"periodic_small.npz {config}",
    )


def eqm7_molecule(slot: str = "c08") -> Structure:
    """A molecule of the reference fixture (c08: C2H6O) with its file field."""
    d = np.load(shared_path(f"{FIXTURES}/molecules_small.npz"))
    p = f"{slot}_"
    return Structure(
        d[p + "core_numbers"],
        d[p + "core_positions"],
        d[p + "pair_positions"],
        field=d[p + "efield"] * FIELD_AU_IN_V_PER_A,
        source=f"molecules_small.npz {slot}",
    )


# ---------------------------------------------------------------------- evaluation
def energies_at(
    model: EMLP,
    structure: Structure,
    positions: np.ndarray,
    cells: np.ndarray | None = None,
    fields: np.ndarray | None = None,
    parts=("energy",),
) -> list[np.ndarray]:
    """Energies (eV) of M geometries of ``structure`` (positions (M, N, 3), all particles), with
    the topology (neighbour list, k set) of ``structure`` held fixed, in one batched call.

    ``parts``: one entry per result, each an energy part name or a tuple of names to sum."""
    m = len(positions)
    g = model.graph([structure] * m)
    dtype = g.dtype
    pos = torch.as_tensor(np.asarray(positions).reshape(-1, 3), dtype=dtype)
    cell = None if cells is None else torch.as_tensor(np.asarray(cells), dtype=dtype)
    field = None if fields is None else torch.as_tensor(np.asarray(fields), dtype=dtype)
    with torch.no_grad():
        out = model.energy_parts(g, pos, cell, field)
    result = []
    for part in parts:
        names = (part,) if isinstance(part, str) else part
        result.append(sum(out[n] for n in names).numpy())
    return result


def kink_gap(model: EMLP, structure: Structure) -> float:
    """Smallest distance (Å) of an edge length from the kinks of the cosine cutoff (its second
    derivative jumps at cutoff - transition and at cutoff); finite-difference stencils must
    not cross them."""
    g = model.graph(structure)
    d = g.positions[g.edge_j] - g.positions[g.edge_i]
    if g.edge_shift.numel():
        d = d + g.edge_shift @ g.cell[0]
    r = d.norm(dim=-1).numpy()
    c = model.config
    return float(np.min(np.abs(r[:, None] - [c.cutoff - c.cutoff_transition, c.cutoff])))


def _edge_lengths_by_key(structure: Structure, cutoff: float) -> dict[tuple, float]:
    """Lengths (Å) of the edges shorter than ``cutoff``, keyed by ``(i, j, *shift)`` in the
    orientation whose key is smaller (each unordered edge once, whichever way round)."""
    p = structure.all_positions
    i, j, shifts = half_neighbor_list(p, structure.cell, structure.pbc, cutoff)
    d = p[j] - p[i] + (shifts @ structure.cell if structure.pbc else 0.0)
    return {min((int(a), int(b), *map(int, c)), (int(b), int(a), *map(int, -c))): float(r)
            for a, b, c, r in zip(i, j, shifts, np.linalg.norm(d, axis=1), strict=True)}


def crossed_kinks(model: EMLP, reference: Structure, structures) -> list[str]:
    """The edges whose length crosses a kink of the cosine cutoff (its second derivative jumps
    at ``cutoff - transition`` and at ``cutoff``) between ``reference`` and any of
    ``structures`` (the same particles, e.g. relaxed at a finite field or strain); one line
    each. The energy is only C1 across a kink, so a finite-difference stencil of a response
    (a derivative of forces or of relaxed coordinates) that straddles one measures a mean of
    two one-sided Hessians, not the derivative at ``reference``."""
    c = model.config
    kinks = (c.cutoff - c.cutoff_transition, c.cutoff)
    reach = c.cutoff + 0.5  # edges outside the cutoff that may move in
    start = _edge_lengths_by_key(reference, reach)
    out = []
    for k, s in enumerate(structures):
        lengths = _edge_lengths_by_key(s, reach)
        for key, r0 in start.items():
            r = lengths.get(key, math.inf)
            out += [f"structure {k}: edge {key} {r0:.6f} -> {r:.6f} Å crosses {kink} Å"
                    for kink in kinks if (r0 - kink) * (r - kink) <= 0.0]
    return out


def fd_forces(model: EMLP, structure: Structure, particles, h: float = 2e-4, part="energy"):
    """-dE/dr by 4th-order central differences for the given particle indices, (len, 3).

    A particle moves by up to 2h: h is reduced below a quarter of :func:`kink_gap`."""
    h = min(h, kink_gap(model, structure) / 4)
    r0 = structure.all_positions
    geoms = []
    for i in particles:
        for a in range(3):
            for o in STENCIL_OFFSETS:
                r = r0.copy()
                r[i, a] += o * h
                geoms.append(r)
    (e,) = energies_at(model, structure, np.array(geoms), parts=(part,))
    return -(e.reshape(len(particles), 3, 4) @ STENCIL_WEIGHTS) / h


def fd_virial(model: EMLP, structure: Structure, h: float = 5e-5, parts=("energy",)):
    """dE/d(eps_ab) for r -> r (I + eps), cell -> cell (I + eps), general (non-symmetric) eps,
    one (3, 3) array per entry of ``parts`` (see :func:`energies_at`).

    An edge of length < 4 Å changes by up to 8h: h is reduced below kink_gap / 16."""
    h = min(h, kink_gap(model, structure) / 16)
    r0, c0 = structure.all_positions, structure.cell
    geoms, cells = [], []
    for a in range(3):
        for b in range(3):
            for o in STENCIL_OFFSETS:
                eps = np.zeros((3, 3))
                eps[a, b] = o * h
                geoms.append(r0 @ (np.eye(3) + eps))
                cells.append(c0 @ (np.eye(3) + eps))
    es = energies_at(model, structure, np.array(geoms), np.array(cells), parts=parts)
    return [(e.reshape(3, 3, 4) @ STENCIL_WEIGHTS) / h for e in es]


def all_forces(result: dict) -> np.ndarray:
    return np.concatenate([result["forces"], result["pair_forces"]])


# ---------------------------------------------------------------------- independent Ewald
def numpy_gaussian_ewald(
    positions: np.ndarray, charges: np.ndarray, cell: np.ndarray, gamma: float, alpha: float
) -> float:
    """Energy (eV) of periodic Gaussian charges (interaction k_e q q erf(gamma r)/r, Gaussian
    self energy included, tin-foil boundary), by an Ewald split at ``alpha`` != gamma:

    E = k_e [1/2 sum'_{ijn} q_i q_j (erfc(alpha r) - erfc(gamma r))/r
             + (2 pi/V) sum_{k!=0} |S(k)|^2 exp(-k^2/4 alpha^2)/k^2
             + (gamma - alpha)/sqrt(pi) sum q^2]

    The real-space part is a direct sum over all images within a converged radius.
    """
    q = np.asarray(charges, float)
    assert abs(q.sum()) < 1e-12
    inv = np.linalg.inv(cell)
    # real space
    rcut = 7.0 / min(alpha, gamma)
    nmax = np.ceil(rcut * np.linalg.norm(inv, axis=0)).astype(int) + 1
    ranges = [np.arange(-m, m + 1) for m in nmax]
    shifts = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, 3) @ cell
    d = positions[None, :, None, :] - positions[:, None, None, :] + shifts[None, None]
    r = np.linalg.norm(d, axis=-1)
    qq = (q[:, None] * q[None, :])[:, :, None] * np.ones_like(r)
    keep = (r > 1e-12) & (r < rcut)
    real = 0.5 * np.sum(qq[keep] * (erfc(alpha * r[keep]) - erfc(gamma * r[keep])) / r[keep])
    # reciprocal space
    gmax = 7.0 * alpha / math.pi  # |k| = 2 pi g, exp(-k^2/4a^2) < exp(-49)
    nk = np.ceil(gmax * np.linalg.norm(cell, axis=1)).astype(int)
    ranges = [np.arange(-m, m + 1) for m in nk]
    n = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, 3)
    n = n[np.any(n != 0, axis=1)]
    k = 2.0 * math.pi * n @ inv.T
    k2 = np.sum(k * k, axis=1)
    s = np.exp(1j * k @ positions.T) @ q
    volume = abs(np.linalg.det(cell))
    recip = 2.0 * math.pi / volume * np.sum(np.abs(s) ** 2 * np.exp(-k2 / (4 * alpha**2)) / k2)
    self_term = (gamma - alpha) / SQRT_PI * np.sum(q * q)
    return COULOMB_EV_A * (real + recip + self_term)
