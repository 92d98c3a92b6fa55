"""The one fallback ladder (`fojax.design._ladder.climb`) used by the functional-observer
LMI, the unknown-input LMI and the state feedback of `fojax.control`.

Oracle: hand-counted rung sequences (which thunks ran, in which order, what was refused).
"""

import pytest

from fojax.design._ladder import climb, Refused  # private: the ladder is tested itself
from fojax.errors import LMIInfeasibleError


def _rungs(outcomes, ran):
    def thunk(label, outcome):
        def run():
            ran.append(label)
            if isinstance(outcome, Exception):
                raise outcome
            return outcome
        return run

    return [(label, thunk(label, outcome)) for label, outcome in outcomes]


def test_first_success_wins_with_the_refusals_before_it():
    ran = []
    first, second = ValueError("inaccurate"), ValueError("singular")
    label, result, refused = climb(_rungs([(("a", 1), first), (("a", 2), second), (("b", 1), "ok"),
                                           (("b", 2), "never")], ran), refusals=(ValueError,))
    assert (label, result) == (("b", 1), "ok") and ran == [("a", 1), ("a", 2), ("b", 1)]
    assert refused == [(("a", 1), first), (("a", 2), second)]


def test_give_up_skips_the_rest_of_a_group_and_every_failure_is_listed():
    ran = []
    infeasible = LMIInfeasibleError("lmi", "infeasible", {}, "")
    with pytest.raises(Refused) as info:
        climb(_rungs([(("lmi", 1), infeasible), (("lmi", 2), "skipped"), (("place", None), ValueError("x"))], ran),
              refusals=(LMIInfeasibleError, ValueError),
              give_up=lambda label, err: isinstance(err, LMIInfeasibleError))
    assert ran == [("lmi", 1), ("place", None)]
    assert [lb for lb, _ in info.value.refused] == [("lmi", 1), ("place", None)]


def test_other_errors_propagate():
    with pytest.raises(KeyError):
        climb(_rungs([("a", KeyError("bug")), ("b", "ok")], []), refusals=(ValueError,))
