"""The client's errors: :class:`ApiError` (a refused request) and :class:`StreamError` (a
stream's or a watch's error message, or its socket closed), and how a reply's words become one."""

from __future__ import annotations

from typing import Any


class ApiError(RuntimeError):
    """The server refused a request: ``status`` (HTTP code, or the stream error's code),
    ``detail`` (its explanation) and, on a 503 (saturated, at the session limit, shutting down),
    ``retry_after`` (seconds to wait before trying again: an HTTP reply's Retry-After, a stream
    error's ``retry_after``; None where the server gave none)."""

    def __init__(self, status: int, detail: Any, instance: str | None = None, retry_after: float | None = None) -> None:
        super().__init__(f"{status}: {detail}")
        self.status = status
        self.detail = detail
        self.instance = instance
        self.retry_after = retry_after


def retry_after(value: str | None) -> float | None:
    """Retry-After in seconds: the server sends delta-seconds; an HTTP date (another proxy's) or
    a bad value gives None rather than a second error."""
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None


def redirected(location: str | None) -> str:
    """The detail of a 3xx: the API never redirects, so a proxy in front of it does (http to
    https, a moved host); the client follows none, as a redirected POST may lose its body."""
    if location is None:
        return "redirected with no Location: not an elastreg reply (the API itself never redirects)"
    return f"redirected to {location}: give the client that URL (the API itself never redirects)"


#: how much of another server's error page an ApiError's detail keeps
PAGE_START = 200


def foreign_page(media: str, url, text: str) -> str:
    """The detail of an error reply whose body is no API reply (a proxy's 502 page, a wrong
    port's 404): what it is, from where, and its first PAGE_START characters, not a whole page
    of HTML in every log line that prints the error."""
    text = " ".join(text.split())
    more = " ..." if len(text) > PAGE_START else ""
    return f"not an elastreg reply ({media or 'no content-type'}) from {url}: {text[:PAGE_START]}{more}"


class StreamError(ApiError):
    """A stream's or a watch's error: an error message (``close_code`` None: the stream stays
    open), or a socket the server closed (``close_code`` set, and ``reason`` its words: a
    refused first message, 1008; an idle stream past ``session_ttl_s`` or a watched session
    that ended, 1000; a message over the size limit, 1009; a connection lost without a close
    frame, 1006). A closed socket's ``status`` is 0 and its ``__cause__`` websockets' own
    ``ConnectionClosed``; a new stream is needed."""

    def __init__(
        self,
        status: int,
        detail: Any,
        frame_id=None,
        close_code: int | None = None,
        retry_after: float | None = None,
        reason: str = "",
    ) -> None:
        super().__init__(status, detail, retry_after=retry_after)
        if status == 0 and close_code is not None:  # a close, not an error message: no status to show
            self.args = (f"closed {close_code}: {detail}",)
        self.frame_id = frame_id
        self.close_code = close_code
        self.reason = reason


def stream_error(e, close_code: int | None = None) -> StreamError:
    """The StreamError of a stream's ``{"error": {...}}`` message."""
    if not isinstance(e, dict):
        return StreamError(0, e, close_code=close_code)
    retry = e.get("retry_after")
    retry = float(retry) if isinstance(retry, (int, float)) and not isinstance(retry, bool) else None
    return StreamError(int(e.get("code", 0)), e.get("detail"), e.get("frame_id"), close_code, retry)
