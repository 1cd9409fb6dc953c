"""Property-based runs of the public API on malformed and extreme input.

Every call must either return finite output (with its flags) or raise a named
:class:`~safestab.errors.SafeStabError`; a raw ``TypeError``, ``KeyError``, ``IndexError`` or a
silent NaN fails. Arguments are drawn from well-formed values and from their corruptions:
other shapes, bool, complex, strings, ``None``, ragged lists, NaN and inf, and magnitudes near
the limits of float64.

The default run draws ``SAFESTAB_PROPERTY_EXAMPLES`` examples per entry point (40); the
documented property run (docs/getting-started.md, "Tests") sets it to 1000:

    SAFESTAB_PROPERTY_EXAMPLES=1000 bash scripts/run-tests.sh tests/test_properties.py
"""

from __future__ import annotations

import functools
import os
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import safestab as ss
from safestab import learning
from safestab.errors import SafeStabError, SafeStabWarning

EXAMPLES = int(os.environ.get("SAFESTAB_PROPERTY_EXAMPLES", "40"))
run = settings(max_examples=EXAMPLES)

FLOATS = st.one_of(
    st.floats(-10.0, 10.0, allow_subnormal=False),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 1e300, -1e300, 1.7e308, np.nan, np.inf, -np.inf]),
)


@st.composite
def arrays(draw: Any, shape: tuple[int, ...]) -> Any:
    """A float array of ``shape``, or one of its corruptions."""
    kind = draw(
        st.sampled_from(
            ["good"] * 6
            + ["shape", "scalar", "bool", "complex", "string", "none", "ragged", "list"]
        )
    )
    size = int(np.prod(shape, dtype=int))
    values = np.array(draw(st.lists(FLOATS, min_size=size, max_size=size)), float).reshape(shape)
    if kind == "good":
        return values
    if kind == "shape":
        other = tuple(s + draw(st.integers(1, 2)) for s in shape) or (2,)
        return np.zeros(other)
    if kind == "scalar":
        return float(values.reshape(-1)[0]) if size else 1.0
    if kind == "bool":
        return values > 0
    if kind == "complex":
        return values + 1j
    if kind == "string":
        return values.astype(str)
    if kind == "none":
        return None
    if kind == "ragged":
        return [[1.0, 2.0], [3.0]]
    return values.tolist()


@st.composite
def params(draw: Any) -> dict[str, Any]:
    """kappa, rho, phi, varphi: mostly valid, sometimes negative, non-finite or not a number."""
    bad = st.sampled_from([-1.0, np.nan, np.inf, "1", None, True, [1.0, 2.0], 1 + 1j])
    good = st.floats(0.0, 10.0, allow_subnormal=False)
    return {k: draw(st.one_of(good, good, good, bad)) for k in ("kappa", "rho", "phi", "varphi")}


def _finite(tree: Any) -> bool:
    """Every float leaf finite, except a controller's limits, which may be infinite on their
    own side (no bound there: u_min = -inf, u_max = +inf), never NaN."""
    if isinstance(tree, ss.Controller) and tree.u_min is not None:
        lo, hi = np.asarray(tree.u_min), np.asarray(tree.u_max)
        if np.any(np.isnan(lo) | np.isnan(hi) | (lo == np.inf) | (hi == -np.inf)):
            return False
        rest = {k: v for k, v in tree.tunables().items() if k not in ("u_min", "u_max")}
        return _finite(rest)
    leaves = jax.tree_util.tree_leaves(tree)
    return all(
        bool(np.all(np.isfinite(np.asarray(leaf))))
        for leaf in leaves
        if np.asarray(leaf).dtype.kind == "f"
    )


def _outcome(fn: Any, *args: Any, flagged_nan: bool = False, **kwargs: Any) -> Any:
    """Call ``fn``: a named error is fine; any other exception fails; the output is returned.

    ``flagged_nan``: the output may hold NaN where its status says the step failed.
    """
    try:
        with warnings.catch_warnings():  # a warning about the data is an answer too
            warnings.simplefilter("ignore", SafeStabWarning)
            out = fn(*args, **kwargs)
    except SafeStabError:
        return None
    except Exception as exc:  # noqa: BLE001 - the point of the test
        pytest.fail(f"{fn.__name__} raised a raw {type(exc).__name__}: {exc}")
    if not flagged_nan:
        assert _finite(out), f"{fn.__name__} returned non-finite output without an error"
    return out


