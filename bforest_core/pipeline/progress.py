"""Progress bars of the pipeline's long stages (a silent stand-in when switched off)."""

from __future__ import annotations

import weakref


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix_str(self, s, refresh=True):
        pass

    def close(self):
        pass


#: the bars this process has open: a message printed while one is open (Ctrl-C, an error) first
#: ends them, so it starts a line of its own instead of being glued to the bar
_OPEN: weakref.WeakSet = weakref.WeakSet()


def progress_bar(total, desc: str, unit: str, enabled: bool = True):
    """A tqdm progress bar, or a silent stand-in when ``enabled`` is false."""
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    bar = tqdm(total=total, unit=unit, desc=desc, dynamic_ncols=True)
    _OPEN.add(bar)
    return bar


def end_open_bars() -> None:
    """Close every progress bar still open (each ends its line), e.g. before a Ctrl-C's message."""
    for bar in list(_OPEN):
        try:
            bar.close()
        except Exception:  # a bar that cannot draw any more still must not hide the message
            pass
    _OPEN.clear()
