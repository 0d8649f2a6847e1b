"""Progress bars of the passes that take more than a few seconds (replay, reference track,
calibration, tuning): tqdm on stderr, drawn only when stderr is a terminal (``enabled=None``) or
when asked (``enabled=True``); ``enabled=False`` (``--quiet``, ``--no-progress``) draws nothing.
``progress_bar`` counts known work (seconds of bag, trials); ``busy`` shows the time spent and the
last message of a pass whose length is not known in advance.

A disabled bar is tqdm's own no-op: wrapping an iterable costs next to nothing."""
from __future__ import annotations

import contextlib
import os
import sys
import threading


def progress_enabled(enabled: bool | None = None) -> bool:
    """``enabled`` as given, else whether stderr is a terminal."""
    if enabled is not None:
        return bool(enabled)
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stderr
        return False


def progress_bar(iterable=None, *, total=None, desc: str = "", unit: str = "it", enabled: bool | None = None,
                 **kwargs):
    """A tqdm bar on stderr (``leave=False``: it disappears when done, the tool's own lines stay)."""
    from tqdm import tqdm

    on = progress_enabled(enabled)
    sized = _terminal_columns() > 0  # a terminal of no size (some ptys): a fixed width, else tqdm draws nothing
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not on, file=sys.stderr, leave=False,
                dynamic_ncols=sized, ncols=None if sized else 100, nrows=None if sized else 40, mininterval=0.1,
                **kwargs)


def _terminal_columns() -> int:
    try:
        return os.get_terminal_size(sys.stderr.fileno()).columns
    except (AttributeError, ValueError, OSError):  # not a terminal, or a replaced stderr
        return 0


def write_line(line: str) -> None:
    """One line on stderr that does not tear a bar being drawn (tqdm.write)."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr)


@contextlib.contextmanager
def busy(desc: str, enabled: bool | None = None, interval: float = 0.5):
    """A pass whose length is not known in advance (a reference track, a calibration): while the
    ``with`` block runs, a bar line on stderr shows ``desc``, the time spent and the pass's last
    message. Yields ``say(line)``: the line goes to stderr (above the bar) and becomes that message."""
    bar = progress_bar(total=None, desc=desc, enabled=enabled, bar_format="{desc} [{elapsed}]{postfix}")
    stop = threading.Event()

    def refresh():
        while not stop.wait(interval):
            bar.refresh()

    ticker = None if bar.disable else threading.Thread(target=refresh, name="progress-busy", daemon=True)
    if ticker is not None:
        ticker.start()

    def say(line: str) -> None:
        write_line(line)
        if not bar.disable:
            bar.set_postfix_str(" ".join(str(line).split())[:80])

    try:
        yield say
    finally:
        stop.set()
        if ticker is not None:
            ticker.join(timeout=2 * interval)
        bar.close()