M = 2


@run
@given(
    arrays(()),
    arrays((M,)),
    arrays(()),
    arrays((M,)),
    params(),
    st.sampled_from([None, 5.0, -1.0, np.nan]),
)
def test_two_constraint_formulas(a, b, c, d, p, slack_weight):
    _outcome(ss.clf_cbf, a, b, c, d, **p)
    _outcome(ss.compatibility, a, b, c, d, **p)
    _outcome(ss.clf_cbf_relaxed, a, b, c, d, **p, slack_weight=slack_weight)
    res = _outcome(ss.clf_cbf, a, b, c, d, **p)
    if res is not None:
        _outcome(ss.kkt_residuals, a, b, c, d, res, **p)
        _outcome(ss.conditions_satisfied, a, b, c, d, res.u, **p)


@run
@given(arrays(()), arrays((M,)), arrays(()), arrays((M,)), params())
def test_single_formulas(a, b, c, d, p):
    _outcome(ss.clf_sontag, a, b, kappa=p["kappa"], phi=p["phi"])
    _outcome(ss.cbf_universal, c, d, rho=p["rho"], varphi=p["varphi"])
    _outcome(ss.zeta, a, b, p["phi"])


@run
@given(arrays((M,)), arrays((M,)), arrays((M,)), arrays(()), arrays((M,)), params())
def test_limits(u, lo, hi, c, d, p):
    _outcome(ss.project_box, u, lo, hi)
    first = [v[:1] if isinstance(v, np.ndarray) and v.ndim else v for v in (u, d, lo, hi)]
    _outcome(ss.saturate_safety_first, first[0], c, first[1], rho=p["rho"], varphi=p["varphi"],
             u_min=first[2], u_max=first[3])  # fmt: skip


@run
@given(
    arrays((2,)), arrays((2, M)), arrays((3,)), arrays((3, M)), params(),
    st.sampled_from([None, 3.0, -1.0]), arrays((M,)), arrays((M,)),
)  # fmt: skip
def test_several_rows(a, b, c, d, p, slack_weight, u_nom, box):
    lo = hi = None
    if isinstance(box, np.ndarray) and box.shape == (M,) and box.dtype.kind == "f":
        lo, hi = -np.abs(box) - 1.0, np.abs(box) + 1.0
    _outcome(ss.clf_cbf_multi, a, b, c, d, **p, slack_weight=slack_weight, u_min=lo, u_max=hi,
             u_nom=u_nom)  # fmt: skip


def _model():
    system = ss.ControlAffineSystem(lambda x: jnp.array([x[1], -x[0]]), lambda x: jnp.eye(2), 2)
    clf = ss.CLF(lambda x: jnp.sum(x**2), lam=1.0)
    cbf = ss.CBF(lambda x: 4.0 - x[0] ** 2, beta=1.0)
    return system, clf, cbf


SYSTEM, CLF_, CBF_ = _model()


@run
@given(params(), arrays((2,)), st.sampled_from([None, 2.0, -2.0, "x", np.inf]))
def test_building_controllers(p, limit, slack_weight):
    box = {}
    if isinstance(limit, np.ndarray) and limit.shape == (2,) and limit.dtype.kind == "f":
        box = {"u_min": -np.abs(limit) - 0.5, "u_max": np.abs(limit) + 0.5}
    _outcome(ss.UniversalController, SYSTEM, CLF_, CBF_, **p, **box, slack_weight=slack_weight)
    _outcome(ss.SafetyFilter, SYSTEM, [CBF_], clfs=[CLF_], **p, **box,
             slack_weight=slack_weight, u_nom=limit)  # fmt: skip


CTRL = ss.UniversalController(SYSTEM, CLF_, CBF_, kappa=0.5, rho=0.1, phi=0.1, varphi=0.1,
                              slack_weight=10.0)  # fmt: skip
