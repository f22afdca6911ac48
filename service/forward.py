"""The one interface between the registration engine and a forward model (FEM or network).

The bottom of the tree: the models (``fem/``, ``surrogate/``) implement these protocols and the
engine (``registration/``) calls them, so neither side imports the other.

A :class:`ForwardModel` is immutable and shared by every session of a model. For a session it
makes a :class:`ForwardOperator` restricted to the session's support (the controls) and to the
nodes the objective reads (the matching surface), so each evaluation computes only what the
optimisation needs; the operator may keep warm-start state, so it belongs to one session.

    op = model.restrict(support, nodes)
    u_nodes, pullback = op(g)          # g (k, 3) -> u (p, 3); pullback(u_bar (p, 3)) -> (k, 3)
    u_all = op.displacement(g)         # the full field, once the optimisation is done

The pullback is the vector-Jacobian product (the adjoint): backpropagation for the network, the
transposed tangent solve for the FEM. It is valid until the operator's next call. Its optional
``rows`` (q,) names the only rows of u_bar that may be nonzero (the distance's candidate nodes,
a fifth of the liver's matching surface); an operator may use the hint to read out through
those rows alone (the network does) or ignore it (the FEM does).
An operator with slow solves (the FEM) may also have a settable ``deadline`` (a
``time.perf_counter()`` value or None): the engine sets it for the length of a frame with a
time budget, and a solve past it gives up with ``ForwardFailed("time_limit")``, so the budget
holds inside a solve of seconds, not only between solves.
:func:`torch_forward` wraps an operator as a torch autograd function.

A model that can give du/dg at g (for Levenberg-Marquardt, ``registration/levenberg.py``) offers
``op.jacobian(g)`` returning a :class:`Jacobian`: the FEM's ``DenseJacobian``
(``fem/jacobian.py``), the reduced network's ``CoefficientJacobian`` (``surrogate/jacobian.py``).
The FEM forms it with 3 solves a support node, so it also says whether it serves the support
(``op.has_jacobian``) and offers ``op.jacobian_products(g)``: du/dg's products, a solve each,
with the Jacobian it formed last to precondition them (or None where forming one is as cheap).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from .mesh import TetMesh

Array = np.ndarray
Pullback = Callable[..., Array]  # (u_bar, rows=None) -> g_bar


class ForwardFailed(RuntimeError):
    """The forward model could not produce a displacement for these forces (e.g. Newton
    diverged). The engine turns it into ``status: forward_failed``, never into a crash."""

    def __init__(self, status: str, detail: str = "") -> None:
        super().__init__(f"{status}: {detail}" if detail else status)
        self.status = status


class Material(Protocol):
    """What the engine reads of a model's material (the FEM's ``NeoHookean``)."""

    E: float  # Young's modulus, Pa
    nu: float  # Poisson's ratio


class Jacobian(Protocol):
    """du/dg = U C at one g, in product form: U (3p, r) over the operator's nodes (node-major),
    C (r, K) over the K = 3k force components; only C's products are formed.

    A Jacobian may also offer ``gradient_image(alpha)``: C grad for the gradient the operator's
    last evaluation gave at this g, or None (Levenberg-Marquardt's right-hand side, cheaply)."""

    U: Array

    def gram_product(self, A: Array) -> Array:
        """C C^T A (r, r) for a symmetric A (r, r), Fortran-ordered as LAPACK takes it."""

    def matvec(self, v: Array) -> Array:
        """C v. Shape: (K,) -> (r,), float64."""

    def rmatvec(self, w: Array) -> Array:
        """C^T w. Shape: (r,) -> (K,), float64."""


class ForwardOperator(Protocol):
    support: Array  # (k,) node ids where forces act
    nodes: Array  # (p,) node ids whose displacement __call__ returns

    def __call__(self, g: Array) -> tuple[Array, Pullback]:
        """Shape: g (k, 3) -> u (p, 3), pullback(u_bar (p, 3), rows=None) -> (k, 3)."""

    def displacement(self, g: Array) -> Array:
        """The displacement of every node. Shape: (k, 3) -> (n, 3)."""

    def reset(self) -> None:
        """Forget warm-start state (after a failed frame, say)."""


class ForwardModel(Protocol):
    method: str  # "fem" or "network"
    mesh: TetMesh
    material: Material

    def with_stiffness(self, E: float) -> ForwardModel:
        """The same model for another Young's modulus (a new object)."""

    def restrict(self, support: Array, nodes: Array | None = None) -> ForwardOperator:
        """An operator from forces on `support` to displacements of `nodes` (all by default)."""


def check_support(mesh: TetMesh, support: Array) -> Array:
    """Validated support node ids: integers, in range, not fixed, no repeats. Shape: (k,)."""
    s = np.asarray(support)
    if s.ndim != 1 or s.size == 0:
        raise ValueError("support must be a non-empty list of node ids")
    if not np.issubdtype(s.dtype, np.integer):
        raise ValueError("support node ids must be integers")
    s = s.astype(np.int64)
    if s.min() < 0 or s.max() >= mesh.n_nodes:
        raise ValueError(f"support node ids must lie in 0..{mesh.n_nodes - 1}")
    if not mesh.free_mask[s].all():
        bad = s[~mesh.free_mask[s]]
        raise ValueError(f"support contains fixed nodes: {bad[:10].tolist()}")
    if np.unique(s).size != s.size:
        raise ValueError("support repeats node ids")
    return s


def torch_forward(op: ForwardOperator):
    """A torch autograd function g (k, 3) -> u (p, 3) whose backward is the operator's pullback.

    Lets torch code (a loss, another network) sit on top of either forward model.
    """
    import torch

    class _Forward(torch.autograd.Function):
        @staticmethod
        def forward(ctx, g):
            u, pullback = op(g.detach().cpu().numpy().astype(np.float64))
            ctx.pullback = pullback
            return torch.as_tensor(u, dtype=g.dtype, device=g.device)

        @staticmethod
        def backward(ctx, u_bar):
            gb = ctx.pullback(u_bar.detach().cpu().numpy().astype(np.float64))
            return torch.as_tensor(gb, dtype=u_bar.dtype, device=u_bar.device)

    return _Forward.apply
