"""A two-input example: stabilise a pendulum while keeping it inside an ellipse.

Run with ``bash scripts/run-acc.sh`` (sets up the environment) or ``python examples/quickstart.py``.
"""

import jax.numpy as jnp
import numpy as np

import safestab as ss


def main() -> None:
    system = ss.ControlAffineSystem(
        f=lambda x: jnp.array([x[1], -jnp.sin(x[0]) - 0.3 * x[1]]),
        g=lambda x: jnp.array([[0.0, 0.1], [1.0, 0.5 * x[0]]]),
        n_states=2,
        name="pendulum",
    )
    clf = ss.CLF(lambda x: 0.5 * x @ x + 0.2 * x[0] * x[1], lam=1.0)
    cbf = ss.CBF(lambda x: 1.0 - x[0] ** 2 - 0.5 * x[1] ** 2, beta=2.0)
    ctrl = ss.UniversalController(system, clf, cbf, kappa=0.5, rho=0.2, phi=1.0, varphi=0.5)
    xs = np.random.default_rng(0).uniform(-0.9, 0.9, size=(8, 2))
    out = ctrl.step(xs)
    print("state -> input (region, compatible, CBF holds)")
    for x, u, r, c, s in zip(xs, out.u, out.region, out.compatible, out.cbf_satisfied, strict=True):
        region = ss.Region(int(r)).name
        flags = f"({region}, {bool(c)}, {bool(s)})"
        print(f"  {np.round(x, 3)} -> {np.round(np.asarray(u), 4)}  {flags}")


if __name__ == "__main__":
    main()