STEPPERS = [
    CTRL,
    CTRL.replace(slack_weight=None, u_min=-1.0, u_max=1.0, saturation="project"),
    ss.SafetyFilter(SYSTEM, [CBF_], clfs=[CLF_], u_nom=lambda x: -x, u_min=-1.0, u_max=1.0),
]


@run
@given(st.sampled_from(range(len(STEPPERS))), arrays((3, 2)))
def test_controller_steps(which, x):
    out = _outcome(STEPPERS[which].step, x, flagged_nan=True)
    if out is not None:  # NaN only where the step's status says why
        bad = np.asarray(out.status) != ss.StepStatus.OK
        assert np.all(np.isfinite(np.asarray(out.u))[~bad])


@run
@given(
    arrays((2,)),
    st.sampled_from([1.0, 0.05, 0.0, -1.0, np.nan, np.inf, 1e12, "1", None]),
    st.sampled_from([0.01, 0.0, -0.01, np.nan, 2.0, 1e-12, "0.1"]),
)
def test_simulate(x0, t_final, dt):
    traj = _outcome(ss.simulate, CTRL, x0, t_final=t_final, dt=dt, flagged_nan=True)
    if traj is not None:
        bad = np.asarray(traj.status) != ss.StepStatus.OK
        assert np.all(np.isfinite(np.asarray(traj.x))[~bad])


@run
@given(arrays((4, 2)))
def test_lie_terms(x):
    terms = _outcome(ss.lie_terms, SYSTEM, CLF_, CBF_, x)
    if terms is not None:
        assert all(np.shape(t)[:1] == (4,) for t in terms)


GP_X = np.linspace(-1.0, 1.0, 24)[:, None] * np.array([[1.0, 0.5]])
GP_Y = np.column_stack([np.sin(GP_X[:, 0]), 0.1 * GP_X[:, 1]])


@functools.cache
def _fitted() -> Any:
    with warnings.catch_warnings():  # noiseless toy data: the noise at its bound is expected
        warnings.simplefilter("ignore", SafeStabWarning)
        return learning.GaussianProcessModel().fit(GP_X, GP_Y)


@settings(max_examples=EXAMPLES)
@given(arrays((24, 2)), arrays((24, 2)), arrays((3, 2)))
def test_gp_fit_and_predict(x, y, x_new):
    # corrupted data sets against a fit; corrupted queries against a fitted model
    if isinstance(x, np.ndarray) and isinstance(y, np.ndarray) and x.shape == y.shape == (24, 2):
        if x.dtype.kind == "f" and y.dtype.kind == "f" and np.all(np.isfinite(x)):
            x = GP_X  # a finite, well-spread x: the fit itself is tested elsewhere
    _outcome(learning.GaussianProcessModel().fit, x, y)
    _outcome(_fitted().predict, x_new, return_std=True)


def _plant(bad: str) -> Any:
    f = {"ok": lambda x: -x, "nan": lambda x: x * jnp.nan, "blowup": lambda x: jnp.exp(50 * x)}
    return ss.ControlAffineSystem(f[bad], lambda x: jnp.eye(2), 2)


PLANTS = {k: _plant(k) for k in ("ok", "nan", "blowup")}


@run
@given(
    st.sampled_from(list(PLANTS)),
    st.sampled_from([(-1.0, 1.0), ([0.0], [1.0]), ([-1.0, -1.0], [1.0, 1.0]), (1.0, -1.0),
                     (np.nan, 1.0), ("a", "b"), None]),
    st.sampled_from([(-1.0, 1.0), (1.0, -1.0), (np.inf, 1.0), ([0.0] * 3, [1.0] * 3)]),
    st.sampled_from([20, 0, -5, 2.5, "20", None]),
)  # fmt: skip
def test_collect_data(plant, x0, box, n_samples):
    data = _outcome(learning.collect_data, PLANTS[plant], PLANTS["ok"], x0=x0,
                    u_low=box[0], u_high=box[1], n_samples=n_samples, rate=10.0, horizon=1.0,
                    seed=0)  # fmt: skip
    if data is not None:
        assert len(data) == n_samples
