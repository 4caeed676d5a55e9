"""The SOT model with lateral buds that may abort, as a component of its own: ``kind = "sot-bud-abort"``."""

from __future__ import annotations

from bforest_core.hookspecs import hookimpl
from bforest_sot.plugin import SOT

from .form import BudAbort


class SOTBudAbort(SOT):
    """SOT (Palubicki et al. 2009; GS 2017) with one more growth form: buds that abort (``bud_abort``)."""

    name = "sot-bud-abort"
    summary = "SOT with lateral buds that abort (example third-party growth form)"
    forms = SOT.forms + (BudAbort,)


@hookimpl
def bforest_components():
    return [SOTBudAbort]
