"""The models in C (kftune.models.c_contract): each model's C, compiled with the header
kftune writes for it, against its Python twin through ctypes.

The C is compiled as the export compiles it (``cc -std=c99 -O2 -Wall -Wextra -Werror
-pedantic``) into a shared library per model and precision; every hook is called on many
rows and compared with the model's compiled Python hook. Skipped without a C compiler
(``$CC`` or ``cc``).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from kftune.models import StateSpaceModel, linear_model
from kftune.models.c_contract import (
    builtin_c_code,
    builtin_names,
    c_identifier,
    defined_functions,
    export_refusal,
    missing_hooks,
    model_header,
    required_hooks,
)

CC = shutil.which(os.environ.get("CC") or "cc")
needs_cc = pytest.mark.skipif(not CC, reason="no C compiler (cc or $CC)")
CFLAGS = ("-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-shared", "-fPIC")


# ------------------------------------------------------------------ compiling and calling --


def compile_model(
    model: StateSpaceModel, folder: Path, real: str = "double", extra: tuple[str, ...] = ()
) -> ctypes.CDLL:
    """The model's C and its header, compiled into a shared library in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    assert model.c_code is not None
    (folder / "kftune_model.h").write_text(model_header(model, real))
    (folder / "kftune_model.c").write_text(model.c_code)
    lib = folder / "libmodel.so"
    cmd = [CC, *CFLAGS, *extra, "-I", str(folder), str(folder / "kftune_model.c"), "-o", str(lib)]
    done = subprocess.run([*cmd, "-lm"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return ctypes.CDLL(str(lib))


class CModel:
    """The hooks of a compiled model, called with numpy arrays like their Python twins."""

    def __init__(self, lib: ctypes.CDLL, model: StateSpaceModel, real: str = "double") -> None:
        self.lib = lib
        self.model = model
        self.dtype = np.float64 if real == "double" else np.float32
        self.ct = ctypes.c_double if real == "double" else ctypes.c_float

    def _arr(self, a: np.ndarray | float | list[float]) -> np.ndarray:
        arr = np.ascontiguousarray(np.atleast_1d(np.asarray(a, dtype=self.dtype)))
        return arr if arr.size else np.zeros(1, self.dtype)

    def _ptr(self, a: np.ndarray) -> ctypes.c_void_p:
        return a.ctypes.data_as(ctypes.c_void_p)

    def _call(self, name: str, *args: np.ndarray | float, size: int) -> np.ndarray:
        out = np.full(size + 4, np.nan, self.dtype)
        cargs = [self.ct(a) if isinstance(a, float) else self._ptr(a) for a in args]
        getattr(self.lib, name)(*cargs, self._ptr(out))
        assert np.all(np.isnan(out[size:])), f"{name} wrote beyond its output"
        return out[:size].astype(np.float64)

    def prior(self, z0: np.ndarray, r: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.model.n_states
        x0 = np.full(n + 4, np.nan, self.dtype)
        P0 = np.full(n * n + 4, np.nan, self.dtype)
        z0, r, p = self._arr(z0), self._arr(r), self._arr(p)
        self.lib.kf_model_prior(*map(self._ptr, (z0, r, p, x0, P0)))
        assert np.all(np.isnan(x0[n:])) and np.all(np.isnan(P0[n * n :]))
        return x0[:n].astype(float), P0[: n * n].reshape(n, n).astype(float)

    def f(self, x: np.ndarray, w: np.ndarray, p: np.ndarray, dt: float) -> np.ndarray:
        args = (self._arr(x), self._arr(w), self._arr(p), float(dt))
        return self._call("kf_model_f", *args, size=self.model.n_states)

    def h(self, x: np.ndarray, w: np.ndarray, p: np.ndarray) -> np.ndarray:
        args = (self._arr(x), self._arr(w), self._arr(p))
        return self._call("kf_model_h", *args, size=self.model.n_measurements)

    def F(self, x: np.ndarray, w: np.ndarray, p: np.ndarray, dt: float) -> np.ndarray:
        n = self.model.n_states
        args = (self._arr(x), self._arr(w), self._arr(p), float(dt))
        return self._call("kf_model_F", *args, size=n * n).reshape(n, n)

    def H(self, x: np.ndarray, w: np.ndarray, p: np.ndarray) -> np.ndarray:
        n, m = self.model.n_states, self.model.n_measurements
        args = (self._arr(x), self._arr(w), self._arr(p))
        return self._call("kf_model_H", *args, size=m * n).reshape(m, n)

    def prepare(self, u: np.ndarray, p: np.ndarray) -> np.ndarray:
        args = (self._arr(u), self._arr(p))
        return self._call("kf_model_prepare", *args, size=self.model.prepared_size)

    def outputs(self, x: np.ndarray) -> np.ndarray:
        return self._call("kf_model_outputs", self._arr(x), size=max(len(self.model.outputs), 1))[
            : len(self.model.outputs)
        ]

    def check(
        self, x: np.ndarray, z: np.ndarray, w: np.ndarray, p: np.ndarray
    ) -> tuple[int, np.ndarray]:
        k = max(len(self.model.held_causes), 1)
        held = np.full(k, -7, dtype=np.intc)
        args = [self._ptr(self._arr(a)) for a in (x, z, w, p)]
        cause = self.lib.kf_model_check(*args, held.ctypes.data_as(ctypes.c_void_p))
        return int(cause), held


def python_outputs(model: StateSpaceModel, x: np.ndarray) -> np.ndarray:
    """(len(outputs),) the model's outputs of one state x, in the model's order."""
    return np.array([float(g(np.asarray(x, float)[None, :])[0]) for g in model.outputs.values()])


def rel_err(c: np.ndarray, py: np.ndarray) -> float:
    """Normwise relative difference ‖c − py‖ / max(‖py‖, tiny)."""
    c, py = np.asarray(c, float), np.asarray(py, float)
    return float(np.linalg.norm(c - py) / max(np.linalg.norm(py), 1e-300))


# ------------------------------------------------------------------------- the contract --


def test_c_identifier() -> None:
    """Names become upper-case C identifiers; one with nothing to keep is refused."""
    assert c_identifier("vx") == "VX"
    assert c_identifier("F[0,1]") == "F_0_1"
    assert c_identifier("b ay") == "B_AY"
    assert c_identifier("β") == "U03B2"
    with pytest.raises(ValueError, match="no C identifier"):
        c_identifier("[]")


def _models() -> list[StateSpaceModel]:
    from kftune.models import CTRV, SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES

    lin = linear_model(np.eye(2), [[1.0, 0.0]], G=[[0.1], [0.2]], D=[[0.5]], name="lin")
    return [SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES, CTRV, lin]


@pytest.mark.parametrize("model", _models(), ids=lambda m: m.name)
def test_header_macros_unique(model: StateSpaceModel) -> None:
    """Every #define of the header names one macro once, for either precision."""
    for real in ("double", "float"):
        text = model_header(model, real)
        macros = [line.split()[1] for line in text.splitlines() if line.startswith("#define")]
        assert len(macros) == len(set(macros))
        assert f"typedef {real} kf_real;" in text
        assert "#include <tgmath.h>" in text
        assert f"#define KF_N {model.n_states} " in text


def test_header_refuses_colliding_names_and_bad_real() -> None:
    """Two names that give one macro, and a type that is not a C real, are refused."""
    import dataclasses

    from kftune.models import CTRV

    twin = dataclasses.replace(CTRV, state_names=("px", "PX", "v", "psi", "omega"))
    with pytest.raises(ValueError, match=r"'px' and 'PX' both give the C macro KF_X_PX"):
        model_header(twin)
    with pytest.raises(ValueError, match="real must be one of double, float"):
        model_header(CTRV, "long double")


def test_missing_hooks_finds_a_missing_function() -> None:
    """A function renamed away is found missing, though a comment, a prototype and a
    call still name it; the export's refusal names it too."""
    import dataclasses

    from kftune.models import CTRV

    full = dataclasses.replace(CTRV, c_code=builtin_c_code("ctrv"))
    assert missing_hooks(full) == []
    # a prototype, a call and a comment do not define a function
    cut = full.c_code.replace("void kf_model_H(", "static void not_H(")  # type: ignore[union-attr]
    cut += "\n/* void kf_model_H(const kf_real x[]) { } */\nvoid kf_model_H(const kf_real x[]);\n"
    broken = dataclasses.replace(CTRV, c_code=cut)
    assert missing_hooks(broken) == ["kf_model_H"]
    assert "kf_model_H" in (export_refusal(broken) or "")
    assert "c_code is None" in (export_refusal(dataclasses.replace(CTRV, c_code=None)) or "")
    assert required_hooks(CTRV)[:4] == ["kf_model_prior", "kf_model_f", "kf_model_h",
                                        "kf_model_outputs"]  # fmt: skip
    assert defined_functions("int kf_model_check (\n const kf_real x[], int h[])\n{ return 0; }",
                             ["kf_model_check"]) == {"kf_model_check"}  # fmt: skip


def test_builtin_c_code_names_the_files() -> None:
    """The built-in C files are package data; an unknown one is refused naming those there are."""
    assert "ctrv" in builtin_names()
    with pytest.raises(ValueError, match="no built-in model C file 'nope'; there are: "):
        builtin_c_code("nope")


# ------------------------------------------------------------------- compiled libraries --

_LIBS: dict[tuple[str, str, tuple[str, ...]], CModel] = {}


@pytest.fixture(scope="module")
def c_model(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., CModel]]:
    """``c_model(model, real="double", extra=())``: the model's C compiled once per module."""

    def get(model: StateSpaceModel, real: str = "double", extra: tuple[str, ...] = ()) -> CModel:
        key = (model.name, real, extra)
        if key not in _LIBS:
            folder = tmp_path_factory.mktemp(f"c-{model.name}-{real}")
            _LIBS[key] = CModel(compile_model(model, folder, real, extra), model, real)
        return _LIBS[key]

    yield get
    _LIBS.clear()


# -------------------------------------------------------------------------------- ctrv --

TOL = 1e-12  # normwise relative, C against its compiled Python twin


def _ctrv_cases() -> list[tuple[np.ndarray, float]]:
    """CTRV states and steps: random over a wide box, and the sinc branches' edges (ω·dt/2
    at 0, just below and above the series threshold 0.1, tiny)."""
    rng = np.random.default_rng(3)
    cases = []
    for _ in range(300):
        x = np.array([rng.uniform(-1e4, 1e4), rng.uniform(-1e4, 1e4), rng.uniform(-60, 60),
                      rng.uniform(-10, 10), rng.uniform(-4, 4)])  # fmt: skip
        cases.append((x, float(rng.choice([0.001, 0.01, 0.05, 0.1, 1.0]))))
    for s in (0.0, 1e-300, 1e-9, -1e-5, 0.0999999, 0.1, 0.1000001, -0.2, 3.0):
        cases.append((np.array([1.0, -2.0, 15.0, 0.3, 2 * s / 0.1]), 0.1))
    return cases


@needs_cc
def test_ctrv_c_matches_python(c_model: Callable[..., CModel]) -> None:
    """ctrv's f, F, h, H and prior against the Python on wide and branch-edge states."""
    from kftune.models import CTRV

    assert CTRV.c_code == builtin_c_code("ctrv")
    c = c_model(CTRV)
    p = CTRV.default_params()
    w = np.zeros(0)
    for x, dt in _ctrv_cases():
        out = np.empty(5)
        CTRV.f(x, w, p, dt, out)
        assert rel_err(c.f(x, w, p, dt), out) <= TOL, (x, dt)
        J = np.empty((5, 5))
        CTRV.F(x, w, p, dt, J)
        assert rel_err(c.F(x, w, p, dt), J) <= TOL, (x, dt)
        z = np.empty(2)
        CTRV.h(x, w, p, z)
        assert rel_err(c.h(x, w, p), z) <= TOL
        Hm = np.empty((2, 5))
        CTRV.H(x, w, p, Hm)
        assert rel_err(c.H(x, w, p), Hm) <= TOL
    z0, r = np.array([12.5, -3.25]), np.array([0.04, 0.09])
    x0, P0 = CTRV.initial_state(z0, r, p)  # type: ignore[misc]
    cx0, cP0 = c.prior(z0, r, p)
    assert rel_err(cx0, x0) <= TOL and rel_err(cP0, P0) <= TOL
    assert c.outputs(x0).shape == (0,)


@needs_cc
def test_ctrv_c_matches_python_on_drawn_states(c_model: Callable[..., CModel]) -> None:
    """Hypothesis draws states and steps widely, also ω near 0 where sinc switches form."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from kftune.models import CTRV

    c = c_model(CTRV)
    p, w = CTRV.default_params(), np.zeros(0)
    big = st.floats(-1e5, 1e5, allow_nan=False)
    om = st.one_of(st.floats(-20, 20), st.floats(-1e-6, 1e-6), st.floats(0.19, 0.21))

    @settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))
    @given(big, big, st.floats(-100, 100), st.floats(-50, 50), om, st.floats(1e-4, 2.0))
    def check(px: float, py: float, v: float, psi: float, omega: float, dt: float) -> None:
        x = np.array([px, py, v, psi, omega])
        out, J = np.empty(5), np.empty((5, 5))
        CTRV.f(x, w, p, dt, out)
        CTRV.F(x, w, p, dt, J)
        assert rel_err(c.f(x, w, p, dt), out) <= TOL
        assert rel_err(c.F(x, w, p, dt), J) <= TOL

    check()


# ------------------------------------------------------------------------------ linear --


@needs_cc
def test_linear_model_c_matches_python(c_model: Callable[..., CModel]) -> None:
    """A linear model's generated C against its Python, its fixed prior read back exactly;
    without a prior it is refused for that reason."""
    rng = np.random.default_rng(5)
    n, nu, m = 4, 2, 3
    F, G = rng.normal(size=(n, n)), rng.normal(size=(n, nu))
    H, D = rng.normal(size=(m, n)), rng.normal(size=(m, nu))
    x0, P0 = rng.normal(size=n), np.diag(rng.uniform(0.1, 2.0, n)) + 0.01
    model = linear_model(F, H, G, D, name="lin-c", x0=x0, P0=P0)
    assert missing_hooks(model) == [] and export_refusal(model) is None
    c = c_model(model)
    p = model.default_params()
    for _ in range(100):
        x, u, dt = rng.normal(size=n) * 10, rng.normal(size=nu), 0.01
        out, z, J, Hm = np.empty(n), np.empty(m), np.empty((n, n)), np.empty((m, n))
        model.f(x, u, p, dt, out)
        model.h(x, u, p, z)
        model.F(x, u, p, dt, J)
        model.H(x, u, p, Hm)
        assert rel_err(c.f(x, u, p, dt), out) <= TOL
        assert rel_err(c.h(x, u, p), z) <= TOL
        assert rel_err(c.F(x, u, p, dt), J) <= TOL
        assert rel_err(c.H(x, u, p), Hm) <= TOL
    px0, pP0 = model.initial_state(np.zeros(m), np.ones(m), p)  # type: ignore[misc]
    cx0, cP0 = c.prior(np.zeros(m), np.ones(m), p)
    np.testing.assert_array_equal(cx0, px0)  # literals read back exactly
    np.testing.assert_array_equal(cP0, pP0)
    # without a prior a linear model is still a linear model, but the export refuses it
    bare = linear_model(F, H, name="lin-bare")
    assert bare.initial_state is None and "kf_model_prior" in missing_hooks(bare)
    assert "no prior rule" in (export_refusal(bare) or "")
    with pytest.raises(ValueError, match="both x0 and P0"):
        linear_model(F, H, x0=x0)


@needs_cc
def test_linear_model_without_inputs_compiles(c_model: Callable[..., CModel]) -> None:
    """No inputs (KF_NU = 0) and float: the loops over the inputs still compile warning-free."""
    model = linear_model([[0.9]], [[2.0]], name="lin-scalar", x0=[1.0], P0=[0.5])
    c = c_model(model, "float")
    assert c.f(np.array([2.0]), np.zeros(0), model.default_params(), 1.0)[0] == pytest.approx(1.8)


# ------------------------------------------------------------------ the single-track family --


def _single_track_models() -> list[StateSpaceModel]:
    from kftune.models import SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES

    return [SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES]


def _bundled_rows(n_states: int, every: int = 4) -> Iterator[tuple[np.ndarray, ...]]:
    """(x, u, z, dt) rows of every manoeuvre of the bundled dataset, every ``every``-th
    sample: x from the measured Vx and r and the reference sideslip, once as it is and once
    perturbed (as a sigma point is, and further, into the Dugoff saturation), random biases."""
    from kftune.data import default_dataset

    rng = np.random.default_rng(11)
    for man in default_dataset().manoeuvres:
        for k in range(0, man.n, every):
            vx, r = float(man.z[k, 0]), float(man.z[k, 2])
            x = np.array([vx, np.tan(man.beta_ref[k]) * vx, r])
            spread = rng.normal(size=3) * np.array([0.5, 0.3 * vx, 0.3])
            for state in (x, x + spread):
                full = np.concatenate([state, rng.normal(size=n_states - 3) * 0.3])
                yield full, man.u[k].astype(float), man.z[k].astype(float), man.dt


def _edge_rows(n_states: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(x, u) where the tyre formulas switch branch: Vx = 0 (tan α_r infinite), a zero
    denominator of tan α_f, 0/0, no front load (strong braking), huge slip, δ = 0."""
    rows = [
        ([0.0, 0.5, 0.1], [0.05, 0.0]),
        ([0.0, 0.0, 0.0], [0.05, 0.0]),
        ([0.0, 0.0, 0.0], [0.0, 0.0]),
        ([10.0, 0.0, 0.0], [0.0, 0.0]),
        ([10.0, 8.0, -1.0], [0.3, -2.0]),
        ([20.0, -15.0, 2.0], [-0.4, 3.0]),
        ([15.0, 1.0, 0.3], [0.1, -60.0]),  # Fz_f <= 0: a lifted front axle
        ([-5.0, 1.0, 0.3], [0.1, 1.0]),
    ]
    # Vx + y_f·tan δ = 0 with y_f = Vy + a·r: δ = 0.5, r = 0, Vy = −Vx/tan δ
    t = np.tan(0.5)
    rows.append(([2.0, -2.0 / t, 0.0], [0.5, 0.0]))
    out = []
    for x, u in rows:
        out.append((np.array(x + [0.1] * (n_states - 3)), np.array(u)))
    return out


def _compare_row(c: CModel, model: StateSpaceModel, x: np.ndarray, u: np.ndarray,
                 z: np.ndarray, p: np.ndarray, dt: float, tol: float) -> None:  # fmt: skip
    """Every hook of one row, C against Python, within ``tol`` normwise relative."""
    n, m = model.n_states, model.n_measurements
    w = np.empty(model.prepared_size)
    model.prepare(u, p, w)  # type: ignore[misc]
    assert rel_err(c.prepare(u, p), w) <= tol, ("prepare", u)
    got = {
        "f": (c.f(x, w, p, dt), np.empty(n), lambda o: model.f(x, w, p, dt, o)),
        "h": (c.h(x, w, p), np.empty(m), lambda o: model.h(x, w, p, o)),
        "F": (c.F(x, w, p, dt), np.empty((n, n)), lambda o: model.F(x, w, p, dt, o)),  # type: ignore[misc]
        "H": (c.H(x, w, p), np.empty((m, n)), lambda o: model.H(x, w, p, o)),  # type: ignore[misc]
    }
    for name, (cval, out, call) in got.items():
        call(out)
        finite = np.isfinite(out)
        assert np.array_equal(finite, np.isfinite(cval)), (name, x, u)
        assert rel_err(cval[finite], out[finite]) <= tol, (name, x, u, cval, out)
    same_check(c, model, x, z, w, p)
    assert rel_err(c.outputs(x), python_outputs(model, x)) <= tol


def same_check(
    c: CModel, model: StateSpaceModel, x: np.ndarray, z: np.ndarray, w: np.ndarray, p: np.ndarray
) -> tuple[int, list[bool]]:
    """check's stop cause, C and Python the same, and (cause 0) the same held flags."""
    py_held = np.zeros(len(model.held_causes), dtype=np.bool_)
    cause = model.check(x, z, w, p, py_held)  # type: ignore[misc]
    c_cause, c_held = c.check(x, z, w, p)
    assert c_cause == cause, (x, z)
    if cause == 0:
        assert c_held.tolist() == py_held.astype(int).tolist(), (x, z)
    return int(cause), py_held.tolist()


@needs_cc
@pytest.mark.parametrize("model", _single_track_models(), ids=lambda m: m.name)
@pytest.mark.slow
def test_single_track_c_matches_python_on_the_bundled_data(
    model: StateSpaceModel, c_model: Callable[..., CModel]
) -> None:
    """prepare, f, h, F, H, check and outputs on the bundled set's manoeuvres (every 4th
    sample, each as measured and perturbed) and at the tyre formulas' edges, and the prior."""
    from kftune.data import default_dataset

    assert model.c_code == builtin_c_code("single_track") and missing_hooks(model) == []
    c = c_model(model)
    data = default_dataset()
    p = model.params_vector(data.vehicle)
    rows = 0
    for x, u, z, dt in _bundled_rows(model.n_states):
        _compare_row(c, model, x, u, z, p, dt, TOL)
        rows += 1
    assert rows > 10_000
    for x, u in _edge_rows(model.n_states):
        _compare_row(c, model, x, u, np.array([x[0] or 1.0, 0.0, 0.0]), p, 0.01, TOL)
    for man in data.manoeuvres[:5]:
        r = np.asarray(data.r_default, float)
        x0, P0 = model.initial_state(man.z[0], r, p)  # type: ignore[misc]
        cx0, cP0 = c.prior(man.z[0], r, p)
        assert rel_err(cx0, x0) <= TOL and rel_err(cP0, P0) <= TOL


@needs_cc
@pytest.mark.parametrize("model", _single_track_models(), ids=lambda m: m.name)
def test_single_track_c_check_at_and_beyond_the_runaway_bounds(
    model: StateSpaceModel, c_model: Callable[..., CModel]
) -> None:
    """The stop causes and held flags of check, C against Python, exactly at each bound
    and one rounding either side: |β| at 60° and at 0.8 rad, |Vx − z_Vx| at 50 % of z_Vx,
    Vx at 0, NaN."""
    from kftune.models._runaway import _TAN_MAX_SIDESLIP, _TAN_RUNAWAY_BETA

    c = c_model(model)
    p = model.default_params()
    w = np.empty(6)
    model.prepare(np.array([0.02, 0.5]), p, w)  # type: ignore[misc]
    vx = 20.0
    causes = set()
    for vy0 in (_TAN_RUNAWAY_BETA * vx, _TAN_MAX_SIDESLIP * vx, 0.0):
        for vy in (np.nextafter(vy0, 0), vy0, np.nextafter(vy0, np.inf)):
            for z_vx in (vx / 1.5, vx / 0.5, vx * 2.0, np.nextafter(vx * 2.0, 0), 40.0001):
                for sign in (1.0, -1.0):
                    for x_vx in (vx, 0.0, -0.0, -1.0, np.nan):
                        x = np.array([x_vx, sign * vy, 0.1] + [0.0] * (model.n_states - 3))
                        z = np.array([z_vx, 0.0, 0.1])
                        cause, held = same_check(c, model, x, z, w, p)
                        causes.add(("held", *held) if cause == 0 else cause)
    assert {2, 3} <= causes  # reverse, sideslip at once
    assert {("held", True, False), ("held", False, True), ("held", True, True)} <= causes


# ------------------------------------------------------------------- a model of one's own --

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "linear_bicycle.py"


@needs_cc
@pytest.mark.slow
def test_example_model_c_matches_its_python(c_model: Callable[..., CModel]) -> None:
    """examples/linear_bicycle.c against linear_bicycle.py on the bundled data."""
    from kftune.data import default_dataset
    from kftune.models.user import load_model

    model = load_model(str(EXAMPLE))
    assert model.c_code == EXAMPLE.with_suffix(".c").read_text()
    assert missing_hooks(model) == [] and export_refusal(model) is None
    c = c_model(model)
    data = default_dataset()
    p = model.default_params()
    rows = 0
    for x, u, _, dt in _bundled_rows(3, every=8):
        x = np.array([max(x[0], 1.0), x[1], x[2]])
        out, zz = np.empty(3), np.empty(3)
        model.f(x, u, p, dt, out)
        model.h(x, u, p, zz)
        assert rel_err(c.f(x, u, p, dt), out) <= TOL, (x, u)
        assert rel_err(c.h(x, u, p), zz) <= TOL, (x, u)
        assert rel_err(c.outputs(x), python_outputs(model, x)) <= TOL
        rows += 1
    assert rows > 5_000
    r = np.asarray(data.r_default, float)
    z0 = data.manoeuvres[0].z[0]
    x0, P0 = model.initial_state(z0, r, p)  # type: ignore[misc]
    cx0, cP0 = c.prior(z0, r, p)
    assert rel_err(cx0, x0) <= TOL and rel_err(cP0, P0) <= TOL


# --------------------------------------------------------------------- single precision --

#: Normwise relative bound of a float model hook against the double Python one: float's
#: unit roundoff is 6e-8, and an RK4 step or a Jacobian chains some hundred roundings;
#: the bound leaves a wide margin over what the bundled rows show (a few 1e-7).
FLOAT_TOL = 1e-5


def _exportable_models() -> list[StateSpaceModel]:
    from kftune.models import CTRV
    from kftune.models.user import load_model

    lin = linear_model(
        np.eye(2), [[1.0, 0.0]], G=[[0.1], [0.2]], name="lin-f", x0=[0, 0], P0=[1, 1]
    )
    return [*_single_track_models(), CTRV, lin, load_model(str(EXAMPLE))]


@needs_cc
@pytest.mark.parametrize("model", _exportable_models(), ids=lambda m: m.name)
def test_float_precision_compiles_and_stays_near(
    model: StateSpaceModel, c_model: Callable[..., CModel]
) -> None:
    """Each model's C compiles with kf_real = float under -Werror, and its f and h (and
    Jacobians) stay within FLOAT_TOL of the double Python on the bundled rows."""
    c = c_model(model, "float")
    if model.n_inputs != 2:  # ctrv, the linear model: a few states of moderate size
        rng = np.random.default_rng(2)
        p, w = model.default_params(), np.zeros(model.n_inputs)
        for _ in range(200):
            x = rng.normal(size=model.n_states) * 3
            out = np.empty(model.n_states)
            model.f(x, w, p, 0.01, out)
            assert rel_err(c.f(x, w, p, 0.01), out) <= FLOAT_TOL
        return
    from kftune.data import default_dataset

    p = (
        model.params_vector(default_dataset().vehicle)
        if model.needs_vehicle
        else model.default_params()
    )
    worst = 0.0
    for x, u, _, dt in _bundled_rows(model.n_states, every=16):
        x[0] = max(x[0], 1.0)
        w = u
        if model.prepare is not None:
            w = np.empty(model.prepared_size)
            model.prepare(u, p, w)
        out, z = np.empty(model.n_states), np.empty(model.n_measurements)
        model.f(x, w, p, dt, out)
        model.h(x, w, p, z)
        worst = max(worst, rel_err(c.f(x, w, p, dt), out), rel_err(c.h(x, w, p), z))
        if model.F is not None:
            J = np.empty((model.n_states, model.n_states))
            model.F(x, w, p, dt, J)
            worst = max(worst, rel_err(c.F(x, w, p, dt), J))
    assert 0 < worst <= FLOAT_TOL


# --------------------------------------------------------------------- sanitizers --

#: A driver that reads p, then rows of x, u (raw), z and dt, and prints every hook's
#: result (the order of :func:`python_row`) in full precision.
_DRIVER = r"""
#include <stdio.h>
#include "kftune_model.h"

static int read_n(kf_real *v, int n) {
    int i; double d;
    for (i = 0; i < n; ++i) { if (scanf("%lf", &d) != 1) return 0; v[i] = (kf_real)d; }
    return 1;
}
static void put(const kf_real *v, int n) {
    int i;
    for (i = 0; i < n; ++i) printf("%.17g ", (double)v[i]);
}
int main(void) {
    kf_real p[KF_NP_ARR], x[KF_N], u[KF_NU_ARR], z[KF_M], dt, r[KF_M];
    kf_real w[KF_NW_ARR], out[KF_N * KF_N], y[KF_NOUT_ARR];
    int i, held[KF_NHELD_ARR];
    if (!read_n(p, KF_NP)) return 2;
    for (i = 0; i < KF_M; ++i) r[i] = 0.01 * (i + 1);
    while (read_n(x, KF_N) && read_n(u, KF_NU) && read_n(z, KF_M) && read_n(&dt, 1)) {
#if KF_HAS_PREPARE
        kf_model_prepare(u, p, w); put(w, KF_NW);
#else
        for (i = 0; i < KF_NW; ++i) w[i] = u[i];
#endif
        kf_model_f(x, w, p, dt, out); put(out, KF_N);
        kf_model_h(x, w, p, out); put(out, KF_M);
#if KF_HAS_F_JACOBIAN
        kf_model_F(x, w, p, dt, out); put(out, KF_N * KF_N);
#endif
#if KF_HAS_H_JACOBIAN
        kf_model_H(x, w, p, out); put(out, KF_M * KF_N);
#endif
#if KF_HAS_CHECK
        for (i = 0; i < KF_NHELD; ++i) held[i] = 0;
        printf("%d ", kf_model_check(x, z, w, p, held));
        for (i = 0; i < KF_NHELD; ++i) printf("%d ", held[i]);
#else
        (void)held;
#endif
        kf_model_outputs(x, y); put(y, KF_NOUT);
        kf_model_prior(z, r, p, x, out); put(x, KF_N); put(out, KF_N * KF_N);
        printf("\n");
    }
    return 0;
}
"""


def python_row(model: StateSpaceModel, x: np.ndarray, u: np.ndarray, z: np.ndarray,
               p: np.ndarray, dt: float) -> np.ndarray:  # fmt: skip
    """Every Python hook of one row, flat, in the order the driver prints."""
    n, m = model.n_states, model.n_measurements
    parts = []
    w = u
    if model.prepare is not None:
        w = np.empty(model.prepared_size)
        model.prepare(u, p, w)
        parts.append(w)
    for hook, shape, args in (("f", (n,), (dt,)), ("h", (m,), ()), ("F", (n, n), (dt,)),
                              ("H", (m, n), ())):  # fmt: skip
        fn = getattr(model, hook)
        if fn is not None:
            out = np.empty(shape)
            fn(x, w, p, *args, out)
            parts.append(out.ravel())
    if model.check is not None:
        held = np.zeros(len(model.held_causes), dtype=np.bool_)
        cause = model.check(x, z, w, p, held)
        parts.append(np.array([cause, *held.astype(float)]))
    parts.append(python_outputs(model, x))
    x0, P0 = model.initial_state(z, 0.01 * np.arange(1, m + 1), p)  # type: ignore[misc]
    parts += [x0, P0.ravel()]
    return np.concatenate(parts)


def _sanitizers_work(folder: Path) -> bool:
    src = folder / "probe.c"
    src.write_text("int main(void) { return 0; }\n")
    exe = folder / "probe"
    flags = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    made = subprocess.run([CC, *flags, str(src), "-o", str(exe)], capture_output=True, check=False)
    return made.returncode == 0 and subprocess.run([str(exe)], check=False).returncode == 0


@needs_cc
@pytest.mark.parametrize("model", _exportable_models(), ids=lambda m: m.name)
def test_model_c_under_sanitizers(model: StateSpaceModel, tmp_path: Path) -> None:
    """Each model's C once with -fsanitize=address,undefined (any finding aborts), through
    a driver on bundled rows, its output against the Python hooks."""
    if not _sanitizers_work(tmp_path):
        pytest.skip("the C toolchain has no working -fsanitize=address,undefined")
    (tmp_path / "kftune_model.h").write_text(model_header(model))
    (tmp_path / "kftune_model.c").write_text(model.c_code or "")
    (tmp_path / "driver.c").write_text(_DRIVER)
    exe = tmp_path / "driver"
    flags = [*CFLAGS[:-2], "-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    files = [str(tmp_path / "kftune_model.c"), str(tmp_path / "driver.c")]
    made = subprocess.run([CC, *flags, "-I", str(tmp_path), *files, "-o", str(exe), "-lm"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    assert made.returncode == 0, made.stderr
    p = model.default_params()
    rows = []
    if model.n_inputs == 2:
        for x, u, z, dt in _bundled_rows(model.n_states, every=200):
            x[0] = max(x[0], 1.0)
            rows.append((x, u, z, dt))
        for x, u in _edge_rows(model.n_states)[: 5 if model.prepare is not None else 0]:
            rows.append((x, u, np.array([1.0, 0.0, 0.0]), 0.01))
    else:
        rng = np.random.default_rng(9)
        for _ in range(50):
            x, u = rng.normal(size=model.n_states) * 5, rng.normal(size=model.n_inputs)
            rows.append((x, u, rng.normal(size=model.n_measurements), 0.05))
    text = " ".join(map(repr, p.tolist())) + "\n"
    text += "\n".join(" ".join(repr(float(v)) for v in np.concatenate([x, u, z, [dt]]))
                      for x, u, z, dt in rows)  # fmt: skip
    ran = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=False)
    assert ran.returncode == 0, ran.stderr[-3000:]
    lines = ran.stdout.splitlines()
    assert len(lines) == len(rows)
    for line, (x, u, z, dt) in zip(lines, rows, strict=True):
        got = np.array([float(v) for v in line.split()])
        want = python_row(model, x, u, z, p, dt)
        finite = np.isfinite(want)
        assert got.shape == want.shape and np.array_equal(finite, np.isfinite(got))
        assert rel_err(got[finite], want[finite]) <= TOL, (x, u)
