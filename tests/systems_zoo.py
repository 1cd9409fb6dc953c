"""Small systems used across the tests."""

import jax.numpy as jnp
import numpy as np

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


#: The three-disc scene of the filter export tests: obstacles, their radius and the goal.
DISC_OBSTACLES = np.array([[0.0, 0.0], [3.0, 0.0], [1.5, 2.0]])
DISC_RADIUS = 1.0
DISC_GOAL = np.array([6.0, 0.0])


def disc_robot():
    """A point robot (single integrator, n = m = 2) and a CBF per disc (beta = 1)."""
    system = ControlAffineSystem(lambda x: jnp.zeros(2), lambda x: jnp.eye(2), 2, name="robot")
    cbfs = [CBF(lambda x, o=o: jnp.sum((x - o) ** 2) - DISC_RADIUS**2, beta=1.0)
            for o in DISC_OBSTACLES]  # fmt: skip
    return system, cbfs


def disc_clf():
    """``|x - goal|^2`` with rate 0.2."""
    return CLF(lambda x: jnp.sum((x - DISC_GOAL) ** 2), lam=0.2)


def disc_filter():
    """The three discs, a hard CLF to the goal, |u_i| <= 1: every phase of the solver."""
    from safestab import SafetyFilter

    system, cbfs = disc_robot()
    return SafetyFilter(system, cbfs, clfs=disc_clf(), u_nom=lambda x: 0.3 * (DISC_GOAL - x),
                        u_min=-1.0, u_max=1.0)  # fmt: skip


def disc_states() -> np.ndarray:
    """220 states: spread over the scene, near the goal, and inside the discs."""
    rng = np.random.default_rng(3)
    spread = rng.uniform([-2.5, -2.5], [8.0, 4.0], (150, 2))
    near_goal = DISC_GOAL + rng.normal(scale=0.8, size=(30, 2))
    inside = DISC_OBSTACLES[rng.integers(0, 3, 40)] + rng.normal(scale=0.3, size=(40, 2))
    return np.concatenate([spread, near_goal, inside])
