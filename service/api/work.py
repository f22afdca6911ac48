"""What the routes hand to the engine, run off the event loop by the solve pool (:mod:`.pool`).

Every function here that touches the engine is a plain ``def`` run by :class:`SolvePool` (a
fixed number of threads, ``solver_threads``): the event loop only reads sockets, decodes small
bodies and writes replies, so ``/health`` and other streams answer while a long FEM frame runs.
Server-wide caps apply before an engine sees a config (:func:`admit_config`: ``max_iter``,
``time_budget_ms``, ``E``), and a result with non-finite numbers is never reported converged.
A job returns the encoded reply (encoding a large field is work too). The engine's
``ValueError`` (a support node outside the network's region, a fixed node, ...) becomes a 422
carrying its message; anything else is a bug and surfaces as a 500 with its traceback logged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from ..forward import check_support
from ..material_range import E_RANGE
from ..registration.settings import NAMES
from . import codec
from .errors import ApiError, unprocessable
from .pool import Dropped, Overloaded, SolvePool
from .schemas.models import SimulateIn
from .schemas.sessions import FrameIn, SessionCreate
from .sessions import Held, Reservation, SessionRegistry

__all__ = ["SolvePool", "Overloaded", "Dropped"]  # the pool lives in .pool; routes import it from here

log = logging.getLogger(__name__)

#: the settings handed over as they are (support, matching and outputs change form on the way)
_FIELDS = tuple(n for n in NAMES if n not in ("support", "matching", "outputs"))


def _ms(t0: float) -> float:
    return 1e3 * (time.perf_counter() - t0)


# -- sessions ------------------------------------------------------------------------------------


def build_session(
    entry, create: SessionCreate, reservation: Reservation, budget_ms: float | None = None, max_iter: int | None = None
) -> Held:
    """The engine's Session for a validated config, wrapped for the registry (in the pool). A
    session without a time budget of its own runs under ``budget_ms`` (the server's cap, listed
    in /health's limits), and its echoed config says so (API.md: the effective value of every
    setting). One that did not set max_iter
    gets the default or the server's cap ``max_iter``, whichever is smaller."""
    # the engine: loaded by the app already
    from ..registration.session import Session, SessionConfig

    given = {k: getattr(create, k) for k in _FIELDS if getattr(create, k) is not None}
    if create.support is not None:
        given["support"] = tuple(create.support.tolist())
    if create.matching is not None:
        given["matching"] = tuple(map(tuple, create.matching.tolist()))
    given["outputs"] = tuple(create.outputs)
    if create.time_budget_ms is None and budget_ms is not None:
        given["time_budget_ms"] = budget_ms
    if max_iter is not None and (create.max_iter is None or "max_iter" not in create.model_fields_set):
        given["max_iter"] = min(SessionConfig.max_iter, max_iter)  # null is unsent: the default, capped
    model = entry.network if create.method == "auto" else entry.model(create.method)
    check_nodes(model, create)
    try:
        if create.method == "auto":
            session = Session(model, SessionConfig(**given), corrector=entry.fem)
        else:
            session = Session(model, SessionConfig(**given))
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


def check_nodes(model, create: SessionCreate) -> None:
    """A 422 whose ``loc`` names the field, for a support or matching the model cannot take: the
    engine's own ValueError does not say which field it found wrong (a frame's errors name it)."""
    from ..registration.inputs import check_faces

    try:
        if create.support is not None:
            check_model_support(model, create.support)
    except ValueError as exc:
        raise unprocessable(str(exc), "support") from None
    try:
        if create.matching is not None:
            check_faces(model.mesh, create.matching)
    except ValueError as exc:
        raise unprocessable(str(exc), "matching") from None


def config_of(held: Held) -> dict:
    """The session's effective config now (its current support included)."""
    return {
        "model": held.model,
        "method": held.config["method"],
        "support": held.session.support,
        **{k: v for k, v in held.config.items() if k not in ("model", "method")},
    }


