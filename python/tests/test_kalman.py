"""spintune.KalmanGradient and spintune.newton_step against the Rust core
(the `spintune replay` CLI runs the core filter) and against the paper's
equations written out in numpy."""

import json

import numpy as np
import pytest

import spintune


def generated_sequence(rng, n, steps, gate_outliers=False):
    """A recorded-like sequence: voltages (mV), values and variances of one parameter."""
    true_g = rng.normal(0.0, 2.0, n)
    v = rng.normal(-700.0, 50.0, n)
    p = 40.0
    out = []
    for k in range(steps):
        if k > 0:
            kind = rng.integers(0, 6)
            if kind == 0:
                dv = rng.normal(0.0, 1e-8, n)  # below the filter's minimum step: skipped
            else:
                dv = rng.normal(0.0, 3.0, n)
            v = v + dv
            true_g = true_g + rng.normal(0.0, 0.05, n)  # the gradient drifts
            p = p + float(true_g @ dv)
        sigma = float(rng.uniform(0.1, 2.0))
        value = p + rng.normal(0.0, sigma)
        if gate_outliers and k > 3 and rng.integers(0, 5) == 0:
            value += 500.0  # a charge jump: the outlier gate should refuse it
        out.append({"voltages": v.tolist(), "value": float(value), "variance": sigma**2})
    return out


def replay_input(rng, n, steps, outlier_sigma):
    g0 = rng.normal(0.0, 1.0, n)
    a = rng.normal(0.0, 1.0, (n, n))
    c0 = a @ a.T + np.eye(n)
    q = np.diag(rng.uniform(0.0, 0.1, n) ** 2)
    return {
        "gates": [f"G{i}" for i in range(n)],
        "initial_gradient": g0.tolist(),
        "initial_covariance": c0.tolist(),
        "process_noise": q.tolist(),
        "outlier_sigma": outlier_sigma,
        "steps": generated_sequence(rng, n, steps, gate_outliers=outlier_sigma is not None),
    }


def python_replay(inp):
    f = spintune.KalmanGradient(
        inp["initial_gradient"],
        inp["initial_covariance"],
        np.asarray(inp["process_noise"]),
        outlier_sigma=inp["outlier_sigma"],
    )
    out, kinds = [], []
    steps = inp["steps"]
    for k in range(1, len(steps)):
        a, b = steps[k - 1], steps[k]
        dv = np.subtract(b["voltages"], a["voltages"])
        res = f.update(dv, b["value"] - a["value"], a["variance"] + b["variance"])
        kinds.append(res["kind"])
        out.append((f.gradient.copy(), f.covariance.copy()))
    return out, kinds


@pytest.mark.parametrize("seed,n,outlier_sigma", [(1, 2, None), (2, 4, None), (3, 4, 3.0), (4, 3, 5.0)])
def test_equals_rust_filter_via_replay_cli(tmp_path, run_cli, seed, n, outlier_sigma):
    rng = np.random.default_rng(seed)
    inp = replay_input(rng, n, 40, outlier_sigma)
    path = tmp_path / "recorded.json"
    path.write_text(json.dumps(inp))
    lines = [json.loads(line) for line in run_cli("replay", path).splitlines()]
    ours, kinds = python_replay(inp)
    assert len(lines) == len(ours) == 39
    for line, (g, c) in zip(lines, ours):
        # the same core code on the same inputs: bit for bit
        assert np.array_equal(np.asarray(line["gradient"]), g), line["step"]
        assert np.array_equal(np.asarray(line["covariance"]), c), line["step"]
    assert "skipped_small_step" in kinds and "updated" in kinds
    if outlier_sigma is not None:
        assert "gated" in kinds


