"""The bridge's side toward the API: the model's surface and the API's limits read at start, a
``/stream`` session per client, and each frame relayed over it and answered (the registered
surface and a status, or the API's error), a stream the API closed on purpose reopened once."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable

import numpy as np

from . import protocol as p
from .answers import SURFACE, error_body, status_message
from .connection import Connection

log = logging.getLogger(__name__)

#: close codes of a stream the API ended on purpose (idle past session_ttl_s, going away,
#: restarting): the frame was not taken, so it is sent again over a new session
_CLEAN_CLOSE = (1000, 1001, 1012)


class Surface:
    """The model's boundary: surface node ids and triangles renumbered onto them."""

    def __init__(self, mesh: dict) -> None:
        self.nodes = np.asarray(mesh["nodes"], np.float64)
        self.surface_nodes = np.asarray(mesh["surface_nodes"], np.int64)
        where = np.full(len(self.nodes), -1, np.int64)
        where[self.surface_nodes] = np.arange(self.surface_nodes.size)
        self.triangles = where[np.asarray(mesh["surface_faces"], np.int64)]
        if (self.triangles < 0).any():
            raise ValueError("the model's surface faces use nodes outside its surface nodes")

    def same(self, other: Surface) -> bool:
        return (
            self.nodes.shape == other.nodes.shape
            and np.array_equal(self.nodes, other.nodes)
            and np.array_equal(self.surface_nodes, other.surface_nodes)
            and np.array_equal(self.triangles, other.triangles)
        )

    def positions(self, result: dict) -> np.ndarray:
        """(s, 3) registered positions of the surface nodes."""
        if "surface_displacement" in result:
            u = np.asarray(result["surface_displacement"], np.float64)
        else:
            u = np.asarray(result["displacement"], np.float64)[self.surface_nodes]
        return self.nodes[self.surface_nodes] + u


class BridgeError(RuntimeError):
    """The bridge cannot start (the API refuses the model or cannot be reached, the port is
    taken): its text is one line that says why; ``exit_status`` the command's."""

    exit_status = 1


class SettingsRefused(BridgeError):
    """The API refuses the session settings given on the command line (a --support id past the
    model's nodes or on a fixed node, an --alpha out of range): a wrong command line, status 2."""

    exit_status = 2


class ApiRefused(Exception):
    """The API refused a session, or could not be reached: `code` is the status to report."""

    def __init__(self, code: int, text: str, retry_after: float | None = None) -> None:
        super().__init__(text)
        self.code = code
        self.retry_after = retry_after


