"""argparse types for the command lines (``elastreg`` and its bench, the load test): an
impossible value is refused at parse time, one line naming the flag, exit status 2."""

from __future__ import annotations

import argparse
import math
import urllib.parse


def whole_number(minimum: int, maximum: int | None = None):
    """An argparse type for whole numbers in minimum..maximum: refused at parse time, not after
    an hour of data generation (or, for a port, not wrapped round: 70000 listened on 4464)."""
    wanted = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"must be a whole number {wanted}, got {text!r}")
        return value

    return parse


def _number(text: str) -> float:
    """The float a flag's text spells, or NaN (which every range refuses) where it spells none."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def positive_number(maximum: float | None = None, unit: str = ""):
    """An argparse type for positive finite numbers, at most `maximum` (`unit` names what it is)."""

    def parse(text: str) -> float:
        value = _number(text)
        if not (value > 0 and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"must be at most {maximum:g}{unit}, got {text!r}")
        return value

    return parse


def model_id(text: str) -> str:
    """An argparse type for a model id, the store's rule for an entry's folder (scene.MODEL_ID):
    no path separator, ".." or empty name reaches a path into the store."""
    from .scene.model_id import check_model_id  # here: the scene package brings pydantic and numpy

    try:
        return check_model_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


#: a positive finite number (a time budget: nan, inf, 0 are none)
positive = positive_number()


def non_negative_number(maximum: float, unit: str = ""):
    """An argparse type for finite numbers in 0..`maximum` (`unit` names what it is)."""

    def parse(text: str) -> float:
        value = _number(text)
        if not 0 <= value <= maximum:  # NaN too
            raise argparse.ArgumentTypeError(f"must be a number in 0..{maximum:g}{unit}, got {text!r}")
        return value

    return parse


#: the longest build budget, in minutes: a year, far past any build and far from 60 * minutes
#: overflowing a float (past 3e306 the deadline was inf and the build a traceback)
MAX_MINUTES = 365 * 24 * 60

#: a build's --minutes (train) or --build-minutes (bench)
build_minutes = positive_number(MAX_MINUTES, " (a year)")


#: the protocols of a Dask scheduler's address that name a host and a port (a bare HOST:PORT is tcp);
#: not inproc, whose scheduler lives inside one process that a command can never join
DASK_HOST_PROTOCOLS = ("tcp", "tls", "ws", "wss", "ucx")


def scheduler_address(text: str) -> str:
    """An argparse type for a Dask scheduler's address, [PROTOCOL://]HOST:PORT: one that is no
    address at all ('garbage', 'http://...', '') failed at once yet said that no scheduler
    answered there within 30 s, and port 99999 waited the 30 s."""
    protocol, sep, rest = text.rpartition("://") if "://" in text else ("tcp", "", text)
    if protocol == "inproc":
        raise argparse.ArgumentTypeError(
            f"{text!r} is an in-process address, reachable only from the process that holds its scheduler: "
            "give the scheduler's [tcp://]HOST:PORT"
        )
    if protocol not in DASK_HOST_PROTOCOLS:
        raise argparse.ArgumentTypeError(
            f"{protocol!r} is not a Dask protocol ({', '.join(DASK_HOST_PROTOCOLS)}), in {text!r}"
        )
    try:
        parts = urllib.parse.urlsplit(f"//{rest}")
        host, port = parts.hostname, parts.port  # port: a ValueError past 65535
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is no HOST:PORT address ({exc})") from None
    wrong = (
        "it has no host" if not host
        else "it has no port" if port is None
        else "port 0 is out of range 1..65535" if port == 0
        else "it holds more than HOST:PORT" if parts.path or parts.query or parts.fragment or "@" in parts.netloc
        else None
    )  # fmt: skip
    if wrong:
        raise argparse.ArgumentTypeError(f"{text!r} is no Dask scheduler address, [tcp://]HOST:PORT: {wrong}")
    return text
