"""Example third-party growth form of the SOT model: lateral buds that abort (``bud_abort``)."""

from .form import BudAbort
from .plugin import SOTBudAbort

__all__ = ["BudAbort", "SOTBudAbort"]
