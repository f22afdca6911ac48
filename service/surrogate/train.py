"""Fitting a surrogate to FEM samples: split by load path, Adam with cosine decay, early stop
on the validation mean nodal error, fixed seeds, metrics in millimetres. Where enough paths are
held out, the epoch is chosen on one part of them and the figures reported on the other."""

from __future__ import annotations

import copy
import dataclasses
import logging
import time

import numpy as np
import torch

from ..fem.assembly import Assembler
from ..fem.rest import rest_compliance
from ..network_size import FEATURES, MAX_LAYERS, MAX_MEMBERS, MAX_WEIGHT_DECAY, MAX_WIDTH, WEIGHT_DECAY
from ..optional import need
from .basis import pod_basis
from .network import PaperSurrogate, ReducedSurrogate

log = logging.getLogger(__name__)

Array = np.ndarray

#: the largest seed: torch's manual_seed takes 0..2**64 - 1 (numpy's default_rng no negative one)
SEED_MAX = 2**64 - 1
#: the held-out paths a reported figure needs for the rebuild gate's confidence bound (its
#: REPLACE_MIN_PATHS in build.py is this): held-out paths are split into a part that chooses the
#: epoch and a part that reports only from twice as many, so each part keeps that many and a
#: split never costs the gate its bound. Fewer: one part does both, and the manifest says so
#: (the figure of the paths that chose the epoch is biased low: 3.45 % against 5.61 % on 150
#: fresh paths, the bar's timed build, seed 1; docs/performance.md)
REPORT_MIN_PATHS = 5


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    layout: str = "reduced"  # "reduced" or "paper"
    hidden: tuple[int, ...] = (512, 512)
    rank: int = 128  # POD modes (reduced layout)
    members: int | None = None  # independently trained MLPs over one basis, averaged (reduced
    # layout); None: the scene's [training] members when built from a scene, else 1
    physics_skip: bool = True  # the physics layout: the exact small-strain response outside the
    # network, which reads its features and learns the remainder (network.py; measured better
    # than raw forces on held-out loads, docs/performance.md)
    features: int = FEATURES  # POD modes of the linear response the physics layout's network reads
    epochs: int = 200
    batch: int = 128
    lr: float = 1e-3
    weight_decay: float = WEIGHT_DECAY  # Adam's L2 decay of the weight matrices (decay_groups)
    patience: int = 40  # epochs without validation improvement before stopping (not in a timed build)
    val_fraction: float = 0.1
    seed: int = 0
    device: str | None = None  # "cuda" when there is one, else "cpu"
    threads: int | None = None  # torch CPU threads (default: torch's)
    max_seconds: float | None = None  # wall-time cap on training (a timed build): the epochs
    # shrink to what fits, the learning-rate schedule with them
    zero_at_rest: bool = True  # the reduced layout answers exactly 0 at zero load, as the physics
    # does (its MLPs fit the change from rest; network.ReducedSurrogate.zero_at_rest_)

    def __post_init__(self) -> None:
        # refused here, where the config is made, so a command line fails before any data
        if self.layout not in ("reduced", "paper"):
            raise ValueError(f"unknown layout {self.layout!r}: 'reduced' or 'paper'")
        if self.members is not None and not 1 <= self.members <= MAX_MEMBERS:
            raise ValueError(f"members must be a whole number in 1..{MAX_MEMBERS}, got {self.members}")
        for key in ("rank", "features", "epochs"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be a whole number >= 1, got {getattr(self, key)}")
        if not 0 <= self.weight_decay <= MAX_WEIGHT_DECAY:  # NaN too
            raise ValueError(f"weight_decay must be a number in 0..{MAX_WEIGHT_DECAY:g}, got {self.weight_decay}")
        if not 0 <= self.seed <= SEED_MAX:  # else torch refused it after all the data
            raise ValueError(f"seed must be a whole number in 0..{SEED_MAX}, got {self.seed}")
        if not 1 <= len(self.hidden) <= MAX_LAYERS or not 1 <= min(self.hidden) <= max(self.hidden) <= MAX_WIDTH:
            raise ValueError(
                f"hidden layers must be 1..{MAX_LAYERS} widths in 1..{MAX_WIDTH}, got {list(self.hidden)[:8]}"
                + (f" ({len(self.hidden)} layers)" if len(self.hidden) > 8 else "")
            )
        if self.layout != "reduced" and (self.members or 1) > 1:
            raise ValueError("members > 1 (an ensemble) needs the reduced layout: its members share one POD basis")


@dataclasses.dataclass
class TrainResult:
    model: torch.nn.Module
    metrics: dict  # validation figures of the best epoch
    history: list[dict]
    config: TrainConfig
    train_paths: Array
    val_paths: Array  # every held-out path: selection_paths and report_paths
    selection_paths: Array  # the held-out paths that chose the epoch
    report_paths: Array  # those the figures come from: disjoint from selection_paths where enough are held out


def split_paths(path_ids: Array, val_fraction: float, seed: int) -> tuple[Array, Array]:
    """Whole load paths go to one side: steps of one path are too alike to split."""
    paths = np.unique(path_ids)
    rng = np.random.default_rng(seed)
    rng.shuffle(paths)
    n_val = max(1, int(round(val_fraction * paths.size))) if paths.size > 1 else 0
    return np.sort(paths[n_val:]), np.sort(paths[:n_val])


def split_held_out(val_paths: Array) -> tuple[Array, Array]:
    """The held-out paths that choose the epoch and those that report: every other one (the loads
    of the paths are drawn independently by index) from 2 x REPORT_MIN_PATHS on, else all of them twice."""
    if val_paths.size < 2 * REPORT_MIN_PATHS:
        return val_paths, val_paths
    return val_paths[::2], val_paths[1::2]


def nodal_errors(pred: Array, true: Array) -> Array:
    """Euclidean error per node per sample. Shape: (N, 3n) x2 -> (N, n)."""
    d = (pred - true).reshape(len(pred), -1, 3)
    return np.sqrt((d**2).sum(-1))


def ratio_standard_error(errors: Array, sizes: Array, paths: Array) -> float | None:
    """The standard error of sum(errors) / sum(sizes) over samples that come in load paths: the
    delta method's residuals errors - ratio * sizes summed per path, their spread over the
    paths' count, as the paths are independent and the steps of one path are not (one growing
    load; per sample the figure was 2.3x too small on simulated paths of 6 steps). None under two
    paths."""
    ids, path = np.unique(paths, return_inverse=True)
    total = float(sizes.sum())
    if ids.size < 2 or total <= 0:
        return None
    d = np.bincount(path, weights=errors - errors.sum() / total * sizes, minlength=ids.size)
    return float(np.sqrt((d**2).sum() * ids.size / (ids.size - 1)) / total)


def evaluate(
    model: torch.nn.Module,
    F: Array,
    U: Array,
    device: str = "cpu",
    chunk: int = 512,
    norms: Array | None = None,
    sizes: Array | None = None,
    paths: Array | None = None,
) -> dict:
    """Mean and 95th-percentile nodal error (mm), and mean and median relative error, over samples.
    `norms`: each sample's displacement norm, for the relative error, where U holds only part
    of it (the physics layout's remainders). `sizes` and `paths`: each sample's mean nodal
    displacement and load path, for the standard error of the mean error over the mean
    displacement (the figure a rebuild is compared by: build.relative_error) and the count of
    paths it rests on."""
    if sizes is not None and paths is None:
        raise ValueError("the relative error's standard error needs each sample's load path")
    errs, rel = [], []
    model.eval()
    with torch.no_grad():
        for i in range(0, len(F), chunk):
            g = torch.from_numpy(F[i : i + chunk].reshape(len(F[i : i + chunk]), -1)).float().to(device)
            pred = model(g).cpu().numpy()
            true = U[i : i + chunk].reshape(len(pred), -1)
            e = nodal_errors(pred, true)
            errs.append(e)
            size = np.linalg.norm(true, axis=1) if norms is None else norms[i : i + chunk]
            rel.append(np.linalg.norm(pred - true, axis=1) / np.maximum(size, 1e-12))
    e, rel_all = np.concatenate(errs), np.concatenate(rel)
    metrics = {
        "mean_mm": float(e.mean() * 1e3),
        "p95_mm": float(np.percentile(e, 95) * 1e3),
        "max_mm": float(e.max() * 1e3),
        "relative": float(np.mean(rel_all)),
        "relative_median": float(np.median(rel_all)),
        "samples": int(len(F)),
    }
    if sizes is not None and paths is not None:  # not relative_error_se: older entries' per-sample figure
        metrics["relative_error_path_se"] = ratio_standard_error(e.mean(1), sizes, paths)
        metrics["paths"] = int(np.unique(paths).size)
    return metrics


def build_model(
    config: TrainConfig, region: Array, F: Array, U: Array, feature_basis: Array | None = None
) -> torch.nn.Module:
    """The untrained network, with its basis and input scale computed from the training set.
    With `feature_basis` (the physics layout) F holds the features and U the remainders."""
    if feature_basis is None:
        n_in = 3 * len(region)
        x_scale = float(np.sqrt((F.reshape(len(F), -1) ** 2).sum(1).mean() / n_in)) or 1.0
    else:
        n_in = F.shape[1]
        x_scale = float(np.sqrt((F**2).mean())) or 1.0
    if config.layout == "paper":  # TrainConfig holds a paper layout to one member
        u_scale = float(np.sqrt((U.reshape(len(U), -1) ** 2).mean())) or 1.0
        return PaperSurrogate(
            n_in,
            U.shape[1] * U.shape[2],
            depth=max(2, len(config.hidden) + 1),
            force_scale=x_scale,
            u_scale=u_scale,
        )
    basis, _ = pod_basis(U.reshape(len(U), -1), config.rank, config.seed)
    coefs = U.reshape(len(U), -1) @ basis
    coef_scale = torch.full((basis.shape[1],), float(np.sqrt((coefs**2).mean())) or 1.0)
    return ReducedSurrogate(
        n_in, torch.from_numpy(basis), list(config.hidden), None, x_scale, coef_scale, members=config.members or 1,
        feature_basis=None if feature_basis is None else torch.from_numpy(feature_basis),
    )  # fmt: skip


def linear_features(asm: Assembler, region: Array, F: Array, train: Array, q: int, seed: int, chunk: int = 1024):
    """The physics layout's inputs and what it leaves to learn: the linear response L of every
    sample (K0^-1 g, chunked: N x 3n), a POD basis of the training samples' L (3n, q), and the
    features L @ basis (N, q) float32. Returns (features, basis, L) with L float32 (N, 3n)."""
    comp = rest_compliance(asm.mesh, asm.material)
    L = np.empty((len(F), 3 * asm.mesh.n_nodes), np.float32)
    for i in range(0, len(F), chunk):
        L[i : i + chunk] = comp.displacements(F[i : i + chunk], region)
    basis, _ = pod_basis(L[train], q, seed)
    return (L @ basis.astype(np.float32)), basis, L


def targets(model: torch.nn.Module, U: Array) -> Array:
    """What the network is fitted to: basis coefficients (reduced) or raw displacements."""
    U = U.reshape(len(U), -1)
    if isinstance(model, ReducedSurrogate):
        return U @ model.basis.double().numpy()
    return U


def _bar(tqdm, config: TrainConfig, spent: float, progress: bool):
    """The training's progress bar: epochs, or under a clock (a timed build, whose epoch count is
    only a ceiling) the seconds of its share, `spent` of them already (the model's making)."""
    if config.max_seconds is None:
        return tqdm(total=config.epochs, desc="training", unit="epoch", disable=not progress)
    return tqdm(
        total=config.max_seconds,
        initial=min(spent, config.max_seconds),
        desc="training",
        unit="s",
        bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]",
        disable=not progress,
    )


