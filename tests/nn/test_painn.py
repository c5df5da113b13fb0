"""PaiNN short-range family: the network against a dense reference of the paper's equations,
symmetries (rotations, reflections, translations, permutations of particles and of the half
edge list), derivatives against finite differences, zero-length edges, the cutoff, and the
training's double backward."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from emlpack.errors import InputError
from emlpack.nn.neighbors import half_neighbor_list
from emlpack.nn.short_range.painn import PaiNN
from tests.nn.helpers import random_rotation

PAIR = 99
#: a short cutoff: the small random graphs below have pairs beyond it
CUTOFF, TRANSITION = 3.0, 0.6
SMALL = {"n_features": 16, "n_interactions": 2, "n_rbf": 8, "cutoff": CUTOFF,
         "cutoff_transition": TRANSITION}


def random_painn(seed: int = 0, dtype: torch.dtype = torch.float64, **params) -> PaiNN:
    """Small PaiNN with seeded random weights N(0, 1/fan_in) and biases N(0, 0.1^2): atomic
    energies ~1 eV and forces ~1 eV/Å on the graphs below (torch's default initialisation
    gives ~0.05; the gated products make larger weights blow up)."""
    torch.manual_seed(seed)
    model = PaiNN(**{**SMALL, **params})
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("bias"):
                p.normal_(0.0, 0.1)
            elif p.ndim == 2 and not name.startswith("embedding"):
                p.normal_(0.0, 1.0 / math.sqrt(p.shape[1]))
    return model.to(dtype)


@pytest.fixture(scope="module")
def model() -> PaiNN:
    return random_painn()


def random_molecule(n: int = 10, seed: int = 0, box: float = 4.0):
    """Particle numbers (cores and electron pairs) and positions (Å) of a random cluster, no
    two particles closer than 0.25 Å."""
    rng = np.random.default_rng(seed)
    numbers = rng.choice([1, 6, 7, 8, PAIR], size=n)
    numbers[:2] = [6, PAIR]
    positions = [rng.uniform(0.0, box, 3)]
    while len(positions) < n:
        x = rng.uniform(0.0, box, 3)
        if min(np.linalg.norm(x - p) for p in positions) > 0.25:
            positions.append(x)
    return torch.as_tensor(numbers), torch.as_tensor(np.array(positions))


def half_edges(positions: torch.Tensor, cutoff: float | None = CUTOFF):
    """Half edge list ``i < j`` within ``cutoff`` (every pair with ``None``)."""
    i, j = torch.triu_indices(len(positions), len(positions), 1)
    if cutoff is not None:
        keep = (positions[j] - positions[i]).norm(dim=1) < cutoff
        i, j = i[keep], j[keep]
    return i, j


def energy(model: PaiNN, numbers, positions, i, j) -> torch.Tensor:
    """Total short-range energy (eV) with the edge vectors ``r_j - r_i``."""
    return model(numbers, positions[j] - positions[i], i, j).sum()


def forces(model: PaiNN, numbers, positions, i, j, create_graph: bool = False) -> torch.Tensor:
    pos = positions.detach().clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(energy(model, numbers, pos, i, j), pos,
                                  create_graph=create_graph)
    return -grad


# ------------------------------------------------------------------ the paper's equations
def dense_reference(model: PaiNN, numbers, positions, cell=None, n_images: int = 0):
    """Atomic energies from PaiNN's equations written out per particle over its neighbours
    (every particle ``b`` and image ``S`` with ``0 < |r_b - r_a + S cell| < cutoff``), with
    the cutoff and Gaussians restated here; independent of the half list and its tricks."""
    f, n_t = model.n_features, model.n_interactions
    n = len(numbers)
    shifts = torch.cartesian_prod(*[torch.arange(-n_images, n_images + 1.0)] * 3)
    shifts = shifts.reshape(-1, 3).to(positions.dtype)
    cell = torch.zeros(3, 3, dtype=positions.dtype) if cell is None else cell
    start, width = 0.0, model.cutoff / len(model.rbf.centers)
    centers = start + width * torch.arange(len(model.rbf.centers), dtype=positions.dtype)
    neighbours = []
    for a in range(n):
        d = (positions[None, :, :] - positions[a] + (shifts @ cell)[:, None, :]).reshape(-1, 3)
        b = torch.arange(n).repeat(len(shifts))
        r = torch.sqrt((d * d).sum(1) + model.edge_eps)
        length = torch.sqrt((d * d).sum(1))  # the cutoff acts on |d|
        keep = (length < model.cutoff) & ((d * d).sum(1) > 0)
        d, b, r, length = d[keep], b[keep], r[keep], length[keep]
        x = ((length - (model.cutoff - model.cutoff_transition)) / model.cutoff_transition)
        fc = torch.where(x <= 0, 1.0, 0.5 * (1.0 + torch.cos(math.pi * x.clamp(0.0, 1.0))))
        rbf = torch.exp(-0.5 * ((r[:, None] - centers) / width) ** 2)
        w = (model.filters(rbf) * fc[:, None] / model.message_norm).view(-1, n_t, 3 * f)
        neighbours.append((b, w, d / r[:, None]))
    s = model.embedding.weight[numbers]
    v = torch.zeros(n, 3, f, dtype=positions.dtype)
    for t in range(n_t):
        phi = model.messages[t](s)
        ds, dv = torch.zeros_like(s), torch.zeros_like(v)
        for a, (b, w, u) in enumerate(neighbours):
            x_s, x_vv, x_vr = (phi[b] * w[:, t]).split(f, -1)
            ds[a] = x_s.sum(0)
            dv[a] = (x_vv[:, None, :] * v[b] + x_vr[:, None, :] * u[:, :, None]).sum(0)
        s, v = s + ds, v + dv
        update = model.updates[t]
        uv = v @ update.mix.weight[:f].T
        vv = v @ update.mix.weight[f:].T
        a_vv, a_sv, a_ss = update.context(
            torch.cat([s, torch.sqrt((vv**2).sum(1) + update.norm_eps)], 1)).split(f, -1)
        v = v + a_vv[:, None, :] * uv
        s = s + a_sv * (uv * vv).sum(1) + a_ss
    return model.output(s).squeeze(-1)


def test_atomic_energies_match_dense_reference_molecule(model):
    numbers, positions = random_molecule(12, seed=1)
    i, j = half_edges(positions)
    assert 0 < len(i) < 66  # some pairs lie beyond the cutoff
    with torch.no_grad():
        ours = model(numbers, positions[j] - positions[i], i, j)
        ref = dense_reference(model, numbers, positions)
    np.testing.assert_allclose(ours.numpy(), ref.numpy(), rtol=0, atol=1e-12)
    assert ours.std() > 0.1  # eV: the particles differ


def test_atomic_energies_match_dense_reference_periodic_with_self_images(model):
    """A triclinic cell smaller than the cutoff: particles see their own images (half-list
    edges with i == j), vesin's half list with image shifts."""
    numbers, frac = random_molecule(5, seed=2, box=1.0)
    cell = torch.tensor([[2.6, 0.0, 0.0], [0.4, 2.4, 0.0], [-0.3, 0.5, 2.8]], dtype=torch.float64)
    positions = frac @ cell
    i, j, shift = (torch.as_tensor(x) for x in half_neighbor_list(
        positions.numpy(), cell.numpy(), True, CUTOFF))
    assert (i == j).any()
    vectors = positions[j] - positions[i] + shift.to(cell.dtype) @ cell
    with torch.no_grad():
        ours = model(numbers, vectors, i, j)
        ref = dense_reference(model, numbers, positions, cell, n_images=2)
    np.testing.assert_allclose(ours.numpy(), ref.numpy(), rtol=0, atol=1e-11)


