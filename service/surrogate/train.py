"""Fitting a surrogate to FEM samples: split by load path, Adam with cosine decay, early stop
on the validation mean nodal error, fixed seeds, metrics in millimetres."""

from __future__ import annotations

import copy
import dataclasses
import logging
import time

import numpy as np
import torch

from ..fem.assembly import Assembler
from ..optional import need
from .basis import linear_response, pod_basis
from .network import PaperSurrogate, ReducedSurrogate

log = logging.getLogger(__name__)

Array = np.ndarray


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    layout: str = "reduced"  # "reduced" or "paper"
    hidden: tuple[int, ...] = (512, 512)
    rank: int = 128  # POD modes (reduced layout)
    members: int | None = None  # independently trained MLPs over one basis, averaged (reduced
    # layout); None: the scene's [training] members when built from a scene, else 1
    physics_skip: bool = False  # linear small-strain skip path: measured no better on held-out
    # paths and 2x worse on the paper's frames (see the README's surrogate section)
    epochs: int = 200
    batch: int = 128
    lr: float = 1e-3
    weight_decay: float = 0.0
    patience: int = 40  # epochs without validation improvement before stopping
    val_fraction: float = 0.1
    seed: int = 0
    device: str | None = None  # "cuda" when there is one, else "cpu"
    threads: int | None = None  # torch CPU threads (default: torch's)
    max_seconds: float | None = None  # wall-time cap on training (a timed build): the epochs
    # shrink to what fits, the learning-rate schedule with them

    def __post_init__(self) -> None:
        # refused here, where the config is made, so a command line fails before any data
        if self.layout not in ("reduced", "paper"):
            raise ValueError(f"unknown layout {self.layout!r}: 'reduced' or 'paper'")
        if self.members is not None and self.members < 1:
            raise ValueError(f"members must be a whole number >= 1, got {self.members}")
        if self.layout != "reduced" and (self.members or 1) > 1:
            raise ValueError("members > 1 (an ensemble) needs the reduced layout: its members share one POD basis")


@dataclasses.dataclass
class TrainResult:
    model: torch.nn.Module
    metrics: dict  # validation figures of the best epoch
    history: list[dict]
    config: TrainConfig
    train_paths: Array
    val_paths: Array


def split_paths(path_ids: Array, val_fraction: float, seed: int) -> tuple[Array, Array]:
    """Whole load paths go to one side: steps of one path are too alike to split."""
    paths = np.unique(path_ids)
    rng = np.random.default_rng(seed)
    rng.shuffle(paths)
    n_val = max(1, int(round(val_fraction * paths.size))) if paths.size > 1 else 0
    return np.sort(paths[n_val:]), np.sort(paths[:n_val])


def nodal_errors(pred: Array, true: Array) -> Array:
    """Euclidean error per node per sample. Shape: (N, 3n) x2 -> (N, n)."""
    d = (pred - true).reshape(len(pred), -1, 3)
    return np.sqrt((d**2).sum(-1))


def evaluate(model: torch.nn.Module, F: Array, U: Array, device: str = "cpu", chunk: int = 512) -> dict:
    """Mean and 95th-percentile nodal error (mm), and mean relative error, over samples."""
    errs, rel = [], []
    model.eval()
    with torch.no_grad():
        for i in range(0, len(F), chunk):
            g = torch.from_numpy(F[i : i + chunk].reshape(len(F[i : i + chunk]), -1)).float().to(device)
            pred = model(g).cpu().numpy()
            true = U[i : i + chunk].reshape(len(pred), -1)
            e = nodal_errors(pred, true)
            errs.append(e)
            rel.append(np.linalg.norm(pred - true, axis=1) / np.maximum(np.linalg.norm(true, axis=1), 1e-12))
    e = np.concatenate(errs)
    return {
        "mean_mm": float(e.mean() * 1e3),
        "p95_mm": float(np.percentile(e, 95) * 1e3),
        "max_mm": float(e.max() * 1e3),
        "relative": float(np.mean(np.concatenate(rel))),
        "samples": int(len(F)),
    }


def build_model(config: TrainConfig, asm: Assembler, region: Array, F: Array, U: Array) -> torch.nn.Module:
    """The untrained network, with its basis and physics prior computed from the training set."""
    n_in = 3 * len(region)
    force_scale = float(np.sqrt((F.reshape(len(F), -1) ** 2).sum(1).mean() / n_in)) or 1.0
    if config.layout == "paper":  # TrainConfig holds a paper layout to one member
        u_scale = float(np.sqrt((U.reshape(len(U), -1) ** 2).mean())) or 1.0
        return PaperSurrogate(
            n_in,
            U.shape[1] * U.shape[2],
            depth=max(2, len(config.hidden) + 1),
            force_scale=force_scale,
            u_scale=u_scale,
        )
    basis, _ = pod_basis(U.reshape(len(U), -1), config.rank, config.seed)
    coefs = U.reshape(len(U), -1) @ basis
    coef_scale = torch.full((basis.shape[1],), float(np.sqrt((coefs**2).mean())) or 1.0)
    skip = None
    if config.physics_skip:
        skip = torch.from_numpy(basis.T @ linear_response(asm, region))  # (r, 3R)
    return ReducedSurrogate(
        n_in, torch.from_numpy(basis), list(config.hidden), skip, force_scale, coef_scale, members=config.members or 1
    )


