"""Conformance kit: checks any Bayes Forest component against the contract of its interface.

A plugin author runs it in their own test suite::

    from bforest_core.testing import check_ssm

    def test_my_model_conforms():
        check_ssm(MyModel, params={"years": 5})      # raises ConformanceError on a failure

or, one pytest test per check (failures then show up individually)::

    import pytest
    from bforest_core.testing import ssm_checks

    @pytest.mark.parametrize("check", ssm_checks(MyModel, params={"years": 5}), ids=str)
    def test_my_model(check):
        check()

Every kind has a ``<kind>_checks(...)`` function returning a list of :class:`Check` objects and a
``check_<kind>(...)`` function running them and returning a :class:`Report` (raising a
:class:`ConformanceError` that lists every failed check, unless ``raise_on_failure=False``).
:func:`check_component` picks the right one from the component's ``kind``; :func:`run_all`
checks every registered component (optionally only those of one distribution).

What is checked
---------------
all components
    ``class``: ``kind``/``name``/``Settings`` well formed; ``settings``: the settings round-trip
    (``model_dump`` -> new instance -> equal, also through JSON) and unknown keys are rejected;
    ``pickle``: an instance survives pickling *and still gives the same results* (executors
    ship components to worker processes); ``registered`` (optional): the registry resolves
    ``(kind, name)`` to this class, from the expected distribution.
SSM
    ``parameters`` (unique identifier names, ``lower <= default <= upper``, integer flags with
    whole values), ``resolve_params`` (defaults, integer rounding, unknown names rejected),
    ``simulate`` (a valid :class:`~bforest_core.Tree` with metadata ``model``, ``params``,
    ``seed``, ``status``), ``determinism`` (same params and seed -> bit-identical arrays),
    ``seeds`` (different seeds give different trees; ``stochastic=False`` turns it off),
    ``bounds`` (every parameter at its bounds returns a valid tree or raises
    ``SimulationFailed`` -- never another exception).
features
    ``set_names``/``columns``, ``extract`` (2-D float64 tables with one column per name, no
    inf), ``determinism``, ``pooled``.
distance
    ``identical`` (zero for identical inputs), ``finite`` (finite, non-negative), ``separates``
    (positive for shifted tables), ``determinism``, ``empty`` (an empty model table gives a
    finite value or ``None``).
qsm_reader / qsm_writer / optimizer / executor / amortised
    see :func:`reader_checks`, :func:`writer_checks`, :func:`optimizer_checks`,
    :func:`executor_checks`, :func:`amortised_checks`.
"""

from ._base import Check, CheckResult, ConformanceError, Report, check_tree
from .amortised import amortised_checks, check_amortised
from .distance import check_distance, distance_checks
from .executor import check_executor, executor_checks
from .features import check_feature_set, feature_set_checks
from .io import check_reader, check_writer, reader_checks, writer_checks
from .optimizer import check_optimizer, optimizer_checks
from .registry_checks import check_component, component_checks, run_all
from .samples import sample_tables, sample_tree, sample_trees
from .ssm import check_ssm, ssm_checks

__all__ = [
    "ConformanceError",
    "Check",
    "CheckResult",
    "Report",
    "check_tree",
    "sample_tree",
    "sample_trees",
    "sample_tables",
    "component_checks",
    "check_component",
    "ssm_checks",
    "check_ssm",
    "feature_set_checks",
    "check_feature_set",
    "distance_checks",
    "check_distance",
    "reader_checks",
    "check_reader",
    "writer_checks",
    "check_writer",
    "optimizer_checks",
    "check_optimizer",
    "executor_checks",
    "check_executor",
    "amortised_checks",
    "check_amortised",
    "run_all",
]
