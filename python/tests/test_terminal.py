"""What the terminal shows: colour only on a terminal (not TERM=dumb) and without NO_COLOR
(no-color.org: set and not empty), progress only on a terminal and once work has run for a second,
and an error or a warning on a line of its own after a bar left part-drawn."""

import io
import sys

import pytest

from trackcal import cli


class Tty(io.StringIO):
    def isatty(self):
        return True


class Clock:
    """time.monotonic as the cli module sees it, moved by hand."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(cli.time, "monotonic", c)
    return c


@pytest.mark.parametrize("value,coloured", [(None, True), ("1", False), ("", True)])
def test_terminal_colour_follows_no_color(monkeypatch, value, coloured):
    if value is None:
        monkeypatch.delenv("NO_COLOR", raising=False)
    else:
        monkeypatch.setenv("NO_COLOR", value)
    term = cli.Terminal(out=Tty(), err=Tty())
    assert (term.c("x", "31") != "x") == coloured
    assert (term.ce("x", "31") != "x") == coloured
    # Not on a pipe, whatever NO_COLOR says.
    piped = cli.Terminal(out=io.StringIO(), err=io.StringIO())
    assert piped.c("x", "31") == "x" and piped.ce("x", "31") == "x"


@pytest.mark.parametrize("term_value,coloured",
                         [("dumb", False), ("xterm-256color", True), (None, True)])
def test_terminal_colour_off_on_a_dumb_terminal(monkeypatch, term_value, coloured):
    """TERM=dumb (Emacs' shell, some CI consoles) shows escape codes as text: no colour there."""
    monkeypatch.delenv("NO_COLOR", raising=False)
    if term_value is None:
        monkeypatch.delenv("TERM", raising=False)
    else:
        monkeypatch.setenv("TERM", term_value)
    term = cli.Terminal(out=Tty(), err=Tty())
    assert (term.c("x", "31") != "x") == coloured
    assert (term.ce("x", "31") != "x") == coloured


@pytest.mark.parametrize("kind", ["bar", "message"])
def test_progress_only_on_a_terminal_after_a_second(clock, kind):
    for err, shown in ((Tty(), True), (io.StringIO(), False)):
        term = cli.Terminal(out=io.StringIO(), err=err)
        if kind == "bar":
            bar = term.progress("figures")
            update = lambda: bar(1, 4)  # noqa: E731
        else:
            message = term.message_progress()
            update = lambda: message("fitting +dipole")  # noqa: E731
        clock.now += 0.5
        update()
        assert err.getvalue() == ""  # work of half a second: no bar
        clock.now += 0.6
        update()
        assert (err.getvalue() != "") == shown, err.getvalue()


def test_an_error_after_a_part_drawn_bar_starts_a_line_of_its_own(clock, monkeypatch, tmp_path):
    # A bar left at 25 % (a fit that failed, a figure refused) and the error printed on after it:
    # "figures [#######                       ]  25.0%error: ..." on the terminal.
    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setattr(sys, "stdout", io.StringIO())

    def failing(args, term):
        bar = term.progress("figures")
        clock.now += 2.0
        bar(1, 4)
        raise ValueError("report.html: exists")
    monkeypatch.setitem(cli.COMMANDS, "history", failing)
    (tmp_path / "work").mkdir()
    assert cli.main(["history", str(tmp_path / "work")]) == 2
    text = err.getvalue()
    assert "25.0%" in text
    last = text.rsplit("\r", 1)[-1]
    assert last.replace("\033[K", "").startswith("\033[31merror: \033[0mreport.html: exists"), repr(text)


def test_a_dumb_terminal_gets_no_escape_code_from_progress_either(clock, monkeypatch, tmp_path):
    """TERM=dumb prints escape codes as text, which is why it gets no colour; the progress
    messages and the clearing of a part-drawn line before an error wrote the erase-line code
    "\\033[K" there all the same. They clear with blanks instead, as wide as what was drawn."""
    monkeypatch.delenv("NO_COLOR", raising=False)
    monkeypatch.setenv("TERM", "dumb")
    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setattr(sys, "stdout", io.StringIO())

    def failing(args, term):
        message = term.message_progress()
        clock.now += 2.0
        message("fitting +dipole, +plane (candidate 3 of 9)")
        message("fitting +dipole")
        raise ValueError("model.yaml:3: field type: unknown")
    monkeypatch.setitem(cli.COMMANDS, "history", failing)
    (tmp_path / "work").mkdir()
    assert cli.main(["history", str(tmp_path / "work")]) == 2
    text = err.getvalue()
    assert "\033" not in text, repr(text)
    # What was drawn is blanked before the next text: nothing of the longer message is left.
    first = "fitting +dipole, +plane (candidate 3 of 9)"
    blank = " " * len(first)
    assert text.split("\r") == ["", first, blank, "fitting +dipole", blank,
                                "error: model.yaml:3: field type: unknown\n"], repr(text)
    # A terminal that knows the code still gets it (one write, no blanks).
    monkeypatch.setenv("TERM", "xterm-256color")
    term = cli.Terminal(out=io.StringIO(), err=Tty())
    message = term.message_progress()
    clock.now += 2.0
    message("fitting +dipole")
    term.end_progress()
    assert term.err.getvalue() == "\r\033[Kfitting +dipole\r\033[K"
