"""The network an entry's manifest describes, built from its tensors, and checked to fit the
entry's mesh and load region."""

from __future__ import annotations

import re

import numpy as np
import torch

from ..mesh import TetMesh
from ..surrogate.network import PaperSurrogate, ReducedSurrogate
from .files import MESH, WEIGHTS, StoreError


def network_from_manifest(spec: dict, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """Rebuild the module the manifest describes (shapes come from the saved tensors). A
    ValueError in one line when the tensors do not fit it (``spec`` checked by _check_network)."""
    # the counts first, from the tensors' names: laying out members 100000 took 123 s and 2.6 GB
    # even on the meta device, before its refusal
    _check_counts(spec, state)
    # laid out on the meta device first (shapes, no storage): a manifest that claims a network
    # far larger than its weights is refused before it allocates (hidden 10^6: 3.2 GB, then refused)
    with torch.device("meta"):
        mismatch = _state_mismatch(_network_of(spec, state).state_dict(), state)
    if mismatch:
        raise ValueError(mismatch)
    net = _network_of(spec, state)
    net.load_state_dict(state, strict=True)
    return net.eval()


#: an MLP's weight matrix: net.<layer>.weight, or net.members.<member>.<layer>.weight in an ensemble
_MLP_WEIGHT = re.compile(r"net\.(?:members\.(\d+)\.)?(\d+)\.weight")


def _check_counts(spec: dict, state: dict[str, torch.Tensor]) -> None:
    """ValueError, in one line, where the manifest's member count or layer count (len(hidden)
    + 1 weight matrices per member) is not the file's, read from its tensors' names and ranks."""
    matrices: dict[int, int] = {}  # member (0 outside an ensemble) -> its weight matrices
    ensemble = False
    for key, tensor in state.items():
        found = _MLP_WEIGHT.fullmatch(key)
        if found and tensor.ndim == 2:
            ensemble |= found[1] is not None
            member = int(found[1] or 0)
            matrices[member] = matrices.get(member, 0) + 1
    members = int(spec.get("members", 1)) if spec.get("layout") == "reduced" else 1
    held = len(matrices) if ensemble else 1
    if members != held:
        raise ValueError(f"the manifest's network.members is {members}, the file holds {held} member(s)")
    layers, per_member = len(spec["hidden"]) + 1, sorted(set(matrices.values())) or [0]
    if per_member != [layers]:
        raise ValueError(
            f"the manifest's network.hidden has {len(spec['hidden'])} layers ({layers} weight matrices per member), "
            f"the file holds {', '.join(map(str, per_member))}"
        )


def _network_of(spec: dict, state: dict[str, torch.Tensor]) -> torch.nn.Module:
    """The manifest's layout, untrained, on the default device (the caller's ``torch.device``)."""
    layout = spec.get("layout")
    if layout == "reduced":
        basis = state.get("basis")
        if basis is None or basis.ndim != 2:
            raise ValueError("no 'basis' matrix among its tensors" if basis is None else "its 'basis' is not a matrix")
        return ReducedSurrogate(
            int(spec["n_in"]), basis, [int(h) for h in spec["hidden"]], members=int(spec.get("members", 1)),
            feature_basis=state.get("feature_basis"),  # the physics layout's (older entries: none)
        )  # fmt: skip
    if layout == "paper":
        return PaperSurrogate(int(spec["n_in"]), int(spec["n_out"]), depth=len(spec["hidden"]) + 1)
    raise StoreError(f"unknown network layout {layout!r}")


def _state_mismatch(wanted: dict[str, torch.Tensor], got: dict[str, torch.Tensor]) -> str | None:
    """What differs between the tensors a network needs and those a file holds, in one line
    (torch's own message takes a line per tensor); None when they fit."""

    def some(names) -> str:
        names = sorted(names)
        return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")

    parts = []
    missing, extra = wanted.keys() - got.keys(), got.keys() - wanted.keys()
    if missing:
        parts.append(f"{len(missing)} missing ({some(missing)})")
    if extra:
        parts.append(f"{len(extra)} not in the network ({some(extra)})")
    shaped = sorted(k for k in wanted.keys() & got.keys() if wanted[k].shape != got[k].shape)
    if shaped:
        k = shaped[0]
        parts.append(
            f"{len(shaped)} of another shape ({k}: {list(got[k].shape)} in the file, {list(wanted[k].shape)} "
            f"in the network{' ...' if len(shaped) > 1 else ''})"
        )
    return "tensors " + "; ".join(parts) if parts else None


def _check_fit(net: torch.nn.Module, mesh: TetMesh, region: np.ndarray, name: str) -> None:
    """The network answers for this mesh's nodes and reads this region's forces: a mesh.npz
    from another entry (under checksums made to match) loaded, and its first frame was a 500."""
    n3 = 3 * mesh.n_nodes
    shapes = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    by_region = f"3 per node of the {region.size}-node region"
    if "basis" in shapes:  # the reduced layout: u = basis (3n, r) times the coefficients
        rows = {"basis": shapes["basis"][0]}
        n_in = shapes["skip.weight"][1]
        if "feature_basis" in shapes:  # the physics layout reads K0^-1 g in its features
            rows["feature_basis"] = shapes["feature_basis"][0]
            inputs, wanted = shapes["feature_basis"][1], "its feature_basis's columns"
        else:
            inputs, wanted = 3 * region.size, by_region
    else:  # the paper's: forces on the region in, displacements (3n) out
        layers = sorted((int(k.split(".")[1]), v) for k, v in shapes.items() if k.endswith(".weight") and len(v) == 2)
        rows = {"output": layers[-1][1][0]}
        n_in, inputs, wanted = layers[0][1][1], 3 * region.size, by_region
    for what, n in rows.items():
        if n != n3:
            raise StoreError(
                f"{name}: {MESH} does not fit {WEIGHTS}: the network's {what} has {n} rows (a {n // 3}-node "
                f"mesh's), the mesh has {mesh.n_nodes} nodes"
            )
    if n_in != inputs:
        raise StoreError(
            f"{name}: {MESH} does not fit {WEIGHTS}: the network reads {n_in} inputs, {wanted} would be {inputs}"
        )