def numpy_filter(g, c, q, steps, outlier_sigma=None, min_step_mv=1e-6):
    """The paper's equations (Teske et al. 2019, eqs. 2–4) with the core's
    Joseph-form covariance, small-step skip and outlier gate, in numpy."""
    g, c = np.array(g, float), np.array(c, float)
    c = 0.5 * (c + c.T)
    out = []
    for dv, z, dz2 in steps:
        h = np.asarray(dv, float)
        if np.linalg.norm(h) < min_step_mv or np.linalg.norm(h) == 0.0:
            out.append((g.copy(), c.copy(), "skipped_small_step"))
            continue
        s = h @ c @ h + dz2
        innovation = z - h @ g
        if outlier_sigma is not None and abs(innovation) > outlier_sigma * np.sqrt(s):
            c = c + q
            c = 0.5 * (c + c.T)
            out.append((g.copy(), c.copy(), "gated"))
            continue
        k = c @ h / s
        g = g + k * innovation
        ikh = np.eye(len(g)) - np.outer(k, h)
        c = ikh @ c @ ikh.T + np.outer(k, k) * dz2 + q
        c = 0.5 * (c + c.T)
        out.append((g.copy(), c.copy(), "updated"))
    return out


@pytest.mark.parametrize("seed,outlier_sigma", [(10, None), (11, 3.0)])
def test_equals_paper_equations_in_numpy(seed, outlier_sigma):
    rng = np.random.default_rng(seed)
    n = 4
    g0 = rng.normal(0, 1, n)
    a = rng.normal(0, 1, (n, n))
    c0 = a @ a.T + 0.5 * np.eye(n)
    sigma2 = 0.075**2
    seq = generated_sequence(rng, n, 60, gate_outliers=outlier_sigma is not None)
    steps = [
        (
            np.subtract(seq[k]["voltages"], seq[k - 1]["voltages"]),
            seq[k]["value"] - seq[k - 1]["value"],
            seq[k]["variance"] + seq[k - 1]["variance"],
        )
        for k in range(1, len(seq))
    ]
    f = spintune.KalmanGradient(g0, c0, sigma2, outlier_sigma=outlier_sigma)
    expected = numpy_filter(g0, c0, sigma2 * np.eye(n), steps, outlier_sigma)
    for (dv, z, dz2), (g, c, kind) in zip(steps, expected):
        assert f.update(dv, z, dz2)["kind"] == kind
        np.testing.assert_allclose(f.gradient, g, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(f.covariance, c, rtol=1e-9, atol=1e-12)


def test_hand_computed_example():
    # n = 2, C = diag(4, 1), g = (1, 2), Δv = (1, 1), z = 5, Δz² = 1, Q = 0.01 I
    f = spintune.KalmanGradient([1.0, 2.0], [[4.0, 0.0], [0.0, 1.0]], 0.01)
    out = f.update([1.0, 1.0], 5.0, 1.0)
    assert out == {"kind": "updated", "innovation": 2.0, "innovation_sigma": pytest.approx(6**0.5)}
    np.testing.assert_allclose(f.gradient, [1 + 8 / 6, 2 + 2 / 6], rtol=1e-14)
    np.testing.assert_allclose(
        f.covariance, [[4 - 16 / 6 + 0.01, -4 / 6], [-4 / 6, 1 - 1 / 6 + 0.01]], rtol=1e-14
    )
    assert isinstance(f.gradient, np.ndarray) and f.gradient.shape == (2,)
    assert f.covariance.shape == (2, 2)
    np.testing.assert_array_equal(f.process_noise, 0.01 * np.eye(2))
    # a scalar σ² and the matrix σ²·I are the same filter
    g = spintune.KalmanGradient([1.0, 2.0], np.diag([4.0, 1.0]), 0.01 * np.eye(2))
    g.update(np.array([1.0, 1.0]), 5.0, 1.0)
    np.testing.assert_array_equal(f.covariance, g.covariance)


def test_bad_inputs_raise_value_error_and_leave_state():
    f = spintune.KalmanGradient([1.0, 0.0], np.eye(2), 0.01)
    before = (f.gradient.copy(), f.covariance.copy())
    cases = [
        (lambda: f.update([1.0, 0.0], 1.0, -1.0), "variance"),
        (lambda: f.update([1.0, 0.0], 1.0, float("nan")), "variance"),
        (lambda: f.update([1.0, 0.0], float("nan"), 1.0), "dz"),
        (lambda: f.update([float("nan"), 0.0], 1.0, 1.0), "dv"),
        (lambda: f.update([1.0, 0.0, 0.0], 1.0, 1.0), "dv"),
        (lambda: f.update([[1.0, 0.0]], 1.0, 1.0), "dv"),
        (lambda: f.update(["a", "b"], 1.0, 1.0), "dv"),
    ]
    for call, name in cases:
        with pytest.raises(ValueError, match=name):
            call()
        np.testing.assert_array_equal(f.gradient, before[0])
        np.testing.assert_array_equal(f.covariance, before[1])
    ctor = [
        (lambda: spintune.KalmanGradient([1.0, float("nan")], np.eye(2), 0.1), "gradient"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], np.eye(3), 0.1), "covariance"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], [[1.0, 0.0], [0.0, -1.0]], 0.1), "covariance"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], [[1.0, np.inf], [0.0, 1.0]], 0.1), "covariance"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], np.eye(2), -0.1), "process_noise"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], np.eye(2), np.eye(3)), "process_noise"),
        (lambda: spintune.KalmanGradient([1.0, 2.0], np.eye(2), float("nan")), "process_noise"),
        (lambda: spintune.KalmanGradient([], np.eye(0), 0.1), "gradient"),
        (lambda: spintune.KalmanGradient([1.0], [[1.0]], 0.1, outlier_sigma=-1.0), "outlier_sigma"),
    ]
    for call, name in ctor:
        with pytest.raises(ValueError, match=name):
            call()


