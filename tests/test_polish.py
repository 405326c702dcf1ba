"""Tests of toggle_id.polish: bounded least squares in the scaled (log/affine) parameterisation."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id.errors import ConfigError
from toggle_id.polish import make_scaling, polish, polish_many

T = np.linspace(0.0, 5.0, 60)
TRUTH = np.array([2.0, 0.8, 0.5])  # a, b, c of y = a·exp(-b t) + c
LOWER = np.array([0.0, 0.0, 0.0])
UPPER = np.array([10.0, 10.0, 10.0])


def model(p: np.ndarray) -> np.ndarray:
    a, b, c = p
    return a * np.exp(-b * T) + c


def model_jac(p: np.ndarray) -> np.ndarray:
    a, b, _ = p
    e = np.exp(-b * T)
    return np.column_stack([e, -a * T * e, np.ones_like(T)])


def data(sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    return model(TRUTH) + sigma * np.random.default_rng(seed).standard_normal(T.shape)


def test_converges_from_poor_start_within_bounds():
    y = data()
    seen = []

    def residual(p):
        seen.append(p.copy())
        return model(p) - y

    res = polish(residual, [0.3, 4.0, 3.0], LOWER, UPPER)
    assert res.improved and res.success
    np.testing.assert_allclose(res.x, TRUTH, rtol=1e-6)
    assert res.sse < 1e-20 and res.cost == pytest.approx(0.5 * res.sse)
    assert res.nfev == len(seen)
    pts = np.array(seen)
    assert np.all(pts >= LOWER) and np.all(pts <= UPPER)


def test_active_bound_is_respected():
    y = data()
    lower = np.array([0.0, 1.0, 0.0])  # truth b = 0.8 lies below the bound
    seen = []

    def residual(p):
        seen.append(p.copy())
        return model(p) - y

    res = polish(residual, [1.0, 3.0, 1.0], lower, UPPER)
    assert res.improved
    assert res.x[1] == pytest.approx(1.0, abs=1e-8)
    pts = np.array(seen)
    assert np.all(pts >= lower) and np.all(pts <= UPPER)


def test_nan_region_never_crashes_and_still_converges():
    y = data()

    def residual(p):
        if p[0] > 3.0:  # the "simulator" fails there (the unhindered path from this start reaches a = 5.4)
            return np.full(T.shape, np.nan)
        return model(p) - y

    res = polish(residual, [0.3, 4.0, 3.0], LOWER, UPPER)
    assert res.n_failed > 0  # the failing region was actually visited
    assert res.improved
    np.testing.assert_allclose(res.x, TRUTH, rtol=1e-6)


def test_trial_exceptions_are_failures_not_crashes():
    y = data()

    def residual(p):
        if p[2] > 0.7:  # the unhindered path from this start reaches c = 0.93
            raise FloatingPointError("overflow in simulator")
        return model(p) - y

    res = polish(residual, [2.4, 0.3, 0.1], LOWER, UPPER)
    assert np.all(np.isfinite(res.residual))
    assert res.sse < res.sse0
    assert res.n_failed > 0
    np.testing.assert_allclose(res.x, TRUTH, rtol=1e-6)


def test_non_finite_start_returns_start_unchanged():
    res = polish(lambda p: np.full(T.shape, np.nan), [1.0, 1.0, 1.0], LOWER, UPPER)
    assert not res.improved and not res.success and res.status == -2
    np.testing.assert_array_equal(res.x, [1.0, 1.0, 1.0])
    assert res.jac is None


def test_analytic_jacobian_is_chain_ruled():
    y = data(0.01)
    fd = polish(lambda p: model(p) - y, [1.0, 2.0, 1.0], LOWER, UPPER)
    an = polish(lambda p: model(p) - y, [1.0, 2.0, 1.0], LOWER, UPPER, jac_fn=model_jac)
    np.testing.assert_allclose(an.x, fd.x, rtol=1e-6)
    # Jacobian in log coordinates is dr/dx · x; back in physical units it is the analytic one.
    np.testing.assert_allclose(an.jac, model_jac(an.x) * an.x[None, :], rtol=1e-10)
    np.testing.assert_allclose(an.jac_phys(), model_jac(an.x), rtol=1e-10)
    np.testing.assert_allclose(fd.jac_phys(), model_jac(fd.x), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(an.jac_log(), model_jac(an.x) * an.x[None, :], rtol=1e-10)


def test_start_at_optimum_is_kept():
    y = data(0.02, seed=3)
    first = polish(lambda p: model(p) - y, [1.0, 1.0, 1.0], LOWER, UPPER)
    assert first.improved
    again = polish(lambda p: model(p) - y, first.x, LOWER, UPPER)
    assert not again.improved
    np.testing.assert_array_equal(again.x, first.x)
    assert again.sse == first.sse == again.sse0
    # the Jacobian is reported at the kept start
    np.testing.assert_allclose(again.jac_phys(), model_jac(first.x), rtol=1e-5, atol=1e-6)


def test_affine_parameters_may_be_negative():
    offset_true = -0.7
    y = model(TRUTH) + offset_true

    def residual(p):
        return model(p[:3]) + p[3] - y

    lo = np.array([0.0, 0.0, 0.0, -5.0])
    hi = np.array([10.0, 10.0, 10.0, 5.0])
    # c and offset are collinear; pin c by narrow bounds so the problem stays well posed
    lo[2], hi[2] = 0.5, 0.5 + 1e-9
    res = polish(residual, [1.0, 2.0, 0.5, 1.0], lo, hi)
    assert not res.scaling.log_mask[3] and res.scaling.log_mask[0]
    np.testing.assert_allclose(res.x[[0, 1, 3]], [TRUTH[0], TRUTH[1], offset_true], rtol=1e-6)


def test_polish_many_returns_best_and_keeps_start_without_improvement():
    y = data(0.02, seed=5)
    opt = polish(lambda p: model(p) - y, [1.0, 1.0, 1.0], LOWER, UPPER).x
    starts = np.array([[5.0, 5.0, 5.0], opt, [5.0, 5.0, 5.0]])
    best = polish_many(lambda p: model(p) - y, starts, LOWER, UPPER, max_nfev=1)
    assert not best.improved and best.start_index == 1
    np.testing.assert_array_equal(best.x, opt)
    best = polish_many(lambda p: model(p) - y, np.array([[0.1, 6.0, 6.0], [1.5, 1.0, 0.4]]), LOWER, UPPER)
    assert best.improved
    np.testing.assert_allclose(best.x, opt, rtol=1e-5)


def test_scaling_log_floor_and_roundtrip():
    sc = make_scaling([2.0, 3.0, 0.0], [0.0, 1.0, -1.0], [10.0, 10.0, 1.0])
    assert sc.log_mask.tolist() == [True, True, False]
    assert sc.lower[0] == pytest.approx(2e-6) and sc.lower[1] == 1.0
    np.testing.assert_allclose(sc.lower_u[:2], np.log([2e-6, 1.0]))
    x = np.array([0.5, 7.0, 0.25])
    np.testing.assert_allclose(sc.to_x(sc.to_u(x)), x, rtol=1e-14)
    assert sc.to_u(x)[2] == pytest.approx(0.625)  # (0.25 + 1) / 2


@pytest.mark.parametrize("kwargs, msg", [
    (dict(x0=[20.0, 1.0, 1.0]), "outside"),
    (dict(lower=[1.0, 0.0, 0.0], upper=[1.0, 1.0, 1.0], x0=[1.0, 0.5, 0.5]), "lower < upper"),
    (dict(x0=[1.0, 1.0, 1.0], log_mask=[True, True]), "log_mask"),
    (dict(x0=[0.0, 1.0, 1.0], log_mask=[True, True, True]), "x0 > 0"),
    (dict(x0=[1.0, np.nan, 1.0]), "finite"),
])
def test_bad_input_raises_config_error(kwargs, msg):
    args = dict(x0=[1.0, 1.0, 1.0], lower=LOWER, upper=UPPER)
    args.update(kwargs)
    x0 = args.pop("x0")
    with pytest.raises(ConfigError, match=msg):
        polish(lambda p: model(p) - data(), x0, args.pop("lower"), args.pop("upper"), **args)


def test_one_blas_thread_inside_the_polish_only_and_the_same_result():
    """scipy iterates with one BLAS thread (the tall, thin SVDs of its steps); the pool is restored afterwards and
    the result is that of the pool as it is."""
    from conftest import blas_threads

    before = blas_threads()
    inside = []

    def residual(p):
        inside.append(blas_threads())
        return model(p) - data(0.01)

    one = polish(residual, [0.3, 4.0, 3.0], LOWER, UPPER, jac_fn=model_jac)
    # the start is evaluated before scipy runs; every call from scipy's iterations sees one thread
    assert len(inside) > 1 and all(all(n == 1 for n in seen) for seen in inside[1:])
    assert blas_threads() == before
    pool = polish(lambda p: model(p) - data(0.01), [0.3, 4.0, 3.0], LOWER, UPPER, jac_fn=model_jac,
                  blas_threads=None)
    np.testing.assert_array_equal(one.x, pool.x)


def test_the_discovery_loops_run_with_one_blas_thread():
    """The toggle and EMPS loops (many small, tall least-squares problems) run under one BLAS thread; the pool is
    restored after them."""
    from conftest import blas_threads

    from toggle_id.discovery.loop import discover
    from toggle_id.emps.loop import run_emps_loop
    from toggle_id.polish import one_blas_thread

    before = blas_threads()
    assert one_blas_thread(blas_threads)() == [1] * len(before)
    assert blas_threads() == before
    for loop in (discover, run_emps_loop):
        assert loop.__code__ is one_blas_thread(len).__code__  # wrapped by it, not by another decorator


@pytest.mark.parametrize("node, needle", [({"fd_tier": "loose"}, "polish.fd_tier"), ({"n_starts": 0}, "n_starts"),
                                          ({"bogus": 1}, "bogus")])
def test_polish_settings_reject_bad_values_in_one_line(node, needle):
    from toggle_id.app.common import polish_settings

    with pytest.raises(ConfigError, match=needle):
        polish_settings({"polish": node})
    assert polish_settings({"polish": {}}).jacobian[1] == 1e-6  # the default: PRECISE at fd_rel_step
