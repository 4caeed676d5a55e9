"""Former home of the objective, now split along what it held: :mod:`.seeds`, :mod:`.target`,
:mod:`.scoring` and :mod:`.worker` (and :mod:`.progress`).

Kept only for ``report/run_view.py``, which still imports these names from here; once it calls
:func:`~.scoring.build_scoring` (issue 34) this module goes.
"""
from .seeds import model_seeds
from .target import build_target, feature_set_for
from .worker import _CTX, init_worker

__all__ = ["model_seeds", "build_target", "feature_set_for", "init_worker", "_CTX"]
