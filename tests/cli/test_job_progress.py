"""``job run --follow``'s progress output: whole messages on a terminal and in files."""

from __future__ import annotations

import io

from cellctl.cli.job import Progress

LONG = "view 7/16: rejected (the plate is only partly in view: 31 of 49 marks found; " \
       "move the robot so the whole plate is seen)"


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_terminal_gets_whole_messages_and_a_bar_below() -> None:
    out = FakeTty()
    p = Progress(out)
    p.update(0.1, "view 1/16: ok")
    p.update(0.2, LONG)
    p.update(0.25, LONG)  # same message: only the bar moves
    p.line("succeeded: done")
    text = out.getvalue()
    assert LONG + "\n" in text and text.count(LONG) == 1
    assert "[######" in text and " 25.0%" in text
    assert text.endswith("succeeded: done\n")


def test_file_gets_plain_lines() -> None:
    out = io.StringIO()
    p = Progress(out)
    assert not p.tty
    p.update(0.5, LONG)
    p.line("failed: failed; the robot was stopped and nothing was stored")
    text = out.getvalue()
    assert "\r" not in text and "\033" not in text
    assert text.splitlines() == [f"[ 50.0%] {LONG}", "failed: failed; the robot was stopped and nothing was stored"]