class Relay:
    """A client of the HTTP/WebSocket API (:class:`clients.AsyncClient`) for one model: what the
    bridge (:class:`~.bridge.Bridge`) hands each client's frames to."""

    def __init__(
        self,
        api_url: str,
        model: str,
        *,
        settings: dict | None = None,
        encoding: str = "msgpack",
        token: str | None = None,
    ) -> None:
        self.api_url = api_url
        self.model = model
        self.token = token  # for a server with tokens: a header on HTTP, the stream's first message
        self.settings = dict(settings or {})
        outputs = set(self.settings.get("outputs") or ["forces"])
        self.settings["outputs"] = sorted(outputs | {"surface_displacement"})
        self.encoding = encoding
        self.surface: Surface | None = None
        #: the API's limits (its /health), read at prepare(): max_points, max_message_bytes,
        #: body_timeout_s (also how long the rest of a message may take once its header began),
        #: max_time_budget_ms (how long a frame in flight may take: frame_cap)
        self.limits: dict = {}
        self.sessions: list[str] = []  # ids of the sessions opened so far (for logs and tests)
        self.announce: Callable[[str], None] = (
            log.info
        )  # what to do with a line a person should see (the CLI prints it)

    async def prepare(self) -> None:
        """Read the API's limits and the model's mesh, check the session settings and ready the
        message kernels; BridgeError (one line) when it cannot."""
        from clients.client import ApiError

        p.warm()
        async with self._api() as api:
            try:
                try:
                    self.limits = dict((await api.health()).get("limits") or {})
                except ApiError:  # a degraded server (503) still names its limits; the mesh says more
                    self.limits = {}
                self.surface = Surface(await api.mesh(self.model))
            except ApiError as exc:
                raise BridgeError(f"the API at {self.api_url} refused model {self.model!r}: {exc}") from None
            except (OSError, _http_error()) as exc:
                raise BridgeError(self._unreachable(exc)) from None
            await self._check_settings(api)

    async def _check_settings(self, api) -> None:
        """Open and close a session with this bridge's settings, so that the API's own checks (a
        support's ids against the model's nodes, its fixed nodes, a network's load region; every
        setting's range) refuse a wrong command line now, not at each client's connection:
        SettingsRefused on a 422. Any other refusal (at its session limit, say) is left for a
        client's connection to report."""
        from clients.client import ApiError

        try:  # over HTTP: a token goes as the header _api() sets
            probe = await api.open_session(self.model, **self.settings)
        except ApiError as exc:
            if exc.status == 422:
                raise SettingsRefused(
                    f"{_refused(exc.detail)} (the API at {self.api_url}, model {self.model!r})"
                ) from None
            log.warning("the session settings could not be checked at start: %s", exc)
            return
        except (OSError, _http_error()) as exc:
            raise BridgeError(self._unreachable(exc)) from None
        with contextlib.suppress(ApiError, OSError, _http_error()):
            await probe.close()

    @property
    def send_timeout(self) -> float:
        """Seconds an answer may wait for the client to take it (the API's send_timeout_s)."""
        return float(self.limits.get("send_timeout_s") or 30.0)

    @property
    def send_min_rate(self) -> float:
        """Bytes a second below which a client taking an answer is as good as stalled (the API's
        send_min_bytes_per_s; its default where an older API lists none)."""
        from ..config import Settings

        return float(self.limits.get("send_min_bytes_per_s") or Settings.model_fields["send_min_bytes_per_s"].default)

    @property
    def frame_cap(self) -> float:
        """Seconds the API may spend on one frame (its max_time_budget_ms; its default where an
        older API lists none): an answering API ends a frame in flight within about this long."""
        from ..config import Settings

        cap = self.limits.get("max_time_budget_ms") or Settings.model_fields["max_time_budget_ms"].default
        return float(cap) / 1e3

    @property
    def read_timeout(self) -> float:
        """Seconds the rest of a message may take once its first byte came (the API's body_timeout_s)."""
        return float(self.limits.get("body_timeout_s") or 30.0)

    def _unreachable(self, exc: BaseException) -> str:
        return f"the API at {self.api_url} cannot be reached ({type(exc).__name__}: {exc})"

    def _api(self):
        from clients import AsyncClient

        api = AsyncClient(self.api_url, encoding=self.encoding)
        if self.token:
            api.http.headers["Authorization"] = f"Bearer {self.token}"
        return api

    async def _open(self, api):
        """A stream for this client, and the model's mesh read again (the API may have restarted
        with the model rebuilt); ApiRefused (with the API's status, 503 if it is unreachable)."""
        from clients.client import ApiError

        extra = {"token": self.token} if self.token else {}
        try:
            stream = await api.stream(self.model, **self.settings, **extra)
        except ApiError as exc:
            raise ApiRefused(exc.status or 503, f"the API refused the session: {exc.detail}", exc.retry_after) from None
        except (OSError, TimeoutError, *_ws_errors()) as exc:
            raise ApiRefused(503, self._unreachable(exc)) from None
        try:
            surface = Surface(await api.mesh(self.model))
        except BaseException as exc:
            with contextlib.suppress(Exception):
                await stream.close()
            if isinstance(exc, ApiError):
                raise ApiRefused(exc.status or 503, f"the API refused the model's mesh: {exc.detail}") from None
            if isinstance(exc, (OSError, TimeoutError, _http_error())):
                raise ApiRefused(503, self._unreachable(exc)) from None
            raise
        if self.surface is not None and not self.surface.same(surface):
            log.warning(
                "model %r: its mesh changed (the API restarted with it rebuilt?); the new one is used", self.model
            )
        self.surface = surface
        self.sessions.append(stream.session)
        from clients.client import viewer_url

        self.announce(f"session {stream.session}: watch it at {viewer_url(self.api_url, stream.session)}")
        return stream

    def _too_large(self, points: np.ndarray) -> str | None:
        """Why the API would refuse this cloud for its size (413), or None: told here, so that
        the stream (and its session) lives on (a message over max_message_bytes closes it)."""
        n = len(points)
        max_points = self.limits.get("max_points")
        if max_points and n > max_points:
            return f"{n} points is over this server's limit of {max_points} per frame"  # the API's words
        max_bytes = self.limits.get("max_message_bytes")
        size = points.nbytes + 256  # a packed array and the frame's map around it
        if max_bytes and self.encoding == "msgpack" and size > max_bytes:
            return f"a frame of {n} points ({size} bytes) is over this server's limit of {max_bytes} bytes per message"
        return None

    async def _frame(self, api, client: Connection, frame: int, points: np.ndarray, version: int) -> None:
        """Register one frame and answer it. ``client.stream`` is the stream to use next (None
        when it was lost: the frame is answered with an error and the next opens a new session).
        A stream the API closed cleanly (idle past its session_ttl_s, restarting) before it
        answered is reopened and the frame sent once more: only a second failure is an error."""
        from clients.client import StreamError

        t0 = time.perf_counter()
        r = None
        for attempt in (0, 1):
            if client.stream is None:  # the API went away at an earlier frame, or closed the stream
                try:
                    client.stream = await self._open(api)
                except ApiRefused as exc:
                    log.warning("%s", exc)
                    await self._frame_error(client, frame, exc.code, str(exc), version, exc.retry_after)
                    return
            stream = client.stream
            lost: BaseException
            try:
                r = await stream.frame(points, frame_id=frame)
                break
            except StreamError as exc:
                if exc.close_code is None:  # the API's error message, or the stream out of step
                    await self._frame_error(client, frame, exc.status, str(exc.detail), version, exc.retry_after)
                    if exc.status != 0:  # an error message: the stream goes on
                        return
                    client.stream = None
                    await close_stream(stream)  # out of step (status 0) ends the stream
                    return
                lost = exc  # the API closed the stream (close_code)
            except (OSError, TimeoutError, *_ws_errors()) as exc:
                lost = exc
            client.stream = None
            await close_stream(stream)
            code = _clean_close(lost)
            if attempt == 0 and code is not None:
                reason = lost.reason if isinstance(lost, StreamError) else ""
                log.warning(
                    "frame %d: the API closed the stream (%d%s); a new session for it (the warm start is lost)",
                    frame,
                    code,
                    f" {reason}" if reason else "",
                )
                continue
            why = _lost(lost)
            log.warning("frame %d: the API stream was lost (%s)", frame, why)
            await self._frame_error(
                client, frame, 503, f"the API stream was lost ({why}); the next frame opens a new session", version
            )
            return
        stream = client.stream
        assert r is not None and stream is not None and self.surface is not None
        surface = self.surface.positions(r)
        status = {
            "frame_id": r.get("frame_id"),
            "converged": bool(r["converged"]),
            "status": r["status"],
            "net_force": np.asarray(r["net_force"], float).tolist(),
            "error_estimate": r.get("error_estimate"),
            "timing_ms": {**r.get("timing_ms", {}), "bridge": 1e3 * (time.perf_counter() - t0)},
            "session": stream.session,
        }
        await client.send(
            p.pack("POLYDATA", SURFACE, p.encode_polydata(surface, self.surface.triangles), version=version),
            status_message(status, version),
        )

    async def _frame_error(
        self, client: Connection, frame: int, code: int, detail: str, version: int, retry_after: float | None = None
    ) -> None:
        """A frame's answer when it has no result: its id and the error."""
        await client.send(status_message({"frame_id": frame, "error": error_body(code, detail, retry_after)}, version))


