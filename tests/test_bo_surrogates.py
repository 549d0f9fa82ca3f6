"""The surrogate contract the optimiser relies on: factory, degenerate data, reproducibility,
conditioning with frozen hyperparameters, resume state, bounds, validation, layering."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel as C
from sklearn.gaussian_process.kernels import Matern

from kftune.bo import SURROGATES, Predictive, make_surrogate
from kftune.bo.acquisition import expected_improvement, log_expected_improvement

NAMES = list(SURROGATES)


def assert_same_predictive(a: Predictive, b: Predictive) -> None:
    """Bit-identical predictives."""
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.variance, b.variance)
    assert a.dof == b.dof


def toy(n: int, d: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((n, d))
    return X, np.sin(5 * X[:, 0]) + (X[:, 1:] ** 2).sum(axis=1)


# ---------------------------------------------------------------- factory
def test_factory_builds_each_surrogate():
    assert set(NAMES) == {"tsp", "gp", "robust-gp"}
    tsp = make_surrogate("tsp", seed=1)
    assert tsp.dof == 15.0 and not tsp.fit_dof
    assert make_surrogate("tsp", dof=7.0, fit_dof=True).fit_dof
    assert make_surrogate("gp").model_name == "gp"
    assert make_surrogate("robust-gp", likelihood_dof=3.0).likelihood_dof == 3.0


def test_factory_rejects_unknown_names_and_options_clearly():
    with pytest.raises(ValueError, match=r"valid names: tsp, gp, robust-gp"):
        make_surrogate("gpr")
    with pytest.raises(ValueError, match=r"unknown option.*'nu'.*valid options"):
        make_surrogate("tsp", nu=5)
    with pytest.raises(ValueError, match="dof"):
        make_surrogate("tsp", dof=1.5)
    with pytest.raises(ValueError, match="bounds row 1"):
        make_surrogate("gp", bounds=[[0, 1], [2, 2]])


# ---------------------------------------------------------------- degenerate data
DEGENERATE = {
    "n=1": (np.array([[0.5, 0.5, 0.5]]), np.array([2.0])),
    "duplicates": (np.repeat([[0.2, 0.3, 0.4], [0.7, 0.1, 0.9]], 3, axis=0), np.arange(6.0)),
    "constant y": (np.random.default_rng(0).random((8, 3)), np.full(8, 3.25)),
    "duplicates, constant y": (np.repeat([[0.5, 0.5, 0.5]], 4, axis=0), np.full(4, -1.0)),
    "two points": (np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), np.array([1.0, 1e6])),
}


@pytest.mark.parametrize("case", list(DEGENERATE))
@pytest.mark.parametrize("name", NAMES)
def test_fit_never_raises_on_degenerate_data(name, case):
    X, y = DEGENERATE[case]
    model = make_surrogate(name, seed=0).fit(X, y)
    cand = np.random.default_rng(1).random((50, 3))
    pred = model.predict(cand)
    assert pred.mean.shape == (50,) and np.all(np.isfinite(pred.mean))
    assert np.all(np.isfinite(pred.variance)) and np.all(pred.variance >= 0)
    assert np.all(np.isfinite(log_expected_improvement(pred, float(y.min()))))
    json.dumps(model.hyperparameters)


def test_constant_data_predicts_the_constant():
    X, y = DEGENERATE["constant y"]
    for name in NAMES:
        pred = make_surrogate(name, seed=0).fit(X, y).predict(X)
        np.testing.assert_allclose(pred.mean, 3.25, rtol=1e-9)


# ---------------------------------------------------------------- reproducibility
@pytest.mark.parametrize("name", NAMES)
def test_same_seed_same_fit_sequence_gives_bit_identical_predictions(name):
    X, y = toy(30)
    cand = np.random.default_rng(9).random((200, 3))

    def run(seed: int) -> list[Predictive]:
        model = make_surrogate(name, seed=seed)
        out = []
        for n in (5, 12, 30):  # a growing design, as in BO (warm starts in between)
            out.append(model.fit(X[:n], y[:n]).predict(cand))
        return out

    for pa, pb in zip(run(3), run(3)):
        assert_same_predictive(pa, pb)


@pytest.mark.parametrize("name", NAMES)
def test_state_round_trip_through_json_resumes_bit_identically(name):
    X, y = toy(25, seed=4)
    cand = np.random.default_rng(2).random((100, 3))
    original = make_surrogate(name, seed=11)
    original.fit(X[:10], y[:10])
    state = json.loads(json.dumps(original.get_state()))
    resumed = make_surrogate(name, seed=999).set_state(state)  # the seed is in the state
    # the next fit continues exactly where the original goes
    assert_same_predictive(original.fit(X, y).predict(cand), resumed.fit(X, y).predict(cand))
    assert original.hyperparameters == resumed.hyperparameters


# ---------------------------------------------------------------- condition (frozen)
@pytest.mark.parametrize("name", NAMES)
def test_condition_keeps_hyperparameters_and_uses_the_new_data(name):
    X, y = toy(30, seed=5)
    model = make_surrogate(name, seed=0).fit(X[:20], y[:20])
    before = model.hyperparameters
    theta = model.theta
    model.condition(X, y)
    assert model.hyperparameters == before
    assert getattr(model, "laplace_converged", True)
    np.testing.assert_array_equal(model.theta, theta)
    # the new points now inform the posterior: uncertainty there collapses
    fresh = make_surrogate(name, seed=0).fit(X[:20], y[:20])
    assert np.all(model.predict(X[20:]).std < fresh.predict(X[20:]).std)
    if name == "robust-gp":
        return
    # Conditioning is exact inference with the *natural-unit* hyperparameters kept: the
    # same as scikit-learn's GP with that kernel, noise and constant mean (the tSP shares
    # the GP's posterior mean).
    hp = model.hyperparameters
    kernel = C(hp["signal_variance"]) * Matern(hp["length_scales"], nu=2.5)
    sk = GaussianProcessRegressor(
        kernel, alpha=hp["noise_variance"] + hp["jitter"], optimizer=None
    ).fit(X, y - hp["mean"])
    cand = np.random.default_rng(3).random((20, 3))
    mean, std = sk.predict(cand, return_std=True)
    pred = model.predict(cand)
    np.testing.assert_allclose(pred.mean, mean + hp["mean"], rtol=1e-7, atol=1e-9)
    if name == "gp":
        np.testing.assert_allclose(pred.std, std, rtol=1e-6)


def test_condition_and_predict_before_fit_raise():
    model = make_surrogate("gp")
    with pytest.raises(RuntimeError, match="before fit"):
        model.condition(*toy(3))
    with pytest.raises(RuntimeError, match="before fit"):
        model.predict(np.zeros((1, 3)))
    assert model.hyperparameters == {"model": "gp", "fitted": False}


# ---------------------------------------------------------------- bounds
@pytest.mark.parametrize("name", NAMES)
def test_bounds_map_the_box_to_the_unit_cube(name):
    X, y = toy(15)
    # power-of-two widths and zero offsets make the normalisation exact in floating point
    widths = np.array([4.0, 0.25, 1024.0])
    lo = np.zeros(3)
    boxed = make_surrogate(name, seed=5, bounds=np.c_[lo, widths]).fit(X * widths, y)
    unit = make_surrogate(name, seed=5).fit(X, y)
    cand = np.random.default_rng(7).random((30, 3))
    assert_same_predictive(boxed.predict(cand * widths), unit.predict(cand))
    np.testing.assert_allclose(
        boxed.hyperparameters["length_scales"],
        np.array(unit.hyperparameters["length_scales"]) * widths,
        rtol=1e-15,
    )


# ---------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("X", "y", "message"),
    [
        (np.zeros(4), np.zeros(4), "2-D"),
        (np.zeros((4, 3)), np.zeros((4, 1)), "1-D"),
        (np.zeros((4, 3)), np.zeros(3), "4 rows but y has 3"),
        (np.zeros((0, 3)), np.zeros(0), "at least one"),
        (np.zeros((4, 3)), np.array([0.0, 1.0, np.nan, 2.0]), "y row 2"),
        (np.array([[0, 0, 0], [0, np.inf, 0]]), np.zeros(2), "row 1, column 1"),
    ],
)
def test_bad_training_data_raise_value_errors_naming_the_problem(X, y, message):
    with pytest.raises(ValueError, match=message):
        make_surrogate("gp").fit(X, y)


def test_predict_checks_the_dimension():
    model = make_surrogate("tsp", seed=0).fit(*toy(6))
    with pytest.raises(ValueError, match="3 columns"):
        model.predict(np.zeros((2, 2)))


def test_acquisition_runs_on_every_surrogate_output():
    X, y = toy(20)
    cand = np.random.default_rng(4).random((300, 3))
    for name in NAMES:
        pred = make_surrogate(name, seed=0).fit(X, y).predict(cand)
        ei = expected_improvement(pred, float(y.min()))
        assert ei.shape == (300,) and np.all(ei >= 0) and ei.max() > 0
        assert (pred.dof == 15.0 + 20) if name == "tsp" else np.isinf(pred.dof)


def test_bo_does_not_import_vehicle_filter_data_or_optim_code():
    code = (
        "import sys, kftune.bo, kftune.bo.acquisition; "
        "bad = [m for m in sys.modules if m.startswith(('kftune.vehicle', 'kftune.filters', "
        "'kftune.data', 'kftune.optim', 'kftune.tuning', 'kftune.report'))]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.parametrize("name", NAMES)
def test_bad_data_is_refused_naming_the_row(name):
    """NaN/inf, and values whose squares (variances in y's units) overflow, are a clear
    error naming the row — never a silent NaN prediction."""
    X = np.random.default_rng(0).random((6, 2))
    y = np.arange(6.0)
    for bad, match in ((np.nan, "y row 3 is not finite"), (1e300, "y row 3 is 1e.300.*overflow")):
        yb = y.copy()
        yb[3] = bad
        with pytest.raises(ValueError, match=match):
            make_surrogate(name, seed=0).fit(X, yb)
    Xb = X.copy()
    Xb[2, 1] = np.inf
    with pytest.raises(ValueError, match="X row 2, column 1 is not finite"):
        make_surrogate(name, seed=0).fit(Xb, y)
    make_surrogate(name, seed=0).fit(X, y * 1e99)  # large but representable: fine
