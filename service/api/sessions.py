"""The sessions a server process holds: bounded in number, expired when idle, thread-safe.

A session lives in the process that opened it. Its id starts with that process's instance id
and, after it, the start that made it (``a3f09c-5be21d.Xq2...``: instance, boot nonce, random
part), so a request that reaches another process (several uvicorn workers, or replicas behind a
load balancer without affinity) gets a 404 that says so instead of a wrong answer, one for a
session of an earlier start of this instance (a fixed ELASTREG_INSTANCE_ID) says it restarted,
and a load balancer can route on the instance prefix.

HTTP sessions expire after ``ttl_s`` seconds without a request (a background sweeper drops
them; a session busy with a frame is never dropped). A WebSocket stream's session belongs to
its connection: it counts against the limit but is never swept; the stream closes it.

A session belongs to the token that opened it (``owner``, a fingerprint of the token; None on a
server without tokens): asked for by any other owner it is not found (404), exactly as if it did
not exist. One owner holds at most ``max_per_owner`` slots, so a single token cannot take them
all and lock the others out until its sessions expire. A session closed while a frame of it is
still being solved keeps its slot (its owner's too) until that solve ends, so the limits count
every session that holds a thread.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import secrets
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from .watch import Channel

if TYPE_CHECKING:
    from ..registration.session import Session

_FORGET = 4096  # closed / expired ids remembered for a precise 404
ANY = object()  # an owner that matches every session (the server's own housekeeping)
BOOT_SEP = "."  # ends a session id's boot nonce (neither an instance id's first "-" nor token_urlsafe has one)


class RegistryFull(RuntimeError):
    """The process holds its maximum number of sessions (HTTP 503; retry after ``retry_after`` s)."""

    def __init__(self, message: str, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class SessionNotFound(KeyError):
    """No such session here; ``str()`` explains why, session affinity included (HTTP 404)."""

    def __str__(self) -> str:
        return str(self.args[0])


class WrongKind(RuntimeError):
    """A stream's session addressed over HTTP (HTTP 409)."""


@dataclasses.dataclass(eq=False)
class Held:
    """A session as the API holds it: the engine's Session and what the API adds."""

    id: str
    kind: str  # "http" | "stream"
    model: str
    session: Session
    config: dict[str, Any]  # the effective config, as echoed when it opened
    created: float = dataclasses.field(default_factory=time.time)
    touched: float = dataclasses.field(default_factory=time.monotonic)
    owner: str | None = None  # the fingerprint of the token that opened it
    busy: int = 0  # frames in flight (never swept while > 0)
    waiting: int = 0  # HTTP frames waiting for the lock
    closed: bool = False  # closed or expired: its waiting frames are dropped
    lock: asyncio.Lock = dataclasses.field(default_factory=asyncio.Lock)  # HTTP frames, FIFO
    watch: Channel = dataclasses.field(default_factory=Channel)  # WS /sessions/{id}/watch

    @property
    def skip_stale(self) -> bool:
        return bool(self.config.get("skip_stale", False))


@dataclasses.dataclass(eq=False)
class Reservation:
    id: str
    kind: str
    owner: str | None = None
    done: bool = False