def model_E(entry) -> float:
    return float(entry.manifest["material"]["E"])


def check_E(E: float | None, entry, settings) -> None:
    """A 422 for a Young's modulus further than ``e_range`` from the model's own (far outside
    it the scaled forces and alpha overflow: E = 1e-300 made alpha infinite), or outside the
    range the material law takes."""
    if E is None:
        return
    E0, k = model_E(entry), settings.e_range
    lo, hi = max(E0 / k, E_RANGE[0]), min(E0 * k, E_RANGE[1])
    if not lo <= E <= hi:
        raise unprocessable(
            f"E = {E:g} Pa is outside this server's range for model {entry.id!r}: within a factor of "
            f"{k:g} of its own {E0:g} Pa and within [{E_RANGE[0]:g}, {E_RANGE[1]:g}] Pa ({lo:g} to {hi:g})",
            "E",
            type_="less_than_equal",
        )


def admit_config(create: SessionCreate, entry, settings) -> None:
    """The server-wide caps: 422 for a max_iter or time_budget_ms over them, or an E out of
    range (a session without a time budget runs under the cap: :func:`build_session`)."""
    if "max_iter" in create.model_fields_set and create.max_iter is not None and create.max_iter > settings.max_iter:
        raise unprocessable(
            f"max_iter {create.max_iter} is over this server's cap of {settings.max_iter}",
            "max_iter",
            type_="less_than_equal",
        )
    if create.time_budget_ms is not None and create.time_budget_ms > settings.max_time_budget_ms:
        raise unprocessable(
            f"time_budget_ms {create.time_budget_ms:g} is over this server's cap of {settings.max_time_budget_ms:g}",
            "time_budget_ms",
            type_="less_than_equal",
        )
    check_E(create.E, entry, settings)


async def open_session(
    entry,
    create: SessionCreate,
    *,
    kind: str,
    registry: SessionRegistry,
    pool: SolvePool,
    settings,
    owner: str | None = None,
) -> Held:
    """Caps applied (422), a slot reserved (RegistryFull at the process's or the owner's limit),
    built, registered."""
    admit_config(create, entry, settings)
    reservation = registry.reserve(kind, owner)
    try:
        held = await pool.run(build_session, entry, create, reservation, settings.max_time_budget_ms, settings.max_iter)
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


def _finite(value) -> bool:
    if isinstance(value, np.ndarray):
        return value.dtype.kind != "f" or bool(np.isfinite(value).all())
    if isinstance(value, float):
        return math.isfinite(value)
    return True


def flag_non_finite(payload: dict) -> None:
    """A result holding NaN or infinity is not converged, whatever the solver said (API.md)."""
    bad = [k for k, v in payload.items() if not _finite(v)]
    if bad:
        log.warning("a frame produced non-finite %s (solver status %s)", ", ".join(bad), payload.get("status"))
        payload["converged"] = False
        payload["status"] = "non_finite"
        payload["message"] = f"non-finite values in {', '.join(bad)} (solver: {payload.get('message') or ''})"


def check_model_support(model, support) -> None:
    """The cheap checks a support must pass (ids, fixed nodes, a network's load region):
    ValueError saying why."""
    nodes = check_support(model.mesh, np.asarray(support))
    region_columns = getattr(model, "region_columns", None)
    if region_columns is not None:
        region_columns(nodes)


def check_frame_support(held: Held, support) -> None:
    """:func:`check_model_support` for a support a skipped frame carried."""
    check_model_support(held.session.model, support)


def solve_frame(
    held: Held,
    frame: FrameIn,
    kind: str,
    timing: dict,
    *,
    t_received: float,
    t_submitted: float,
    support=None,
    extra: dict | None = None,
) -> bytes:
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
    flag_non_finite(payload)
    if extra:
        payload.update(extra)
    timing.update(result.timing_ms)
    timing["solve"] = _ms(t0)  # the engine call as the server sees it (its own total inside)
    timing["server"] = _ms(t_received)
    body = codec.encode_timed(payload, kind, timing)
    held.watch.publish(frame.points, payload, timing)  # never blocks: see watch.py
    return body


