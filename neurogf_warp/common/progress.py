"""Progress display of long stages (ground truth, training, evaluation), the same for every stage.

On a terminal it is a tqdm bar redrawn in place. Written to a file, a pipe, a CI log or ``nohup.out`` such a bar
comes out as thousands of carriage-return updates, so there it is a plain line every ``PLAIN_EVERY_S`` seconds and
one at the end: ``training: 1,200/4,000 steps (30%), 21.4 steps/s, 56 s elapsed``.
"""
from __future__ import annotations

import sys
import time

__all__ = ["Progress", "progress", "PLAIN_EVERY_S"]

PLAIN_EVERY_S = 20.0  # seconds between plain lines when stderr is not a terminal


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # a closed or odd stream: no bar
        return False


def _in_notebook(stream) -> bool:
    # Jupyter's stderr is no terminal, yet tqdm.auto draws a widget there that updates in place
    return stream is sys.stderr and "ipykernel" in sys.modules


class Progress:
    """Progress of ``total`` units of work, shown on ``stream`` (default stderr) while ``on``.

    Parameters
    ----------
    total : int
        units of work expected (steps, sources, paths)
    desc : str
        the stage's name, the start of every line
    unit : str
        the unit's singular name ("step", "source")
    on : bool
        False shows nothing (``progress=False``, ``-q``)
    initial : int
        units already done (a resumed run)
    leave : bool
        keep the finished bar on the terminal (plain lines always stay)
    total_tolerance : float
        ``set_total`` takes a new total only when it differs from the shown one by more than this fraction, so
        that a total re-estimated every few seconds does not change what the reader sees every few seconds
    stream : file-like or None
        where to write (default: ``sys.stderr`` at construction)
    every_s : float
        seconds between plain lines
    clock : callable
        seconds, monotonic (tests pass their own)
    """

    def __init__(self, total: int, desc: str, unit: str = "step", on: bool = True, initial: int = 0,
                 leave: bool = True, total_tolerance: float = 0.0, stream=None, every_s: float = PLAIN_EVERY_S,
                 clock=time.monotonic):
        self.stream = sys.stderr if stream is None else stream
        on = on and self.stream is not None  # None: the process was started with stderr closed
        self.on, self.desc, self.unit = on, desc, unit
        self.n, self.total = int(initial), int(total)
        self.tolerance, self.every_s, self.clock = total_tolerance, every_s, clock
        self.postfix = ""
        self.total_changes = 0  # how often the shown total changed (tests read it)
        self._bar = None
        self._closed = not on
        self._t0 = self._last = clock()
        self._n0 = self.n
        if on and (_is_terminal(self.stream) or _in_notebook(self.stream)):
            from tqdm.auto import tqdm

            self._bar = tqdm(total=self.total, initial=self.n, desc=desc, unit=unit, dynamic_ncols=True,
                             file=self.stream, leave=leave)

    # -- the work
    def update(self, n: int = 1) -> None:
        """``n`` more units done."""
        self.n += int(n)
        if self._closed:
            return
        if self._bar is not None:
            self._bar.update(n)
        elif self.clock() - self._last >= self.every_s:
            self._line()

    def set_postfix(self, text: str) -> None:
        """A short status shown after the counts (a loss, a learning rate)."""
        self.postfix = text
        if self._bar is not None and not self._closed:
            self._bar.set_postfix_str(text)

    def set_total(self, total: int) -> bool:
        """A new expected total; returns whether the shown total changed (see ``total_tolerance``)."""
        total = int(total)
        if total == self.total or abs(total - self.total) <= self.tolerance * max(self.total, 1):
            return False
        self.total = total
        self.total_changes += 1
        if self._bar is not None and not self._closed:
            self._bar.total = total
            self._bar.refresh()
        return True

    def finish(self) -> None:
        """All work done: the total becomes the count done (an estimated total was off), then ``close``."""
        if self.n != self.total:
            self.total = self.n
            if self._bar is not None and not self._closed:
                self._bar.total = self.n
                self._bar.refresh()
        self.close()

    def close(self) -> None:
        """Stop showing; in plain mode one last line with the final counts."""
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        else:
            self._line()

    # -- plain lines
    def _line(self) -> None:
        now = self.clock()
        self._last = now
        elapsed = now - self._t0
        rate = (self.n - self._n0) / elapsed if elapsed > 0 else 0.0
        units = self.unit if self.total == 1 else self.unit + "s"
        pct = f" ({100 * self.n / self.total:.0f}%)" if self.total > 0 else ""
        text = (f"{self.desc}: {self.n:,}/{self.total:,} {units}{pct}, {rate:.3g} {self.unit}s/s, "
                f"{elapsed:.0f} s elapsed" + (f", {self.postfix}" if self.postfix else ""))
        try:
            print(text, file=self.stream, flush=True)
        except (OSError, ValueError):  # stderr closed or gone: progress is not worth failing the work for
            self.on, self._closed = False, True

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(total: int, desc: str, on: bool = True, **kw) -> Progress:
    """``Progress(total, desc, on=on, **kw)``: the one way stages show progress."""
    return Progress(total, desc, on=on, **kw)