class SessionRegistry:
    """Held sessions by id. Every method is thread-safe."""

    def __init__(
        self,
        *,
        max_sessions: int,
        ttl_s: float,
        instance_id: str,
        retry_after: int,
        max_per_owner: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_sessions = max_sessions
        self.max_per_owner = max_sessions if max_per_owner is None else max_per_owner
        self.retry_after = retry_after  # seconds, for the 503 at the limit
        self.ttl_s = ttl_s
        self.instance_id = instance_id
        self.boot = secrets.token_hex(3)  # this start's, in every id it makes: a restart's 404 can say so
        self.clock = clock
        self._held: dict[str, Held] = {}
        self._pending = 0
        self._draining = 0  # closed sessions whose frame is still being solved
        self._owned: collections.Counter[str | None] = collections.Counter()  # slots by owner, all three kinds
        self._gone: collections.OrderedDict[str, tuple[object, str]] = collections.OrderedDict()  # id: owner, why
        self._lock = threading.Lock()

    # -- opening -----------------------------------------------------------------------------------

    def reserve(self, kind: str, owner: str | None = None) -> Reservation:
        """A slot and an id for a session `owner` is about to build; RegistryFull at the limit
        of the process or of the owner."""
        with self._lock:
            if len(self._held) + self._pending + self._draining >= self.max_sessions:
                raise RegistryFull(
                    f"this server process holds its maximum of {self.max_sessions} sessions; "
                    f"close one (DELETE /sessions/{{id}}) or retry in {self.retry_after} s",
                    self.retry_after,
                )
            if self._owned[owner] >= self.max_per_owner:
                raise RegistryFull(
                    f"this token holds its maximum of {self.max_per_owner} sessions on this server process "
                    f"(max_sessions_per_token); close one (DELETE /sessions/{{id}}) or retry in {self.retry_after} s",
                    self.retry_after,
                )
            self._pending += 1
            self._owned[owner] += 1
            return Reservation(f"{self.instance_id}-{self.boot}{BOOT_SEP}{secrets.token_urlsafe(9)}", kind, owner)

    def commit(self, reservation: Reservation, held: Held) -> Held:
        """The built session in its reserved slot, owned by the reservation's owner."""
        with self._lock:
            if not reservation.done:
                reservation.done = True
                self._pending -= 1
            held.owner = reservation.owner
            held.touched = self.clock()
            self._held[held.id] = held
        return held

    def cancel(self, reservation: Reservation) -> None:
        with self._lock:
            if not reservation.done:
                reservation.done = True
                self._pending -= 1
                self._release(reservation.owner)

    def _release(self, owner: str | None) -> None:
        """One of `owner`'s slots is free (under the lock)."""
        self._owned[owner] -= 1
        if self._owned[owner] <= 0:
            del self._owned[owner]

    # -- use ---------------------------------------------------------------------------------------

    def _find(self, session_id: str, kind: str | None, instead: str, owner) -> Held:
        """The held session (under the lock); `instead` tells a caller of the wrong kind what to do."""
        held = self._held.get(session_id)
        if held is None or (owner is not ANY and held.owner != owner):
            raise SessionNotFound(self._not_found(session_id, owner))
        if kind is not None and held.kind != kind:
            raise WrongKind(f"session {session_id!r} belongs to a WebSocket stream: {instead}")
        return held

    def get(self, session_id: str, *, kind: str | None = None, touch: bool = True, owner=ANY) -> Held:
        with self._lock:
            held = self._find(session_id, kind, "send its frames on that socket, and close the socket to end it", owner)
            if touch:
                held.touched = self.clock()
            return held

    def begin(self, held: Held) -> None:
        """A frame starts: the session is busy (never swept) until :meth:`end`."""
        with self._lock:
            if held.closed:
                raise SessionNotFound(self._not_found(held.id))
            held.busy += 1
            held.touched = self.clock()

    def end(self, held: Held) -> None:
        """A frame is over (from any thread): a closed session's slot is free once idle."""
        with self._lock:
            held.busy -= 1
            held.touched = self.clock()
            if held.closed and held.busy == 0:
                self._draining -= 1
                self._release(held.owner)

    def close(self, session_id: str, *, kind: str | None = None, why: str = "closed", owner=ANY) -> Held:
        with self._lock:
            held = self._find(session_id, kind, "close the socket to end it", owner)
            del self._held[session_id]
            held.closed = True
            if held.busy:
                self._draining += 1
            else:
                self._release(held.owner)
            self._forget(session_id, held.owner, why)
            return held

    def expire(self, now: float | None = None) -> list[str]:
        """Drop idle HTTP sessions (idle longer than ttl_s, no frame in flight); their ids."""
        now = self.clock() if now is None else now
        with self._lock:
            gone = [
                sid
                for sid, h in self._held.items()
                if h.kind == "http" and h.busy == 0 and now - h.touched > self.ttl_s
            ]
            for sid in gone:
                held = self._held.pop(sid)
                held.closed = True
                self._release(held.owner)
                self._forget(sid, held.owner, f"expired after {self.ttl_s:g} s without a request")
        return gone

    def expires_in(self, held: Held) -> float | None:
        if held.kind != "http":
            return None
        return max(0.0, self.ttl_s - (self.clock() - held.touched))

    def idle(self, held: Held) -> float:
        return 0.0 if held.busy else self.clock() - held.touched

    def counts(self) -> dict[str, int]:
        with self._lock:
            http = sum(h.kind == "http" for h in self._held.values())
            return {"open": len(self._held), "http": http, "stream": len(self._held) - http}

    @property
    def closing(self) -> int:
        """Closed sessions whose last frame is still being solved (they hold their slot)."""
        return self._draining

    def __len__(self) -> int:
        with self._lock:
            return len(self._held)

    # -- 404s that explain themselves ----------------------------------------------------------------

    def _forget(self, session_id: str, owner, why: str) -> None:
        self._gone[session_id] = (owner, why)
        while len(self._gone) > _FORGET:
            self._gone.popitem(last=False)

    def _not_found(self, session_id: str, owner=ANY) -> str:
        """Why there is no such session; what became of it only for its own token (another's
        gets the answer for an id that never existed: deployment.md)."""
        here = f"this server process is instance {self.instance_id!r}"
        gone = self._gone.get(session_id)
        if gone is not None and (owner is ANY or gone[0] == owner):
            return f"session {session_id!r} {gone[1]} ({here})"
        owner, dash, rest = session_id.partition("-")
        boot = rest.partition(BOOT_SEP)[0] if BOOT_SEP in rest else None  # None: an id without one
        if owner == self.instance_id and boot and boot != self.boot:
            return (
                f"session {session_id!r} is not held here: it was opened by an earlier start of this server "
                f"(instance {owner!r}, start {boot!r}; {here}, start {self.boot!r}): this server restarted "
                "since (sessions do not survive a restart: open a new one), or another process runs with the "
                "same ELASTREG_INSTANCE_ID (give each process its own)"
            )
        if dash and owner and owner != self.instance_id:  # a restart and a mis-route look the same from here
            return (
                f"session {session_id!r} is not held here: it was opened by another server process "
                f"(instance {owner!r}; {here}): this server restarted (sessions do not survive a restart: "
                "open a new one) or requests are routed to more than one process (route every request of a "
                'session to the process that opened it, session affinity: docs/usage.md, "Scaling out"; or '
                "use the WebSocket /stream, whose state lives with its connection)"
            )
        return (
            f"no session {session_id!r} ({here}): it was closed, expired after {self.ttl_s:g} s "
            "idle, or never existed. Sessions live in the process that opened them (session "
            'affinity: docs/usage.md, "Scaling out")'
        )
