"""The one progress helper: a tqdm bar on a terminal, plain lines otherwise, nothing quiet."""

from __future__ import annotations

import io
import re

from emlpack.progress import progress, write


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_off_a_terminal_a_plain_line_every_n_items_with_rate_and_time_left():
    out = io.StringIO()
    for _ in progress(range(25), desc="label", unit="conf", file=out):
        pass
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    # the default: about ten lines a run (every ceil(25/10) = 3 items), and one at the end
    assert [int(re.match(r"label: (\d+)/25", line).group(1)) for line in lines] == [
        3, 6, 9, 12, 15, 18, 21, 24, 25]
    assert re.fullmatch(r"label: 25/25 \(100%\) \S+ elapsed, \S+ left, .*conf/s", lines[-1])


def test_every_initial_and_postfix_of_a_resumed_run():
    out = io.StringIO()
    bar = progress(total=10, desc="md", unit="step", initial=4, every=2, file=out)
    for _ in range(6):
        bar.update(1)
        bar.set_postfix_str("T 300 K")  # a refresh is no extra line
    bar.close()
    lines = out.getvalue().splitlines()
    assert [line.split()[1] for line in lines] == ["6/10", "8/10", "10/10"]
    assert lines[-1].endswith(", T 300 K")


def test_quiet_writes_nothing_and_lines_false_writes_nothing_off_a_terminal():
    for kwargs in ({"enabled": False}, {"lines": False}):
        out = io.StringIO()
        for _ in progress(range(5), desc="x", file=out, **kwargs):
            pass
        assert out.getvalue() == ""


def test_on_a_terminal_it_is_tqdms_bar_with_rate_and_eta():
    out = _Terminal()
    for _ in progress(range(5), desc="relabel", unit="frame", file=out):
        pass
    text = out.getvalue()
    assert "\r" in text and "relabel: 100%" in text and "5/5" in text and "frame/s" in text
    quiet = _Terminal()
    for _ in progress(range(5), desc="relabel", file=quiet, enabled=False, lines=False):
        pass
    assert quiet.getvalue() == ""


def test_write_puts_a_line_between_the_plain_lines():
    out = io.StringIO()
    bar = progress(total=2, desc="w", every=1, file=out)
    bar.update(1)
    write("a message", file=out)
    bar.update(1)
    bar.close()
    assert out.getvalue().splitlines()[1] == "a message"
    assert len(out.getvalue().splitlines()) == 3