# ------------------------------------------------------------------------- symmetries
def test_energy_invariant_under_rotation_reflection_and_translation(model):
    numbers, positions = random_molecule(12, seed=3)
    i, j = half_edges(positions)
    e0 = energy(model, numbers, positions, i, j)
    rot = torch.as_tensor(random_rotation(4))
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    for q in (rot, mirror @ rot):
        moved = positions @ q.T + torch.tensor([3.1, -7.2, 11.9], dtype=torch.float64)
        assert energy(model, numbers, moved, i, j).item() == pytest.approx(e0.item(), abs=1e-11)
    # a deformation changes it (the test can fail)
    stretched = positions * torch.tensor([1.0, 1.0, 1.05], dtype=torch.float64)
    assert abs(energy(model, numbers, stretched, i, j) - e0) > 1e-3


def test_energy_invariant_under_permutation_of_particles(model):
    """Relabelling the particles (the electron pairs among themselves included) permutes the
    atomic energies and leaves the total unchanged."""
    numbers, positions = random_molecule(12, seed=4)
    i, j = half_edges(positions)
    atomic = model(numbers, positions[j] - positions[i], i, j)
    perm = torch.as_tensor(np.random.default_rng(5).permutation(len(numbers)))
    inverse = torch.argsort(perm)  # new index of each old particle
    pi, pj = inverse[i], inverse[j]
    permuted = model(numbers[perm], positions[perm][pj] - positions[perm][pi], pi, pj)
    np.testing.assert_allclose(permuted.detach().numpy(), atomic[perm].detach().numpy(),
                               rtol=0, atol=1e-12)
    pairs = torch.nonzero(numbers == PAIR).squeeze(1)
    assert len(pairs) >= 2


