"""The plugin's own tests, as a third-party author would write them: the Bayes Forest
conformance kit plus a few known answers of the model.

Run with ``pytest docs/examples/bforest-example-ssm/tests`` (after installing the plugin).
"""

import numpy as np
import pytest

from bforest_core.testing import check_ssm, ssm_checks
from bforest_example_ssm import LSystemSSM


# one pytest test per conformance check: a failure names the check
@pytest.mark.parametrize(
    "check", ssm_checks(LSystemSSM, params={"iterations": 5}, registered="bforest-example-ssm"), ids=str
)
def test_conformance(check):
    check()


def test_conformance_with_a_small_segment_cap():
    # every bound setting must give a valid tree or fail with SimulationFailed
    check_ssm(LSystemSSM, settings={"max_segments": 500}, bounds="each")


def test_no_laterals_gives_a_straight_trunk():
    t = LSystemSSM().simulate({"lateral_prob": 0.0, "angle_sd": 0.0, "iterations": 4}, seed=1)
    assert t.n == 4 and t.n_branches == 1
    np.testing.assert_allclose(t.end[-1], [0.0, 0.0, 4 * 0.4])
