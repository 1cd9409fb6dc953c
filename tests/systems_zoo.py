"""Small systems used across the tests."""

import jax.numpy as jnp

from safestab import CBF, CLF, ControlAffineSystem


def pendulum_two_inputs():
    """A damped pendulum with a second, state-dependent input channel (n = 2, m = 2)."""

    def f(x):
        return jnp.array([x[1], -jnp.sin(x[0]) - 0.3 * x[1]])

    def g(x):
        return jnp.array([[0.0, 0.1 * jnp.cos(x[1])], [1.0, 0.5 * x[0]]])

    system = ControlAffineSystem(f, g, 2, name="pendulum")
    clf = CLF(lambda x: 0.5 * x[0] ** 2 + 0.5 * x[1] ** 2 + 0.2 * x[0] * x[1], lam=1.0)
    cbf = CBF(lambda x: 1.0 - x[0] ** 2 - 0.5 * x[1] ** 2, beta=2.0)
    return system, clf, cbf


def unicycle_obstacle():
    """A unicycle-like 3-state system (x, y, heading) with speed and turn-rate inputs."""

    def f(x):
        return jnp.array([0.1 * x[1], -0.05 * x[0], 0.0])

    def g(x):
        return jnp.array([[jnp.cos(x[2]), 0.0], [jnp.sin(x[2]), 0.0], [0.0, 1.0]])

    system = ControlAffineSystem(f, g, 3, name="unicycle")
    clf = CLF(lambda x: x[0] ** 2 + x[1] ** 2 + 0.1 * jnp.sin(x[2]) ** 2, lam=0.5)
    cbf = CBF(lambda x: (x[0] - 1.0) ** 2 + (x[1] - 0.5) ** 2 - 0.25, beta=1.0)
    return system, clf, cbf


def small_stress_gp():
    """A GP of the stress preset's model error with given hyperparameters (no fit: seconds):
    200 noisy samples of omega in the preset's box. Returns (scenario, gp, rng), the rng
    ready for drawing test states."""
    import numpy as np

    from safestab.learning import Dataset, GaussianProcessModel
    from safestab.scenarios import load_scenario

    sc = load_scenario("stress")
    rng = np.random.default_rng(1)
    xd = rng.uniform(sc.x0_low, sc.x0_high, (300, 3))
    yd = np.asarray(sc.omega(xd)) + 0.01 * rng.standard_normal((300, 3))
    data = Dataset(x=xd, u=np.zeros((300, 1)), xdot=yd, y=yd, t=np.zeros(300))
    gp = GaussianProcessModel.from_hyperparameters(
        data.x[:200], data.y[:200], amplitude=np.array([0.7, 0.05, 0.05]),
        noise=np.full(3, 0.01), lengthscale=np.tile([25.0, 25.0, 250.0], (3, 1)),
    )  # fmt: skip
    return sc, gp, rng