def test_energy_invariant_under_edge_order_and_direction(model):
    """Shuffling the half list and swapping (i, j) with the vector negated on some edges gives
    the same atomic energies."""
    numbers, positions = random_molecule(12, seed=6)
    i, j = half_edges(positions)
    vectors = positions[j] - positions[i]
    atomic = model(numbers, vectors, i, j)
    rng = np.random.default_rng(7)
    order = torch.as_tensor(rng.permutation(len(i)))
    flip = torch.as_tensor(rng.random(len(i)) < 0.5)
    i2, j2 = torch.where(flip, j, i)[order], torch.where(flip, i, j)[order]
    v2 = torch.where(flip[:, None], -vectors, vectors)[order]
    np.testing.assert_allclose(model(numbers, v2, i2, j2).detach().numpy(),
                               atomic.detach().numpy(), rtol=0, atol=1e-12)
    # a flip without negating the vector is a different geometry (the test can fail)
    v3 = vectors[order]
    assert (model(numbers, v3, i2, j2) - atomic).abs().max() > 1e-3


def test_forces_equivariant_under_rotation(model):
    numbers, positions = random_molecule(12, seed=8)
    i, j = half_edges(positions)
    f0 = forces(model, numbers, positions, i, j)
    rot = torch.as_tensor(random_rotation(9))
    f1 = forces(model, numbers, positions @ rot.T, i, j)
    np.testing.assert_allclose(f1.numpy(), (f0 @ rot.T).numpy(), rtol=0, atol=1e-11)
    assert f0.abs().max() > 0.1  # eV/Å


# ------------------------------------------------------------------------ derivatives
def test_forces_match_central_finite_differences(model):
    numbers, positions = random_molecule(10, seed=10)
    i, j = half_edges(positions, None)  # all pairs: the list never changes under a step
    f = forces(model, numbers, positions, i, j)
    h = 1e-5
    fd = torch.zeros_like(positions)
    for a in range(len(numbers)):
        for k in range(3):
            step = torch.zeros_like(positions)
            step[a, k] = h
            with torch.no_grad():
                fd[a, k] = -(energy(model, numbers, positions + step, i, j)
                             - energy(model, numbers, positions - step, i, j)) / (2 * h)
    np.testing.assert_allclose(f.numpy(), fd.numpy(), rtol=0, atol=1e-7)  # h^2 f''' ~ 2e-8
    assert f.abs().max() > 0.1


def test_hessian_matches_finite_differences_of_forces(model):
    numbers, positions = random_molecule(8, seed=11)
    i, j = half_edges(positions, None)

    def e(x):
        return energy(model, numbers, x.view(-1, 3), i, j)

    hessian = torch.autograd.functional.hessian(e, positions.reshape(-1))
    h = 1e-5
    fd = torch.zeros_like(hessian)
    for k in range(hessian.shape[0]):
        step = torch.zeros(hessian.shape[0], dtype=torch.float64)
        step[k] = h
        plus = forces(model, numbers, (positions.reshape(-1) + step).view(-1, 3), i, j)
        minus = forces(model, numbers, (positions.reshape(-1) - step).view(-1, 3), i, j)
        fd[:, k] = -(plus - minus).reshape(-1) / (2 * h)
    np.testing.assert_allclose(hessian.numpy(), hessian.T.numpy(), rtol=0, atol=1e-10)
    np.testing.assert_allclose(hessian.numpy(), fd.numpy(), rtol=0, atol=2e-6)
    assert hessian.abs().max() > 1.0  # eV/Å^2


