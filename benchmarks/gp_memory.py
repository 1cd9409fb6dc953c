"""Peak memory and time of the ACC study's data collection and GP fit at a given Q.

Backs the ``learning.n_samples`` limit of scenario files (docs/acc.md, "Scenario files").
Run one Q per process, since peak resident memory only grows::

    PYTHONPATH=src python benchmarks/gp_memory.py 10000

Prints Q, the seconds spent collecting and fitting, and the peak resident memory (Linux
``ru_maxrss``, kB).
"""

from __future__ import annotations

import resource
import sys
import time

import safestab  # noqa: F401  (float64)
from safestab.learning import GaussianProcessModel, collect_data
from safestab.scenarios import load_scenario


def main(q: int) -> None:
    sc = load_scenario("stress").replace(n_samples=q)
    span = sc.excitation_limit * sc.mass * sc.gravity / sc.input_scale
    t0 = time.perf_counter()
    data = collect_data(
        sc.system("true"), sc.system("nominal"), x0=(sc.x0_low, sc.x0_high),
        u_low=-span, u_high=span, n_samples=q, rate=sc.sample_rate,
        horizon=sc.sample_horizon, noise_std=sc.noise_std, seed=0,
    )  # fmt: skip
    t1 = time.perf_counter()
    GaussianProcessModel(kernel=sc.kernel).fit(
        data.x, data.y, hyper_subset=min(sc.hyper_subset, q), seed=0
    )
    t2 = time.perf_counter()
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"Q = {q}: collect {t1 - t0:.1f} s, GP fit {t2 - t1:.1f} s, peak RSS {peak_gb:.2f} GB")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2000)
