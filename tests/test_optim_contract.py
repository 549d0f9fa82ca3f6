"""The contract every optimiser keeps: bounds, budget, seed reproducibility, failures
survived, and the ask/tell protocol. Peers whose package (or PyTorch) is missing skip;
kftune's own methods never do (a broken import of kftune's own code fails the tests)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.optim import METHODS, Execution, ExhaustedError, make_optimizer, minimize
from kftune.optim.base import coincides

#: The contract runs every method on small budgets: the GA's "no generation" warning
#: is expected there.
pytestmark = pytest.mark.filterwarnings("ignore::kftune.errors.SettingWarning")

SPACE = {"a": (-5.0, 10.0), "q": (1e-10, 1.0, "log10"), "c": (0.0, 1.0)}
BUDGET = 12


def _available(method: str) -> bool:
    """Whether a method's *third-party* package is installed; kftune's own methods (TSBO,
    GA, random, manual) are always available."""
    if method.startswith("optuna"):
        if importlib.util.find_spec("optuna") is None:
            return False
        return method != "optuna-gp" or importlib.util.find_spec("torch") is not None
    if method == "cma":
        return importlib.util.find_spec("cma") is not None
    return True


def _method(method: str) -> str:
    if not _available(method):
        pytest.skip(f"{method}: optuna, torch or cma is not installed")
    return method


def objective(x: np.ndarray) -> float:
    """Smooth, minimum inside the box; uses the log10 parameter as log10."""
    return float((x[0] - 1.0) ** 2 / 10 + (np.log10(x[1]) + 4.0) ** 2 + (x[2] - 0.3) ** 2)


def _options(method: str) -> dict:
    """Method options for the contract runs: two fixed points for manual; for TSBO no
    surrogate restarts (the optimiser's contract is under test here, not fit quality, and
    restarts multiply the fit time)."""
    if method == "manual":
        return {"points": [[0.0, 1e-3, 0.5], [1.0, 1e-4, 0.3]]}
    if method.startswith("tsbo"):
        return {"surrogate_options": {"n_restarts": 0}}
    return {}


def _run(method: str, seed: int, fun=objective, budget: int = BUDGET):
    return minimize(fun, SPACE, method, budget=budget, seed=seed, **_options(method))


@pytest.mark.parametrize("method", METHODS)
def test_bounds_and_budget(method):
    method = _method(method)
    calls = []

    def fun(x):
        calls.append(np.array(x))
        return objective(x)

    res = _run(method, 0, fun)
    expected = 2 if method == "manual" else BUDGET
    assert res.n_evals == len(calls) == expected
    assert res.status == ("exhausted" if method == "manual" else "completed")
    lows, highs = np.array([-5.0, 1e-10, 0.0]), np.array([10.0, 1.0, 1.0])
    for r, x in zip(res.history, calls):
        np.testing.assert_array_equal(np.array(r.x), x)
        assert np.all(x >= lows) and np.all(x <= highs), (method, x)
        assert all(0.0 <= v <= 1.0 for v in r.u)
        assert r.state == "complete" and r.value == objective(x)
    assert res.fun == min(r.value for r in res.history)
    assert res.x is not None and objective(res.x) == res.fun


@pytest.mark.parametrize("method", METHODS)
def test_same_seed_same_run_other_seed_other_run(method):
    method = _method(method)
    r1, r2 = _run(method, 7), _run(method, 7)
    assert [h.x for h in r1.history] == [h.x for h in r2.history]
    assert [h.value for h in r1.history] == [h.value for h in r2.history]
    assert [h.acquisition for h in r1.history] == [h.acquisition for h in r2.history]
    if method != "manual":
        r3 = _run(method, 8)
        assert [h.x for h in r3.history] != [h.x for h in r1.history]


@pytest.mark.parametrize("method", METHODS)
def test_failures_are_recorded_and_survived(method):
    """An exception, NaN and inf are failed evaluations with their reason; a huge finite
    value is a value; the run goes on to its budget and never re-proposes a failed point."""
    method = _method(method)

    def flaky(x):
        if x[0] > 6.0:
            raise RuntimeError("filter diverged")
        if x[2] > 0.8:
            return float("nan")
        if x[2] < 0.15:
            return -float("inf") if x[0] < 0.0 else float("inf")
        if x[0] < -3.0:
            return 1e300  # finite: must not break a surrogate
        return objective(x)

    res = _run(method, 1, flaky, budget=16)
    n = 2 if method == "manual" else 16
    assert res.n_evals == n
    for r in res.history:
        x = np.array(r.x)
        if x[0] > 6.0:
            assert r.state == "failed" and r.value is None
            assert r.reason == "RuntimeError: filter diverged"
        elif x[2] > 0.8:
            assert r.state == "failed" and r.reason == "non-finite value nan"
        elif x[2] < 0.15:
            assert r.state == "failed" and r.reason.startswith("non-finite value")
            assert "inf" in r.reason
        else:
            assert r.state == "complete" and r.value == flaky(x)
    assert res.n_failed == sum(r.state == "failed" for r in res.history)
    if res.fun is not None:
        assert res.fun == min(r.value for r in res.history if r.ok)
    if method != "manual":
        assert res.n_failed > 0
    u = np.array([r.u for r in res.history])
    failed = np.array([r.state == "failed" for r in res.history])
    for i in np.flatnonzero(failed):
        others = np.delete(u, i, axis=0)
        gap = np.max(np.abs(others - u[i]), axis=1).min() if len(others) else np.inf
        assert gap > 1e-9, (method, "failed point proposed again", u[i])


def _sleepy(x):
    if x[0] > 5.0:
        import time

        time.sleep(5.0)
    return objective(x)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.slow
def test_timeouts_fail_the_evaluation_only(method):
    method = _method(method)
    res = minimize(
        _sleepy,
        SPACE,
        method,
        budget=8,
        seed=2,
        execution=Execution(timeout=0.5),
        **_options(method),
    )
    assert res.n_evals == (2 if method == "manual" else 8)
    for r in res.history:
        if r.x[0] > 5.0:
            assert r.state == "failed" and r.reason == "timeout after 0.5 s", r
        else:
            assert r.state == "complete" and r.value == objective(np.array(r.x))
    if method != "manual":
        assert 0 < res.n_failed < res.n_evals, [r.x for r in res.history]


@pytest.mark.parametrize("method", METHODS)
def test_ask_tell_protocol(method):
    method = _method(method)
    opt = make_optimizer(method, SPACE, budget=3, seed=0, **_options(method))
    with pytest.raises(RuntimeError, match=r"no trial is pending"):
        opt.tell(0, 1.0)
    t = opt.ask()
    with pytest.raises(RuntimeError, match=r"still pending"):
        opt.ask()
    with pytest.raises(ValueError, match=r"not the pending trial"):
        opt.tell(t.number + 5, 1.0)
    # A trial can be told by its point in natural units, and a failure by state.
    rec = opt.tell(t.x, state="failed", reason="sensor file missing")
    assert rec.state == "failed" and rec.reason == "sensor file missing"
    while not opt.done:
        t = opt.ask()
        opt.tell(t, objective(t.x))
    with pytest.raises(ExhaustedError):
        opt.ask()


def test_unknown_method_and_option():
    with pytest.raises(ValueError, match=r"unknown method 'nelder'.*tsbo-tsp"):
        make_optimizer("nelder", SPACE)
    with pytest.raises(ValueError, match=r"'ga' has no option.*'popsize'.*population_size"):
        make_optimizer("ga", SPACE, popsize=3)
    with pytest.raises(ValueError, match=r"budget must be a positive integer"):
        make_optimizer("random", SPACE, budget=0)
    with pytest.raises(ValueError, match=r"seed must be a non-negative integer"):
        make_optimizer("random", SPACE, seed=-1)


def test_manual_points_are_evaluated_exactly():
    pts = [[0.5, 3.3e-7, 0.25]]
    seen = []
    res = minimize(lambda x: seen.append(x.copy()) or 1.0, SPACE, "manual", points=pts)
    assert seen[0].tolist() == pts[0]  # no log10 round trip on the given point
    assert res.n_evals == 1
    with pytest.raises(ValueError, match=r"manual point 0.*outside"):
        make_optimizer("manual", SPACE, points=[[20.0, 1e-3, 0.5]])


def test_optuna_gp_without_torch_is_a_clear_error(monkeypatch):
    real = importlib.util.find_spec

    def fake(name, *a, **k):
        return None if name == "torch" else real(name, *a, **k)

    monkeypatch.setattr(importlib.util, "find_spec", fake)
    from kftune.optim.peers import PeerUnavailableError

    with pytest.raises(PeerUnavailableError, match=r"'optuna-gp' needs the package 'torch'"):
        make_optimizer("optuna-gp", SPACE)


def test_trial_points_are_read_only_and_resume_needs_storage():
    opt = make_optimizer("random", SPACE, seed=0)
    t = opt.ask()
    with pytest.raises(ValueError, match="read-only"):
        t.x[0] = 1.0
    with pytest.raises(ValueError, match="resume=True needs storage"):
        minimize(objective, SPACE, "random", resume=True)


@pytest.mark.parametrize("method", METHODS)
def test_budget_independent_methods_make_a_prefix_of_a_longer_run(method):
    """A method that declares its proposals budget-independent (benchmarks then read short
    budgets off one long run) proposes, with budget 10, exactly the first 10 points of a
    run with budget 25."""
    method = _method(method)
    if not type(make_optimizer(method, SPACE, **_options(method))).budget_independent:
        pytest.skip(f"{method}: the budget shapes its run (run once per budget)")
    short, long = _run(method, 3, budget=10), _run(method, 3, budget=25)
    assert [r.x for r in short.history] == [r.x for r in long.history[: short.n_evals]]
    assert short.n_evals == min(10, long.n_evals)


@pytest.mark.parametrize("method", ["trbo", "tsbo-tsp", "tsbo-gp", "tsbo-robust", "ga", "random"])
def test_kftunes_own_methods_are_never_skipped(method):
    """Only a missing third-party package may skip a contract test: were kftune's own
    surrogates unimportable, the TSBO tests must fail, not skip."""
    assert _available(method)
    assert _method(method) == method


@settings(max_examples=60, deadline=None)
@given(
    m=st.integers(0, 30),
    n=st.integers(0, 30),
    d=st.integers(1, 4),
    seed=st.integers(0, 2**32 - 1),
    atol=st.sampled_from([0.0, 1e-9, 0.05, 0.3]),
)
def test_coincides_equals_a_dense_max_norm_comparison(m, n, d, seed, atol):
    """The k-d tree answer equals the brute-force one, also for exact copies, points at
    exactly ``atol`` on a grid, and duplicated rows among the others."""
    rng = np.random.default_rng(seed)
    grid = np.round(rng.random((n, d)) * 4) / 4  # many exact ties at distance 0.25, 0.5, …
    others = np.vstack([grid, grid[: n // 3]])
    points = np.vstack([np.round(rng.random((m, d)) * 4) / 4, others[: m // 2] + atol])
    dense = (
        (np.abs(points[:, None, :] - others[None, :, :]).max(axis=2) <= atol).any(axis=1)
        if len(others) and len(points)
        else np.zeros(len(points), dtype=bool)
    )
    np.testing.assert_array_equal(coincides(points, others, atol), dense)