def _centrosymmetric():
    """A core at the origin and pairs of particles at +-x (the inversion maps the structure
    onto itself: the central core's vector features vanish at every layer)."""
    numbers, half = random_molecule(5, seed=15, box=2.0)
    half = half - half.mean(0) + torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    positions = torch.cat([torch.zeros(1, 3, dtype=torch.float64), half, -half])
    return torch.cat([torch.tensor([6]), numbers, numbers]), positions


@pytest.mark.parametrize("norm_eps", [1.0, 1e-8])
def test_hessian_smooth_at_a_centre_of_symmetry(norm_eps):
    """The central core's Hessian block by autograd equals finite differences of its forces
    (step 1e-4 Å): smooth where its vector features vanish. With PaiNN's plain norm
    (``norm_eps = 1e-8``) the norm's cone makes the two disagree (the test can fail)."""
    model = random_painn(norm_eps=norm_eps)
    numbers, positions = _centrosymmetric()
    i, j = half_edges(positions, None)

    def e(x):
        return energy(model, numbers, torch.cat([x[None], positions[1:]]), i, j)

    block = torch.autograd.functional.hessian(e, positions[0])
    h = 1e-4
    fd = torch.zeros(3, 3, dtype=torch.float64)
    for k in range(3):
        step = torch.zeros_like(positions)
        step[0, k] = h
        fd[:, k] = -(forces(model, numbers, positions + step, i, j)[0]
                     - forces(model, numbers, positions - step, i, j)[0]) / (2 * h)
    gap = (block - fd).abs().max().item()
    if norm_eps == 1.0:
        assert gap < 1e-5 * block.abs().max().item()
        assert block.abs().max() > 1.0
    else:
        assert gap > 0.1 * block.abs().max().item()


# ------------------------------------------------------------------ zero-length edges
def _pair_on_core(offset: torch.Tensor):
    """A molecule whose particle 1 (an electron pair) sits at ``offset`` from core 0."""
    numbers, positions = random_molecule(9, seed=12)
    positions = positions.clone()
    positions[1] = positions[0] + offset
    return numbers, positions


def test_zero_length_edge_finite_energy_and_derivatives(model):
    numbers, positions = _pair_on_core(torch.zeros(3, dtype=torch.float64))
    i, j = half_edges(positions)
    assert ((positions[j] - positions[i]).norm(dim=1) == 0).sum() == 1

    def e(x):
        return energy(model, numbers, x.view(-1, 3), i, j)

    x = positions.reshape(-1).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(e(x), x, create_graph=True)
    hessian = torch.autograd.functional.hessian(e, positions.reshape(-1))
    # third derivatives along a direction: d/dx of the Hessian-vector product
    hv = torch.autograd.grad(grad @ torch.ones_like(x), x, create_graph=True)[0]
    (third,) = torch.autograd.grad(hv @ torch.ones_like(x), x)
    assert torch.isfinite(e(positions.reshape(-1)))
    assert torch.isfinite(grad).all()
    assert torch.isfinite(hessian).all()
    assert torch.isfinite(third).all()
    # bounded by the smoothing length sqrt(edge_eps) = 0.1 Å, not by 1/sqrt(1e-20)
    assert grad.abs().max() < 1e3
    assert hessian.abs().max() < 1e5


def test_zero_length_edge_energy_and_forces_continuous(model):
    """The pair moved 1e-6 Å off the core: the energy changes by the first-order term
    ``-F(0) . d`` only and the forces by ~H d (with ``edge_eps = 1e-20``, the reference's
    length guard, the direction ``d / r`` would jump from 0 to a unit vector)."""
    zero = _pair_on_core(torch.zeros(3, dtype=torch.float64))
    i, j = half_edges(zero[1])
    e0 = energy(model, *zero, i, j)
    f0 = forces(model, *zero, i, j)
    for step in 1e-6 * torch.eye(3, dtype=torch.float64):
        near = _pair_on_core(step)
        de = energy(model, *near, i, j) - e0
        assert abs(de.item()) < 1e-5
        assert abs((de + f0[1] @ step).item()) < 1e-9  # eV: O(H d^2)
        np.testing.assert_allclose(forces(model, *near, i, j).numpy(), f0.numpy(), atol=1e-3)
    sharp = random_painn(edge_eps=1e-20)
    near = _pair_on_core(1e-6 * torch.eye(3, dtype=torch.float64)[0])
    assert abs(energy(sharp, *near, i, j) - energy(sharp, *zero, i, j)) > 1e-3


