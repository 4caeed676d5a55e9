"""The report: figures and the Markdown/HTML summary of a run directory.

Split by subject: ``trees`` (tree and clone figures), and the run report in ``build``. Imports the
kernel and the pipeline (to read a run); the pipeline never imports it.
"""

from .build import write_report

__all__ = ["write_report"]
