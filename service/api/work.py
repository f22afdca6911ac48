"""What the routes hand to the engine, and the pool that runs it off the event loop.

Every function here that touches the engine is a plain ``def`` run by :class:`SolvePool` (a
fixed number of threads, ``solver_threads``): the event loop only reads sockets, decodes small
bodies and writes replies, so ``/health`` and other streams answer while a long FEM frame runs.
A job returns the encoded reply (encoding a large field is work too). The engine's
``ValueError`` (a support node outside the network's region, a fixed node, ...) becomes a 422
carrying its message; anything else is a bug and surfaces as a 500 with its traceback logged.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..registration.settings import NAMES
from . import codec
from .errors import ApiError, unprocessable
from .schemas import FrameIn, SessionCreate, SimulateIn
from .sessions import Held, Reservation, SessionRegistry

log = logging.getLogger(__name__)

#: the settings handed over as they are (support, matching and outputs change form on the way)
_FIELDS = tuple(n for n in NAMES if n not in ("support", "matching", "outputs"))


def _ms(t0: float) -> float:
    return 1e3 * (time.perf_counter() - t0)


class SolvePool:
    """A fixed thread pool for solves; ``await pool.run(fn, ...)`` from the event loop."""

    def __init__(self, threads: int) -> None:
        self.threads = threads
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="elastreg-solve")

    async def run(self, fn: Callable, *args, **kwargs) -> Any:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, functools.partial(fn, *args, **kwargs))

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


# -- sessions ------------------------------------------------------------------------------------


def build_session(entry, create: SessionCreate, reservation: Reservation) -> Held:
    """The engine's Session for a validated config, wrapped for the registry (in the pool)."""
    # the engine: loaded by the app already
    from ..registration.session import Session, SessionConfig

    given = {k: getattr(create, k) for k in _FIELDS if getattr(create, k) is not None}
    if create.support is not None:
        given["support"] = tuple(create.support.tolist())
    if create.matching is not None:
        given["matching"] = tuple(map(tuple, create.matching.tolist()))
    given["outputs"] = tuple(create.outputs)
    try:
        if create.method == "auto":
            session = Session(entry.network, SessionConfig(**given), corrector=entry.fem)
        else:
            session = Session(entry.model(create.method), SessionConfig(**given))
    except ValueError as exc:
        raise unprocessable(str(exc)) from None
    c = session.config
    config = {k: getattr(c, k) for k in _FIELDS}
    config.update(
        model=entry.id,
        outputs=list(c.outputs),
        matching=np.asarray(c.matching, np.int64) if c.matching is not None else session.mesh.surface_faces,
        skip_stale=create.skip_stale,
    )
    return Held(id=reservation.id, kind=reservation.kind, model=entry.id, session=session, config=config)


def config_of(held: Held) -> dict:
    """The session's effective config now (its current support included)."""
    return {"model": held.model, "method": held.config["method"], "support": held.session.support,
            **{k: v for k, v in held.config.items() if k not in ("model", "method")}}


async def open_session(entry, create: SessionCreate, *, kind: str, registry: SessionRegistry, pool: SolvePool) -> Held:
    """Reserve a slot (RegistryFull at the limit, before any work), build, register."""
    reservation = registry.reserve(kind)
    try:
        held = await pool.run(build_session, entry, create, reservation)
    except BaseException:
        registry.cancel(reservation)
        raise
    return registry.commit(reservation, held)


def opened(held: Held, instance: str) -> dict:
    return {"session": held.id, "config": config_of(held), "instance": instance}


def info(held: Held, registry: SessionRegistry) -> dict:
    return {
        "session": held.id,
        "kind": held.kind,
        "instance": registry.instance_id,
        "config": config_of(held),
        "counters": held.session.summary(),
        "created": held.created,
        "idle_s": registry.idle(held),
        "expires_in_s": registry.expires_in(held),
    }


# -- frames --------------------------------------------------------------------------------------


