"""Progress bars of the pipeline's long stages (a silent stand-in when switched off)."""

from __future__ import annotations


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix_str(self, s, refresh=True):
        pass

    def close(self):
        pass


def progress_bar(total, desc: str, unit: str, enabled: bool = True):
    """A tqdm progress bar, or a silent stand-in when ``enabled`` is false."""
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, unit=unit, desc=desc, dynamic_ncols=True)