async def http_frame(
    held: Held,
    frame: FrameIn,
    kind: str,
    *,
    decode_ms: float,
    t_received: float,
    registry: SessionRegistry,
    pool: SolvePool,
    session_queue: int,
    gone: Callable[[], bool] = lambda: False,
) -> bytes:
    """A frame posted over HTTP: frames of one session run one at a time, in arrival order;
    at most ``session_queue`` wait behind the running one (503 beyond). A frame whose session
    closed, or whose client left (``gone()``), while it waited is dropped, not solved."""
    if held.lock.locked() and held.waiting >= session_queue:
        raise Overloaded(
            f"session {held.id!r} already has {held.waiting} frame(s) waiting behind the one being solved",
            pool.retry_after,
        )
    held.waiting += 1
    try:
        await held.lock.acquire()  # asyncio.Lock wakes waiters first come, first served
    finally:
        held.waiting -= 1
    try:
        registry.begin(held)  # SessionNotFound if it closed while this frame waited
        return await pool.run(
            solve_frame,
            held,
            frame,
            kind,
            {"decode": decode_ms},
            t_received=t_received,
            t_submitted=time.perf_counter(),
            cancelled=lambda: held.closed or gone(),
            done=lambda: registry.end(held),
        )
    finally:
        held.lock.release()


# -- models --------------------------------------------------------------------------------------


def simulate(entry, body: SimulateIn, kind: str, timing: dict, t_received: float, budget_ms: float) -> bytes:
    """The forward problem in the pool: displacement under the body's forces, the FEM's solve
    within the server's time cap (`budget_ms`, as a frame's)."""
    nodes, values = body.forces.nodes, body.forces.values
    t0 = time.perf_counter()
    try:
        if body.method == "network":
            model = entry.network if body.E is None else entry.network.with_stiffness(body.E)
            u = model.predict(values[None], nodes)[0]
            result = judge_network(entry.network, u, values * model.stiffness_factor, nodes)
        else:
            model = entry.fem if body.E is None else entry.fem.with_stiffness(body.E)
            res = model.solve(values, nodes, deadline=t0 + budget_ms / 1e3)
            u = res.u
            result = {
                "converged": bool(res.converged),
                "status": res.status,
                "iterations": int(res.iterations),
                "residual": res.residual,  # the returned field's, under the body's forces
            }
    except ValueError as exc:
        raise unprocessable(str(exc), "forces") from None
    if not np.isfinite(u).all():  # never a converged field of NaN (E far from the model's did it)
        result.update(converged=False, status="non_finite")
    timing["solve"] = _ms(t0)
    timing["server"] = _ms(t_received)
    payload = {"displacement": u, "net_force": values.sum(axis=0), "method": body.method, **result}
    return codec.encode_timed(payload, kind, timing)


def judge_network(network, u, scaled, nodes) -> dict:
    """A network's answer judged as a frame's is (docs/usage.md): its error estimate, from the
    Neo-Hookean residual (confidence.py), and not converged where that is infinite (the field
    is not finite or inverts elements: ``non_finite``) or where the load is larger than any the
    network was trained on (``beyond_training``). `scaled`: the forces at the network's own E
    (E0 / E of the body's), where the estimate is the same and its factorisation already made."""
    from ..registration.confidence import beyond_training, estimator_for

    estimate = estimator_for(network).forward_error(u, scaled, nodes) if np.isfinite(u).all() else math.inf
    result = {"converged": True, "status": "converged", "iterations": 0, "residual": None, "error_estimate": estimate}
    if not math.isfinite(estimate):
        result.update(converged=False, status="non_finite", error_estimate=None)
    elif beyond_training(scaled, network.max_force):
        result.update(converged=False, status="beyond_training")
    return result


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
