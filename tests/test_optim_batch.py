"""The ask(n) contract for every registered optimiser: n distinct points (fewer only where
the optimiser must hear back first), none at an asked point, tells by trial number in any
order, and asking again afterwards works; sequential use is unchanged (see
test_optim_contract.py, and the bit-identity of proposals checked when batch mode came in)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.optim import METHODS, make_optimizer
from kftune.optim.base import coincides
from test_optim_contract import SPACE, _method, _options, objective

#: The contract runs every method on small budgets: the GA's "no generation" warning
#: is expected there.
pytestmark = pytest.mark.filterwarnings("ignore::kftune.errors.SettingWarning")


def _drive(method: str, q: int, order_seed: int, budget: int = 14) -> list:
    opt = make_optimizer(_method(method), SPACE, budget=budget, seed=0, **_options(method))
    rng = np.random.default_rng(order_seed)
    asked = np.empty((0, 3))
    while not opt.done:
        try:
            trials = opt.ask(q)
        except RuntimeError:  # must hear back first: only with trials pending
            assert opt.pending_trials
            trials = []
        us = np.array([t.u for t in trials]).reshape(-1, 3)
        if len(us):
            assert len(trials) <= q
            # distinct among themselves and from every earlier point
            for i in range(len(us)):
                assert not coincides(us[i : i + 1], np.vstack([asked, us[:i]])).any()
            asked = np.vstack([asked, us])
        pending = list(opt.pending_trials)
        assert pending, "ask(n) gave nothing while nothing was pending"
        # tell a random non-empty subset, in random order (by number)
        k = int(rng.integers(1, len(pending) + 1))
        for j in rng.permutation(len(pending))[:k]:
            t = pending[j]
            opt.tell(t.number, objective(t.x))
    for t in opt.pending_trials:
        opt.tell(t.number, objective(t.x))
    assert opt.n_evals == len(asked) <= budget
    return [h.number for h in opt.history]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("q", [2, 4])
def test_ask_n_contract(method, q):
    numbers = _drive(method, q, order_seed=q)
    assert sorted(numbers) == list(range(len(numbers)))


@given(order_seed=st.integers(0, 2**16), q=st.integers(1, 5))
@settings(max_examples=8, deadline=None)
def test_any_tell_order_is_accepted_by_the_default_tuner(order_seed, q):
    _drive("trbo", q, order_seed, budget=12)


def test_ask_one_still_refuses_while_pending_and_tell_rejects_unknown_numbers():
    opt = make_optimizer("random", SPACE, budget=5, seed=0)
    trials = opt.ask(3)
    assert len(trials) == 3
    with pytest.raises(RuntimeError, match="still pending"):
        opt.ask()
    with pytest.raises(ValueError, match="not the pending trial"):
        opt.tell(99, 1.0)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        opt.ask(0)
    opt.tell(trials[2].number, 1.0)
    opt.tell(trials[0], 2.0)
    opt.tell(trials[1].x, 3.0)
    assert [h.number for h in opt.history] == [2, 0, 1]
    assert len(opt.ask(5)) == 2  # the budget ends
