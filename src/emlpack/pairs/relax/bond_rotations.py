"""Steps of the pairs turned about the axis through their two nearest cores
(:class:`BondRotations`, the default method's ``bond_rotations``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from emlpack.structure import Structure


class BondRotations:
    """Steps of the pairs in cylindrical coordinates about the axis through each pair's two
    nearest cores (molecules; fixed for the relaxation): the tangential part of a Cartesian
    step rotates the pair about that axis (the distances to both cores are kept), the radial
    and axial parts are applied as they are. To first order this is the Cartesian step; it
    follows soft rotations of pairs about a bond (e.g. acetylene's triple-bond pairs) without
    the radial stretch of a straight step. Pairs closer than ``rho_min`` (Å) to their axis,
    tangential steps over 1 rad, zero steps and crystals take the straight step.

    The quasi-Newton model works in these coordinates (per pair: radial, arc length at the
    current radius, axial; :meth:`connection`, :meth:`generalized`): its SR1 secants are the
    turned step and the gradient turned back, and its short-range part turns with the pairs,
    so a rotation along a soft mode no longer reads as the Cartesian chord (whose radial
    O(theta^2 rho) part made SR1 take away the stiff radial curvature)."""

    def __init__(self, structures: Sequence[Structure], x: torch.Tensor,
                 rho_min: float = 0.3) -> None:
        # (measured: rho_min 0.1, 0.2, 0.3 Å alike on the benchmark's acetylene, with the
        # curvilinear secants 0.2 and 0.3 too; 0.3 kept the fixture-weight propane of
        # tests/pairs within 100 quasi-Newton iterations: 77 evaluations, > 100 with 0.2)
        a, b, on, axis = [], [], [], []
        for k, s in enumerate(structures):
            n = len(s.pairs)
            if n == 0:
                continue
            if np.any(s.pbc) or s.n_cores < 2:
                a.append(np.zeros((n, 3)))
                b.append(np.zeros((n, 3)))
                on.append(np.zeros(n, dtype=bool))
                axis.append(np.full((n, 4), -1))
                continue
            d = np.linalg.norm(s.pairs[:, None] - s.positions[None], axis=-1)
            near = np.argsort(d, axis=1)[:, :2]
            a.append(s.positions[near[:, 0]])
            b.append(s.positions[near[:, 1]])
            on.append(np.ones(n, dtype=bool))
            # the sign orients each axis from its lower-numbered core (the same sense of
            # rotation for every pair of a bond)
            sign = np.where(near[:, 0] < near[:, 1], 1, -1)
            axis.append(np.column_stack([np.full(n, k), np.sort(near, axis=1), sign]))
        cat = np.concatenate
        # per pair: the bond it turns about (structure, both cores); -1 for straight steps
        # and the sign of its axis u relative to that bond
        axis = torch.as_tensor(cat(axis) if axis else np.zeros((0, 4), dtype=np.int64))
        self.axis, self.axis_sign = axis[:, :3], axis[:, 3:].to(x.dtype)
        self.a = torch.as_tensor(cat(a) if a else np.zeros((0, 3)), dtype=x.dtype)
        u = torch.as_tensor(cat(b) if b else np.zeros((0, 3)), dtype=x.dtype) - self.a
        self.u = u / torch.clamp(torch.linalg.norm(u, dim=1, keepdim=True), min=1e-12)
        self.on = torch.as_tensor(cat(on) if on else np.zeros(0, dtype=bool))
        self.rho_min = rho_min
        if len(self.a) != len(x):
            raise ValueError(f"{len(self.a)} pair axes for {len(x)} pairs")

    def __call__(self, x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        """The new pairs (P, 3) for the step (P, 3): :meth:`turn` without the rotations."""
        return self.turn(x, step)[0]

    def _frame(self, x: torch.Tensor):
        """Per pair: distance along the axis (P, 1), radius (P, 1), radial and tangential unit
        vectors (P, 3), and whether the pair turns (P, 1) (kept for the last ``x`` object: the
        relaxation asks for it several times per iteration)."""
        cached = getattr(self, "_cache", None)
        if cached is not None and cached[0] is x and cached[1] == x._version:
            return cached[2]
        self._cache = (x, x._version, self._compute_frame(x))
        return self._cache[2]

    def _compute_frame(self, x: torch.Tensor):
        rel = x - self.a
        along = (rel * self.u).sum(1, keepdim=True)
        perp = rel - along * self.u
        rho = torch.linalg.norm(perp, dim=1, keepdim=True)
        rhat = perp / torch.clamp(rho, min=1e-12)
        that = torch.linalg.cross(self.u, rhat, dim=1)
        return along, rho, rhat, that, self.on[:, None] & (rho > self.rho_min)

    def turn(self, x: torch.Tensor, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The new pairs (P, 3) for the step (P, 3) in cylindrical coordinates (radial,
        tangential as the arc, axial; Å) and each pair's rotation (P, 3, 3) about its axis
        (identity for the straight steps)."""
        along, rho, rhat, that, on = self._frame(x)
        s_t = (step * that).sum(1, keepdim=True)
        s_r = (step * rhat).sum(1, keepdim=True)
        s_a = (step * self.u).sum(1, keepdim=True)
        theta = s_t / torch.clamp(rho, min=1e-12)
        turned = self.a + (along + s_a) * self.u + (rho + s_r) * (
            torch.cos(theta) * rhat + torch.sin(theta) * that
        )
        # (a zero step stays exactly zero: the turn would move the pair by rounding)
        use = on & (theta.abs() <= 1.0) & (step != 0).any(1, keepdim=True)
        theta = torch.where(use, theta, 0.0)[:, :, None]
        # Rodrigues: R = cos I + sin [u]x + (1 - cos) u u^T
        u = self.u
        zero = torch.zeros_like(u[:, 0])
        cross = torch.stack([
            torch.stack([zero, -u[:, 2], u[:, 1]], 1),
            torch.stack([u[:, 2], zero, -u[:, 0]], 1),
            torch.stack([-u[:, 1], u[:, 0], zero], 1),
        ], 1)
        rot = (torch.cos(theta) * torch.eye(3, dtype=x.dtype) + torch.sin(theta) * cross
               + (1 - torch.cos(theta)) * u[:, :, None] * u[:, None, :])
        return torch.where(use, turned, x + step), rot

    def collective(self, x: torch.Tensor, arc: float, min_pairs: int) -> torch.Tensor:
        """A step (P, 3) that turns every group of at least ``min_pairs`` pairs about one bond
        (e.g. a triple bond's three pairs) together, each pair by the arc ``arc`` (Å, a step for
        :meth:`turn`); zero for the other pairs."""
        *_, that, on = self._frame(x)
        on = on[:, 0]
        if not bool(on.any()):
            return torch.zeros_like(x)
        _, group, count = torch.unique(self.axis[on], dim=0, return_inverse=True,
                                       return_counts=True)
        member = torch.zeros_like(on)
        member[on] = count[group] >= min_pairs
        return torch.where(member[:, None], arc * self.axis_sign * that, 0.0)

    def connection(self, x: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
        """Per-pair 3x3 blocks (P, 3, 3; eV/Å^2) that turn a Cartesian pair Hessian at ``x``
        into the Hessian in the cylindrical coordinates of :meth:`turn` (arc length at ``x``'s
        radius, axes in the Cartesian frame of ``x``) given the gradient ``grad`` (P, 3):
        ``-g_r / rho`` on the tangential diagonal, ``g_t / rho`` between radial and
        tangential; zero for the pairs that step straight."""
        _, rho, rhat, that, on = self._frame(x)
        inv = torch.where(on, 1.0 / torch.clamp(rho, min=1e-12), 0.0)[:, :, None]
        g_r = (grad * rhat).sum(1)[:, None, None]
        g_t = (grad * that).sum(1)[:, None, None]
        tt = that[:, :, None] * that[:, None, :]
        rt = rhat[:, :, None] * that[:, None, :]
        return inv * (-g_r * tt + g_t * (rt + rt.transpose(1, 2)))

    def generalized(self, x: torch.Tensor, step: torch.Tensor, rot: torch.Tensor,
                    grad_new: torch.Tensor) -> torch.Tensor:
        """The gradient (P, 3) at ``x`` + the turned ``step`` in the cylindrical coordinates of
        :meth:`turn` at ``x`` (the Cartesian gradient turned back, its tangential part scaled
        by the radius ratio); the straight pairs' gradient as it is."""
        _, rho, rhat, that, _ = self._frame(x)
        back = torch.einsum("pji,pj->pi", rot, grad_new)
        ratio = (step * rhat).sum(1, keepdim=True) / torch.clamp(rho, min=1e-12)
        turned = (rot - torch.eye(3, dtype=x.dtype)).abs().amax((1, 2))[:, None] > 0
        return back + torch.where(turned, ratio, 0.0) * (back * that).sum(1, keepdim=True) * that
