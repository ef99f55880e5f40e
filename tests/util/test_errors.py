"""BadInput's one line and `one_line`, which keeps a user's text from breaking or forging a line."""

from __future__ import annotations

import pytest

from riskplan.util.errors import BadInput, one_line


@pytest.mark.parametrize(
    ("text", "shown"),
    [
        ("x\n[2/2] failed FAKE", "x\\n[2/2] failed FAKE"),  # a forged progress line stays on its own line
        ("a\rb", "a\\rb"),
        ("\x1b[31mred", "\\x1b[31mred"),  # an escape code is shown, not obeyed
        ("tab\there", "tab\\there"),
        ("a\u202eb", "a\\u202eb"),  # right-to-left override: would reverse what follows on the terminal
        ("Quelle ☢ 源 β=0.1", "Quelle ☢ 源 β=0.1"),  # printable text of any script is left as it is
    ],
)
def test_one_line_shows_what_does_not_print_escaped(text, shown):
    assert one_line(text) == shown
    assert one_line(shown) == shown  # what it made prints as it is


def test_bad_input_is_one_line_whatever_the_key_and_value_hold():
    err = BadInput("world.sources.0.name", "got 'a\nb\x1b[2J'; give a name")
    assert str(err) == "world.sources.0.name: got 'a\\nb\\x1b[2J'; give a name"
    assert err.where == "world.sources.0.name" and isinstance(err, ValueError)
