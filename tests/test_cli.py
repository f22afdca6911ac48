"""The command line refuses impossible values at parse time, with the value named and exit
status 2, before any server starts or store loads."""

from __future__ import annotations

import pytest

from service.cli import parser


@pytest.mark.parametrize(
    "argv, words",
    [
        (["serve", "--port", "70000"], "whole number in 1..65535"),  # it bound 70000 - 65536 = 4464
        (["serve", "--port", "-1"], "whole number in 1..65535"),
        (["serve", "--workers", "0"], "whole number >= 1"),
        (["serve", "--workers", "-3"], "whole number >= 1"),
        (["igtl", "--model", "phantom", "--port", "0"], "whole number in 1..65535"),
        (["demo", "--frames", "0"], "whole number >= 2"),
        (["demo", "--viewer", "--port", "99999"], "whole number in 1..65535"),
    ],
)
def test_impossible_values_are_refused_at_parse_time(argv, words, capsys):
    with pytest.raises(SystemExit) as exit_:
        parser().parse_args(argv)
    assert exit_.value.code == 2 and words in capsys.readouterr().err


def test_good_values_parse():
    args = parser().parse_args(["serve", "--port", "8080", "--workers", "2"])
    assert (args.port, args.workers) == (8080, 2)
    assert parser().parse_args(["demo", "--frames", "2"]).frames == 2
