"""A torch network's layers as float32 NumPy arrays, for the operator's hand-written passes.

Each layer is (W, b, PReLU slopes or None). An ensemble becomes one wider network whose
layers between the first and the last are block-diagonal, kept as their blocks
(:class:`BlockDiagonal`).
"""

from __future__ import annotations

import numpy as np
import torch

from .network import Ensemble

Array = np.ndarray


def mlp_layers(mlp: torch.nn.Sequential) -> list[tuple[Array, Array, Array | None]]:
    """(W, b, PReLU slopes or None) per layer of one MLP, as float32 arrays."""
    mods = list(mlp)
    out = []
    for i, m in enumerate(mods):
        if isinstance(m, torch.nn.Linear):
            nxt = mods[i + 1] if i + 1 < len(mods) else None
            a = None
            if isinstance(nxt, torch.nn.PReLU):
                a = nxt.weight.detach().numpy().astype(np.float32)
                a = np.broadcast_to(a, (m.out_features,)).copy()
            out.append((m.weight.detach().numpy().astype(np.float32), m.bias.detach().numpy().astype(np.float32), a))
    return out


def network_layers(net: torch.nn.Module) -> list:
    """(W, b, PReLU slopes or None) per layer of the network's MLP. An ensemble's members
    become one MLP whose hidden units are all the members' side by side: the first layer
    stacked, the layers between block-diagonal (kept as blocks), the last side by side and
    divided by their number (their mean)."""
    if not isinstance(net.net, Ensemble):
        return mlp_layers(net.net)
    each = [mlp_layers(m) for m in net.net.members]
    k, depth = len(each), len(each[0])
    out = []
    for i, parts in enumerate(zip(*each, strict=True)):
        Ws, bs, slopes = zip(*parts, strict=True)
        if i == depth - 1:  # the last: the members' mean
            W, b = np.hstack(Ws) / np.float32(k), np.sum(bs, axis=0) / np.float32(k)
        else:
            W = np.vstack(Ws) if i == 0 else BlockDiagonal(np.stack(Ws))
            b = np.concatenate(bs)
        a = None if slopes[0] is None else np.concatenate(slopes)
        out.append((W, b, a))
    return out


class BlockDiagonal:
    """A block-diagonal matrix kept as its blocks (q, m, n): an ensemble's layers between the
    first and the last. Products cost the blocks' q m n, not the dense (q m)(q n) (3 members
    of 512: 0.12 ms against 0.37 ms a product). NumPy defers ``A @ self`` to it."""

    __array_ufunc__ = None  # ndarray @ BlockDiagonal -> BlockDiagonal.__rmatmul__

    def __init__(self, blocks: Array, transposed: BlockDiagonal | None = None) -> None:
        # a transpose reads its original's memory (a view: BLAS takes each block transposed)
        self.blocks = blocks if transposed is not None else np.ascontiguousarray(blocks)
        q, m, n = blocks.shape
        self.shape = (q * m, q * n)
        self.dtype = blocks.dtype
        self._T = transposed

    @property
    def T(self) -> BlockDiagonal:
        """Made once, a view of the same blocks: the pullback's products then read the
        weights the forward pass just read, not a second copy."""
        if self._T is None:
            self._T = BlockDiagonal(self.blocks.transpose(0, 2, 1), transposed=self)
        return self._T

    def astype(self, dtype, copy: bool = True) -> BlockDiagonal:
        if not copy and self.dtype == dtype:
            return self
        return BlockDiagonal(self.blocks.astype(dtype))

    def __matmul__(self, x: Array) -> Array:
        """self @ x for x (q n,) or (q n, c)."""
        q, _, n = self.blocks.shape
        y = np.matmul(self.blocks, x.reshape(q, n, -1))  # (q, m, c)
        return y.reshape(-1) if x.ndim == 1 else y.reshape(-1, x.shape[1])

    def __rmatmul__(self, A: Array) -> Array:
        """A @ self for A (c, q m)."""
        q, m, n = self.blocks.shape
        y = np.matmul(A.reshape(-1, q, m).transpose(1, 0, 2), self.blocks)  # (q, c, n)
        return np.ascontiguousarray(y.transpose(1, 0, 2)).reshape(A.shape[0], q * n)

    def __getitem__(self, rows: Array) -> Array:
        """Dense rows (len(rows), q n): zeros outside each row's block."""
        q, m, n = self.blocks.shape
        rows = np.asarray(rows)
        out = np.zeros((rows.size, q * n), self.dtype)
        blk, r = np.divmod(rows, m)
        cols = blk[:, None] * n + np.arange(n)
        out[np.arange(rows.size)[:, None], cols] = self.blocks[blk, r]
        return out