def _refused(detail) -> str:
    """A 422's detail as one line, each field named by its flag (``--support: ...``)."""
    if not isinstance(detail, list):
        return " ".join(str(detail).split())
    return "; ".join(f"{_flag(e.get('loc') or [])}: {' '.join(str(e.get('msg')).split())}" for e in detail)


def _flag(loc: list) -> str:
    fields = [str(x) for x in loc if x != "body"]
    return "--" + fields[0].replace("_", "-") if fields else "the session settings"


def _ws_errors() -> tuple[type[BaseException], ...]:
    from websockets.exceptions import WebSocketException

    return (WebSocketException,)


def _http_error() -> type[BaseException]:
    import httpx

    return httpx.TransportError


def _clean_close(exc: BaseException) -> int | None:
    """The close code of a stream the API closed on purpose (see _CLEAN_CLOSE), else None: the
    client raises a closed stream as its StreamError, with the server's ``close_code``."""
    from clients.client import StreamError

    if not isinstance(exc, StreamError) or exc.close_code not in _CLEAN_CLOSE:
        return None
    return exc.close_code


def _lost(exc: BaseException) -> str:
    """How a stream was lost, in a few words: the API's close code and reason, or the error."""
    from clients.client import StreamError

    if isinstance(exc, StreamError) and exc.close_code == 1006:  # no close frame came
        return "the connection to the API dropped, 1006"
    if isinstance(exc, StreamError) and exc.close_code is not None:
        return f"closed by the API, {exc.close_code}{f' {exc.reason}' if exc.reason else ''}"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


async def close_stream(stream) -> None:
    """Close an API stream; one already lost has nothing more to say."""
    with contextlib.suppress(Exception):
        await stream.close()