def decay_groups(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """Adam's parameter groups: the L2 decay on weight matrices alone. Decayed, a PReLU's slopes
    sank to 6e-15 and its units' gradients into subnormal floats, which CPUs handle slowly: epochs
    2x slower by the 700th (docs/performance.md). Biases are left undecayed too, the usual rule."""
    params = list(model.parameters())
    return [
        {"params": [p for p in params if p.ndim >= 2], "weight_decay": weight_decay},
        {"params": [p for p in params if p.ndim < 2], "weight_decay": 0.0},
    ]


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
    selection_paths, report_paths = split_held_out(val_paths)
    tr = np.isin(path_ids, train_paths)
    va = np.isin(path_ids, selection_paths) if val_paths.size else tr  # chooses the epoch
    rep = np.isin(path_ids, report_paths) if val_paths.size else tr  # the figures reported
    F = F.reshape(len(F), -1).astype(np.float32)
    sizes = np.linalg.norm(U[rep], axis=-1).mean(1)  # each sample's mean nodal displacement
    zero_mm = float(sizes.mean() * 1e3)  # the u = 0 baseline
    norm_all = np.linalg.norm(U.reshape(len(U), -1), axis=1)  # the relative error's yardstick
    norms, norms_rep = norm_all[va], norm_all[rep]
    linear_mm = None
    if config.layout == "reduced" and config.physics_skip:
        # the network sees features of the linear response and fits what it leaves: every
        # figure below is on the remainder, which is the error of linear + network
        F, feature_basis, L = linear_features(asm, region, F, tr, config.features, config.seed)
        U = (U.reshape(len(U), -1) - L).reshape(U.shape)
        del L
        linear_mm = float(np.linalg.norm(U[rep], axis=-1).mean() * 1e3)
    else:
        feature_basis = None
    model = build_model(config, region, F[tr], U[tr], feature_basis).to(device)
    Y = torch.from_numpy(targets(model.cpu(), U).astype(np.float32))
    model.to(device)
    X = torch.from_numpy(F)
    Xtr, Ytr = X[tr].to(device), Y[tr].to(device)
    y_norm = float((Ytr**2).sum(1).mean())
    reduced = isinstance(model, ReducedSurrogate)

    at_rest = reduced and config.zero_at_rest
    rest = torch.zeros(1, Xtr.shape[1], device=device)

    def predict(x):
        """(members, B, out): each member fits the targets on its own (an ensemble trained on
        the loss of its mean would be one wide network, without the members' independence)."""
        if not at_rest:
            return model.member_coefficients(x) if reduced else model(x)[None]
        out = model.member_coefficients(torch.cat([x, rest]))
        return out[:, :-1] - out[:, -1:]

    opt = torch.optim.Adam(decay_groups(model, config.weight_decay), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs, eta_min=config.lr * 1e-2)
    gen = torch.Generator().manual_seed(config.seed)
    # the untrained model (the linear response alone in the physics layout) is a candidate too:
    # a build never ships a network worse on held-out paths than where it started
    start = evaluate(model, F[va], U[va], device, norms=norms)
    start_report = evaluate(model, F[rep], U[rep], device, norms=norms_rep)  # the linear response's figure
    best, best_state, history, stale = start["mean_mm"], copy.deepcopy(model.state_dict()), [], 0
    bar = _bar(tqdm, config, time.perf_counter() - t_start, progress)
    t0 = time.perf_counter()
    loop_budget = None if config.max_seconds is None else config.max_seconds - (t0 - t_start)
    for epoch in range(config.epochs):
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
        if at_rest:
            model.zero_at_rest_()
        metrics = evaluate(model, F[va], U[va], device, norms=norms)
        elapsed = time.perf_counter() - t0
        if loop_budget is not None and epoch == 0:  # the schedule ends where the clock does
            fits = int(loop_budget / max(elapsed, 1e-9))
            sched.T_max = max(1, min(config.epochs, fits))
        history.append({"epoch": epoch, "loss": total / len(Xtr), **metrics, "seconds": time.perf_counter() - t0})
        if config.max_seconds is None:
            bar.update(1)
        else:  # the seconds of its share spent, the epoch beside them
            bar.update(min(time.perf_counter() - t_start, bar.total) - bar.n)
        bar.set_postfix(
            **({} if config.max_seconds is None else {"epoch": epoch + 1}),
            loss=f"{total / len(Xtr):.2e}",
            val_mm=f"{metrics['mean_mm']:.3f}",
            p95=f"{metrics['p95_mm']:.2f}",
        )
        if metrics["mean_mm"] < best:
            best, best_state, stale = metrics["mean_mm"], copy.deepcopy(model.state_dict()), 0
        else:
            stale += 1
            # a timed build spends its minutes: the best epoch is kept, so later ones cost only time
            if stale >= config.patience and config.max_seconds is None:
                log.info("early stop at epoch %d", epoch)
                break
        if loop_budget is not None and elapsed * (epoch + 2) / (epoch + 1) > loop_budget:  # no room for one more
            log.info("training stops at epoch %d: its %.0f s are spent", epoch, config.max_seconds)
            break
    bar.close()
    model.load_state_dict(best_state)
    model.cpu().eval()
    final = evaluate(model, F[rep], U[rep], norms=norms_rep, sizes=sizes, paths=path_ids[rep])
    final["zero_mean_mm"] = zero_mm
    if linear_mm is not None:  # the linear response alone (the physics layout's start)
        final["linear_mean_mm"], final["linear_relative_median"] = linear_mm, start_report["relative_median"]
    # which held-out paths the figures come from, and which chose the epoch (the same ones, and
    # so biased low, under 2 x REPORT_MIN_PATHS held out)
    final["report_paths"] = [int(i) for i in report_paths]
    final["selection_paths"] = [int(i) for i in selection_paths]
    final["chosen_on_report_paths"] = bool(np.array_equal(selection_paths, report_paths))
    final["train_samples"] = int(tr.sum())
    final["train_seconds"] = time.perf_counter() - t0
    final["epochs"] = len(history)
    return TrainResult(model, final, history, config, train_paths, val_paths, selection_paths, report_paths)