def frame_payload(result) -> dict:
    """A FrameResult as the reply's map (arrays stay arrays: the codec packs or lists them)."""
    out = {
        "frame_id": result.frame_id,
        "converged": bool(result.converged),
        "status": result.status,
        "message": result.message,
        "objective": float(result.objective),
        "distance_rms": float(result.distance_rms),
        "iterations": int(result.iterations),
        "evaluations": int(result.evaluations),
        "net_force": result.net_force,
        "alpha": float(result.alpha),
        "error_estimate": float(result.error_estimate) if np.isfinite(result.error_estimate) else None,
        "method_used": result.method_used,
    }
    out.update(result.outputs)
    if "forces" in result.outputs:
        out["support"] = result.support
    return out


def solve_frame(held: Held, frame: FrameIn, kind: str, timing: dict, *, t_received: float,
                t_submitted: float, support=None, extra: dict | None = None) -> bytes:
    """One frame in the pool: solve, build the reply, encode it (timing filled in)."""
    timing["queue"] = _ms(t_submitted)
    support = frame.support if support is None else support
    t0 = time.perf_counter()
    try:
        result = held.session.frame(frame.points, support, frame.frame_id)
    except ValueError as exc:
        log.info("frame refused by the engine: %s", exc)
        field = "support" if support is not None and "support" in str(exc) else "points"
        raise unprocessable(str(exc), field) from None
    payload = frame_payload(result)
    if extra:
        payload.update(extra)
    timing.update(result.timing_ms)
    timing["solve"] = _ms(t0)  # the engine call as the server sees it (its own total inside)
    timing["server"] = _ms(t_received)
    body = codec.encode_timed(payload, kind, timing)
    held.watch.publish(frame.points, payload, timing)  # never blocks: see watch.py
    return body


async def http_frame(held: Held, frame: FrameIn, kind: str, *, decode_ms: float, t_received: float,
                     registry: SessionRegistry, pool: SolvePool) -> bytes:
    """A frame posted over HTTP: frames of one session run one at a time, in arrival order."""
    async with held.lock:  # asyncio.Lock wakes waiters first come, first served
        registry.begin(held)
        try:
            return await pool.run(solve_frame, held, frame, kind, {"decode": decode_ms},
                                  t_received=t_received, t_submitted=time.perf_counter())
        finally:
            registry.end(held)


# -- models --------------------------------------------------------------------------------------


def simulate(entry, body: SimulateIn, kind: str, timing: dict, t_received: float) -> bytes:
    """The forward problem in the pool: displacement under the body's forces."""
    nodes, values = body.forces.nodes, body.forces.values
    t0 = time.perf_counter()
    try:
        if body.method == "network":
            model = entry.network if body.E is None else entry.network.with_stiffness(body.E)
            u = model.predict(values[None], nodes)[0]
            result = {"converged": True, "status": "converged", "iterations": 0, "residual": None}
        else:
            model = entry.fem if body.E is None else entry.fem.with_stiffness(body.E)
            res = model.solve(values, nodes)
            u = res.u
            result = {"converged": bool(res.converged), "status": res.status,
                      "iterations": int(res.iterations), "residual": float(res.residual)}
    except ValueError as exc:
        raise unprocessable(str(exc), "forces") from None
    timing["solve"] = _ms(t0)
    timing["server"] = _ms(t_received)
    payload = {"displacement": u, "net_force": values.sum(axis=0), "method": body.method, **result}
    return codec.encode_timed(payload, kind, timing)


def mesh_payload(entry) -> dict:
    mesh = entry.mesh
    return {
        "nodes": mesh.nodes,
        "tets": mesh.tets,
        "surface_faces": mesh.surface_faces,
        "surface_nodes": mesh.surface_nodes,
        "fixed_nodes": mesh.fixed,
        "region_nodes": entry.region,
    }


def summary(entry) -> dict:
    return entry.summary()


def not_found_model(model: str, models: dict) -> ApiError:
    known = ", ".join(sorted(models)) or "none"
    return ApiError(404, f"no model {model!r} in this server's store (models: {known})")


def encode(obj, kind: str) -> bytes:
    return codec.encode(obj, kind)
