"""Surrogate networks: nodal forces on the load region -> nodal displacements.

Two layouts:

- ``"reduced"`` (the default, chosen by measurement: see the README's surrogate section): an MLP
  from the region's force dofs to the coefficients of a POD basis learnt from the training
  displacements, plus a linear skip path initialised with the exact small-strain response
  projected onto that basis. Physics gives the linear part for free; the network only learns the
  nonlinear remainder, and the basis keeps its output small (r << 3n) and smooth.
- ``"paper"``: the paper's network, fully connected layers as wide as the number of degrees of
  freedom with PReLU activations, nodal forces in, nodal displacements out.

With a ``feature_basis`` (the physics layout, built by default) the exact small-strain response
K0^-1 g lies outside the network, added by the forward model over any support (fem/rest.py),
and the network reads that response's coefficients in its own POD basis (the features), not
the raw forces: its output is the nonlinear remainder, in a POD basis of remainders. A local
load's response is a field the features describe at any site, so what is learnt at some sites
carries to others; raw forces at a site few paths loaded are inputs it has barely seen (on the paper's
liver, whole surface, 3,220 samples: linear alone 0.78 mm, the network on raw forces 1.15-1.46
mm, on features 0.49 mm; docs/performance.md).

The reduced layout may hold an ensemble of ``members`` MLPs over one basis and skip path, each
trained on its own loss from its own initialisation; it answers their mean. One network's error
depends on its training run (the liver's resultant-force error over three seeds: 7.8-10.3 %);
the mean of independently trained members has less of that spread (see the README).

Shapes: forces g (B, 3R) flattened node-major over the region's R nodes; coefficients (B, r);
displacements (B, 3n) node-major.
"""

from __future__ import annotations

import torch
from torch import nn


def mlp(n_in: int, hidden: list[int], n_out: int) -> nn.Sequential:
    """Linear/PReLU stack; the last layer is linear and starts at zero (the skip path rules
    at initialisation, so training starts from the physics prior, not from noise)."""
    layers: list[nn.Module] = []
    width = n_in
    for h in hidden:
        layers += [nn.Linear(width, h), nn.PReLU(h)]
        width = h
    last = nn.Linear(width, n_out)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


class Ensemble(nn.Module):
    """Independently initialised MLPs of one shape; answers the mean of their outputs."""

    def __init__(self, n_in: int, hidden: list[int], n_out: int, members: int) -> None:
        super().__init__()
        self.members = nn.ModuleList(mlp(n_in, hidden, n_out) for _ in range(members))

    def each(self, x: torch.Tensor) -> torch.Tensor:
        """Every member's output. Shape: (B, n_in) -> (members, B, n_out)."""
        return torch.stack([m(x) for m in self.members])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.each(x).mean(0)


class ReducedSurrogate(nn.Module):
    """c = A x + MLP(x) in a POD basis; u = basis @ (c * scale). x: the region's forces, or in
    the physics layout the features of their linear response (then u is the remainder).

    `skip` (r, n_in) is a trainable linear map (zero, or the linear response in basis
    coordinates for the older in-basis skip path).
    With `members` > 1 the MLP is an :class:`Ensemble` (the skip path stays one, shared).
    Inputs are divided by `force_scale` and coefficients multiplied by `coef_scale` so the
    network works with O(1) numbers.
    """

    layout = "reduced"

    def __init__(
        self,
        n_in: int,
        basis: torch.Tensor,
        hidden: list[int],
        skip: torch.Tensor | None = None,
        force_scale: float = 1.0,
        coef_scale: torch.Tensor | None = None,
        members: int = 1,
        feature_basis: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        if members < 1:
            raise ValueError(f"members must be at least 1, not {members}")
        r = basis.shape[1]
        self.register_buffer("basis", basis.float())  # (3n, r), orthonormal columns
        self.register_buffer("force_scale", torch.tensor(float(force_scale)))
        cs = torch.ones(r) if coef_scale is None else coef_scale.float()
        self.register_buffer("coef_scale", cs)
        self.skip = nn.Linear(n_in, r, bias=False)
        if skip is None:
            nn.init.zeros_(self.skip.weight)
        else:
            with torch.no_grad():
                self.skip.weight.copy_(skip.float() * (force_scale / cs[:, None]))
        self.net = mlp(n_in, hidden, r) if members == 1 else Ensemble(n_in, hidden, r, members)
        self.hidden = list(hidden)
        self.members = members
        if feature_basis is not None:  # (3n, q): the physics layout's input is K0^-1 g in it
            self.register_buffer("feature_basis", feature_basis.float())

    @property
    def physics(self) -> bool:
        """Whether the forward model adds the exact linear response and feeds its features."""
        return "feature_basis" in self._buffers

    def coefficients(self, g: torch.Tensor) -> torch.Tensor:
        x = g / self.force_scale
        return (self.skip(x) + self.net(x)) * self.coef_scale

    def member_coefficients(self, g: torch.Tensor) -> torch.Tensor:
        """Each member's coefficients, what each is trained on. Shape: (members, B, r)."""
        x = g / self.force_scale
        out = self.net.each(x) if isinstance(self.net, Ensemble) else self.net(x)[None]
        return (self.skip(x) + out) * self.coef_scale

    def forward(self, g: torch.Tensor) -> torch.Tensor:
        return self.coefficients(g) @ self.basis.T

    @torch.no_grad()
    def zero_at_rest_(self) -> None:
        """Shift each MLP's last bias so that it answers 0 at zero load (rest is exact): the
        trainer fits the outputs' change from rest, to which that bias is blind."""
        mlps = self.net.members if isinstance(self.net, Ensemble) else [self.net]
        for m in mlps:
            assert isinstance(m, nn.Sequential)
            m[-1].bias -= m(torch.zeros(1, m[0].in_features, device=m[-1].bias.device))[0]


class PaperSurrogate(nn.Module):
    """The paper's layout: FC layers of width 3n (the dofs), PReLU, forces in, displacements out."""

    layout = "paper"

    def __init__(self, n_in: int, n_out: int, depth: int = 4, force_scale: float = 1.0, u_scale: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("force_scale", torch.tensor(float(force_scale)))
        self.register_buffer("u_scale", torch.tensor(float(u_scale)))
        self.net = mlp(n_in, [n_out] * (depth - 1), n_out)
        self.hidden = [n_out] * (depth - 1)

    def forward(self, g: torch.Tensor) -> torch.Tensor:
        return self.net(g / self.force_scale) * self.u_scale