# ------------------------------------------------------------------------ the cutoff
def _edge_at(r: float, model: PaiNN):
    """Two cores and a pair; the pair at the distance ``r`` (Å, the cutoff's argument) from
    core 1, 2.5 Å from core 0 at r = 3 Å."""
    d = r
    numbers = torch.tensor([6, 8, PAIR])
    positions = torch.tensor([[0.0, 0.0, 0.0], [1.3, 0.0, 0.0], [1.3 - d * 0.6, d * 0.8, 0.0]],
                             dtype=torch.float64)
    return numbers, positions


def test_energy_and_forces_continuous_as_an_edge_crosses_the_cutoff(model):
    """The edge's contribution (energy and forces with it minus without it) vanishes as
    ``(cutoff - r)^2`` (energy) and ``cutoff - r`` (forces): nothing jumps when the
    neighbour list drops it."""
    gaps = {}
    for delta in (1e-3, 1e-2):
        numbers, positions = _edge_at(CUTOFF - delta, model)
        i, j = half_edges(positions)
        keep = ~((i == 1) & (j == 2))
        assert len(i) == 3
        de = energy(model, numbers, positions, i, j) - energy(model, numbers, positions,
                                                             i[keep], j[keep])
        df = forces(model, numbers, positions, i, j) - forces(model, numbers, positions,
                                                             i[keep], j[keep])
        gaps[delta] = abs(de.item()), df.abs().max().item()
    assert gaps[1e-3][0] < 1e-5 and gaps[1e-3][1] < 1e-2
    assert 90 < gaps[1e-2][0] / gaps[1e-3][0] < 110  # quadratic onset
    assert 8 < gaps[1e-2][1] / gaps[1e-3][1] < 12  # linear onset of the forces


def test_edges_beyond_the_cutoff_contribute_nothing(model):
    numbers, positions = random_molecule(12, seed=13)
    i, j = half_edges(positions)
    ia, ja = half_edges(positions, None)
    assert len(ia) > len(i)
    assert energy(model, numbers, positions, ia, ja).item() == pytest.approx(
        energy(model, numbers, positions, i, j).item(), abs=1e-12)


# -------------------------------------------------------------------------- training
def test_force_loss_double_backward_is_finite_at_a_zero_length_edge():
    model = random_painn(dtype=torch.float32)
    numbers, positions = _pair_on_core(torch.zeros(3, dtype=torch.float64))
    positions = positions.float()
    i, j = half_edges(positions)
    f = forces(model, numbers, positions, i, j, create_graph=True)
    loss = (energy(model, numbers, positions, i, j) - 1.0) ** 2 + ((f - 0.1) ** 2).mean()
    params = list(model.parameters())
    grads = torch.autograd.grad(loss, params)
    assert f.dtype == torch.float32
    assert all(torch.isfinite(g).all() for g in grads)
    assert all(g.abs().max() > 0 for g in grads)


def test_follows_the_input_dtype():
    numbers, positions = random_molecule(6, seed=14)
    i, j = half_edges(positions)
    for dtype in (torch.float32, torch.float64):
        model = random_painn(dtype=dtype)
        assert model(numbers, (positions[j] - positions[i]).to(dtype), i, j).dtype == dtype


def test_parameter_count_and_bad_hyperparameters():
    f, t, r = 64, 3, 20
    expected = 100 * f + (r + 1) * 3 * f * t + t * (4 * f * f + 4 * f + 7 * f * f + 4 * f) \
        + f * (f // 2) + f // 2 + f // 2 + 1
    assert sum(p.numel() for p in PaiNN().parameters()) == expected == 157_313
    with pytest.raises(InputError, match="cutoff_transition"):
        PaiNN(cutoff=3.0, cutoff_transition=0.0)
    with pytest.raises(InputError, match="edge_eps"):
        PaiNN(edge_eps=0.0)