def targets(model: torch.nn.Module, U: Array) -> Array:
    """What the network is fitted to: basis coefficients (reduced) or raw displacements."""
    U = U.reshape(len(U), -1)
    if isinstance(model, ReducedSurrogate):
        return U @ model.basis.double().numpy()
    return U


def train(
    F: Array,
    U: Array,
    path_ids: Array,
    asm: Assembler,
    region: Array,
    config: TrainConfig = TrainConfig(),
    progress: bool = True,
) -> TrainResult:
    """Fit a surrogate to samples F (N, R, 3) -> U (N, n, 3), validating on held-out paths."""
    tqdm = need("tqdm.auto", "the trainer's progress bar").tqdm
    t_start = time.perf_counter()  # a capped training counts its model's making (a skip path's solves)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = config.device or ("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(config.seed)
    train_paths, val_paths = split_paths(path_ids, config.val_fraction, config.seed)
    tr = np.isin(path_ids, train_paths)
    va = np.isin(path_ids, val_paths) if val_paths.size else tr
    F = F.reshape(len(F), -1).astype(np.float32)

    model = build_model(config, asm, region, F[tr], U[tr]).to(device)
    Y = torch.from_numpy(targets(model.cpu(), U).astype(np.float32))
    model.to(device)
    X = torch.from_numpy(F)
    Xtr, Ytr = X[tr].to(device), Y[tr].to(device)
    y_norm = float((Ytr**2).sum(1).mean())
    reduced = isinstance(model, ReducedSurrogate)

    def predict(x):
        """(members, B, out): each member fits the targets on its own (an ensemble trained on
        the loss of its mean would be one wide network, without the members' independence)."""
        return model.member_coefficients(x) if reduced else model(x)[None]

    opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs, eta_min=config.lr * 1e-2)
    gen = torch.Generator().manual_seed(config.seed)
    best, best_state, history, stale = np.inf, None, [], 0
    bar = tqdm(range(config.epochs), desc="training", unit="epoch", disable=not progress)
    t0 = time.perf_counter()
    loop_budget = None if config.max_seconds is None else config.max_seconds - (t0 - t_start)
    for epoch in bar:
        model.train()
        order = torch.randperm(len(Xtr), generator=gen).to(device)
        total = 0.0
        for i in range(0, len(order), config.batch):
            idx = order[i : i + config.batch]
            loss = ((predict(Xtr[idx]) - Ytr[idx]) ** 2).sum(-1).mean() / y_norm
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.item() * len(idx)
        sched.step()
        metrics = evaluate(model, F[va], U[va], device)
        elapsed = time.perf_counter() - t0
        if loop_budget is not None and epoch == 0:  # the schedule ends where the clock does
            fits = int(loop_budget / max(elapsed, 1e-9))
            sched.T_max = max(1, min(config.epochs, fits))
        history.append({"epoch": epoch, "loss": total / len(Xtr), **metrics, "seconds": time.perf_counter() - t0})
        bar.set_postfix(
            loss=f"{total / len(Xtr):.2e}", val_mm=f"{metrics['mean_mm']:.3f}", p95=f"{metrics['p95_mm']:.2f}"
        )
        if metrics["mean_mm"] < best:
            best, best_state, stale = metrics["mean_mm"], copy.deepcopy(model.state_dict()), 0
        else:
            stale += 1
            if stale >= config.patience:
                log.info("early stop at epoch %d", epoch)
                break
        if loop_budget is not None and elapsed * (epoch + 2) / (epoch + 1) > loop_budget:  # no room for one more
            log.info("training stops at epoch %d: its %.0f s are spent", epoch, config.max_seconds)
            break
    bar.close()
    model.load_state_dict(best_state)
    model.cpu().eval()
    final = evaluate(model, F[va], U[va])
    final["zero_mean_mm"] = float(np.linalg.norm(U[va], axis=-1).mean() * 1e3)  # the u = 0 baseline
    final["train_samples"] = int(tr.sum())
    final["train_seconds"] = time.perf_counter() - t0
    final["epochs"] = len(history)
    return TrainResult(model, final, history, config, train_paths, val_paths)