def test_small_step_is_skipped_and_copy_is_independent():
    f = spintune.KalmanGradient([1.0, 0.0], np.eye(2), 0.01, min_step_mv=0.01)
    g = f.copy()
    assert f.update([0.001, 0.0], 5.0, 0.0)["kind"] == "skipped_small_step"
    np.testing.assert_array_equal(f.gradient, [1.0, 0.0])
    f.update([1.0, 0.0], 5.0, 0.0)
    np.testing.assert_array_equal(g.gradient, [1.0, 0.0])


def test_newton_step_is_min_norm_and_limited():
    rng = np.random.default_rng(5)
    j = rng.normal(0, 1, (2, 4))
    d = rng.normal(0, 1, 2)
    step = spintune.newton_step(j, d, 1e9)
    np.testing.assert_allclose(step, -np.linalg.pinv(j) @ d, rtol=1e-10, atol=1e-12)
    limited = spintune.newton_step(j, d * 1e3, 10.0)
    assert np.linalg.norm(limited) == pytest.approx(10.0)
    np.testing.assert_allclose(limited / 10.0, step / np.linalg.norm(step), rtol=1e-9)
    # the docstring example: p = 2 v0, p is 1 above target
    np.testing.assert_allclose(spintune.newton_step([[2.0, 0.0]], [1.0], 10.0), [-0.5, 0.0])
    for call, name in [
        (lambda: spintune.newton_step([1.0, 2.0], [1.0], 10.0), "jacobian"),
        (lambda: spintune.newton_step([[1.0, 2.0]], [1.0, 2.0], 10.0), "residual"),
        (lambda: spintune.newton_step([[np.nan, 2.0]], [1.0], 10.0), "jacobian"),
        (lambda: spintune.newton_step([[1.0, 2.0]], [1.0], 0.0), "max_step_mv"),
        (lambda: spintune.newton_step([[1.0, 2.0]], [1.0], 10.0, rank_tolerance=-1), "rank_tolerance"),
    ]:
        with pytest.raises(ValueError, match=name):
            call()
