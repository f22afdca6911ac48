"""The status STRING: any error fits one, its detail cut (whole characters) where it is longer
than a STRING can carry."""

from __future__ import annotations

import json

import pytest

from service.igtl import protocol as p
from service.igtl.answers import error_body, status_message


def _status(message: bytes) -> dict:
    version, mtype, device, ts, size, crc = p.parse_header(message[: p.HEADER_SIZE])
    msg = p.parse_body(version, mtype, device, ts, message[p.HEADER_SIZE :], crc)
    assert (msg.type, msg.device) == ("STRING", "status")
    return json.loads(p.decode_string(msg.content))


@pytest.mark.parametrize("unit", ["a", "é", '"', "\u2603", "\U0001f600"])  # 1 to 12 bytes in JSON
def test_a_detail_longer_than_a_string_is_cut_to_fit(unit):
    detail = "names " + unit * 70_000
    got = _status(status_message({"frame_id": 3, "error": error_body(400, detail)}, 2))
    assert got["frame_id"] == 3 and got["error"]["code"] == 400
    cut = got["error"]["detail"]
    assert cut.endswith("…") and detail.startswith(cut[:-1]) and len(cut) > 1000


def test_a_detail_that_fits_is_sent_whole():
    detail = "é" * 10_000  # 60 kB of JSON: under a STRING's 65535 bytes
    assert _status(status_message({"error": error_body(422, detail)}, 1))["error"]["detail"] == detail
