"""Search spaces (:mod:`kftune.space`): validation with clear errors, and the [0, 1]^d mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftune.space import Param, Space


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "q_vy", "low": 1.0, "high": 1.0}, r"'q_vy'.*lower bound 1.0 must be below"),
        ({"name": "q_vy", "low": 2.0, "high": 1.0}, r"'q_vy'.*lower bound 2.0 must be below"),
        ({"name": "q_r", "low": float("nan"), "high": 1.0}, r"'q_r'.*low must be finite"),
        ({"name": "q_r", "low": 0.0, "high": math.inf}, r"'q_r'.*high must be finite"),
        ({"name": "q_vx", "low": 0.0, "high": 1.0, "scale": "log10"}, r"'q_vx'.*positive"),
        ({"name": "q_vx", "low": -1.0, "high": 1.0, "scale": "log10"}, r"'q_vx'.*positive"),
        ({"name": "q_vx", "low": 0.0, "high": 1.0, "scale": "ln"}, r"'q_vx'.*scale must be"),
        ({"name": "q_vx", "low": "a", "high": 1.0}, r"'q_vx'.*low must be a number"),
        ({"name": "", "low": 0.0, "high": 1.0}, r"non-empty"),
    ],
)
def test_bad_bounds_are_refused_naming_the_parameter(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Param(**kwargs)


def test_space_refuses_duplicates_and_empty():
    with pytest.raises(ValueError, match=r"duplicate parameter names.*'a'"):
        Space((Param("a", 0, 1), Param("a", 0, 2)))
    with pytest.raises(ValueError, match=r"at least one"):
        Space(())
    with pytest.raises(ValueError, match=r"'b'.*expected \(low, high\)"):
        Space.coerce({"b": (0.0,)})


def test_coerce_forms_agree():
    s1 = Space.coerce({"a": (0.0, 2.0), "q": (1e-10, 1.0, "log10")})
    s2 = Space((Param("a", 0.0, 2.0), Param("q", 1e-10, 1.0, "log10")))
    assert s1 == s2
    s3 = Space.coerce([(0.0, 2.0), (1e-10, 1.0, "log10")])
    assert s3.names == ("x0", "x1")
    assert Space.from_dict(s1.to_dict()) == s1


def test_log10_mapping_values():
    s = Space.coerce({"q": (1e-10, 1.0, "log10"), "a": (-5.0, 10.0)})
    # Known points: 1e-5 is mid-range in log10 over [1e-10, 1]; -5 → 0, 10 → 1.
    np.testing.assert_allclose(s.to_unit([1e-5, -5.0]), [0.5, 0.0])
    np.testing.assert_allclose(s.to_unit([1.0, 10.0]), [1.0, 1.0])
    np.testing.assert_allclose(s.from_unit([0.3, 0.2]), [1e-7, -2.0], rtol=1e-12)
    np.testing.assert_allclose(s.centre(), [1e-5, 2.5], rtol=1e-12)
    # Ends map exactly onto the bounds (no 10**x round-off outside the box).
    assert s.from_unit([1.0, 1.0])[0] <= 1.0
    assert s.from_unit([0.0, 0.0])[0] >= 1e-10


def test_multiplicative_change_is_additive_on_log_scale():
    s = Space.coerce({"q": (1e-10, 1.0, "log10")})
    u1 = s.to_unit([1e-4])[0]
    u2 = s.to_unit([1.15e-4])[0]
    assert u2 - u1 == pytest.approx(math.log10(1.15) / 10.0, rel=1e-12)


def test_shape_errors_name_the_parameters():
    s = Space.coerce({"a": (0, 1), "b": (0, 1)})
    with pytest.raises(ValueError, match=r"shape \(2,\).*\['a', 'b'\]"):
        s.to_unit([0.1, 0.2, 0.3])


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-1e6, 1e6), st.floats(1e-3, 1e6), st.booleans(), st.floats(0.0, 1.0)),
        min_size=1,
        max_size=5,
    )
)
def test_round_trip_unit_natural(specs):
    params = []
    u = []
    tol = []  # float64 round-off of (lo + u·w − lo)/w grows like eps·|bounds|/w
    for i, (low, width, log, ui) in enumerate(specs):
        if log:
            lo = abs(low) + 1e-6
            params.append(Param(f"p{i}", lo, lo * (1 + width), "log10"))
            t_lo, t_w = abs(np.log10(lo)), np.log10(1 + width)
        else:
            params.append(Param(f"p{i}", low, low + width))
            t_lo, t_w = abs(low), width
        u.append(ui)
        tol.append(1e-13 + 8 * np.finfo(float).eps * (t_lo + t_w) / t_w)
    s = Space(tuple(params))
    x = s.from_unit(np.array(u))
    assert s.contains(x)
    assert np.all(np.abs(s.to_unit(x) - u) <= tol)


def test_top_level_exports_are_lazy():
    import subprocess
    import sys

    code = (
        "import sys, kftune; assert 'kftune.optim' not in sys.modules; "
        "from kftune import minimize, Space, OptimizeResult, EvalRecord, Param; "
        "import kftune.optim as o; assert minimize is o.minimize and Space is o.Space"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
