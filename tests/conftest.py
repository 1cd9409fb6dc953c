import os

import matplotlib

matplotlib.use("Agg")

# the tests fit their GPs afresh (the fit cache, safestab/learning/_fit_cache.py, is tested
# on its own folder in tests/test_fit_cache.py); set SAFESTAB_FIT_CACHE to a folder to use it
os.environ.setdefault("SAFESTAB_FIT_CACHE", "off")

import jax  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

import safestab  # noqa: E402,F401  (enables float64 before any test builds arrays)

# The library stores every compiled program (safestab/_cache.py, MIN_COMPILE_SECONDS = 0: a
# study's second run reads its ~140 small programs back), and so does the suite (about 12,000
# small programs). Storing them made a first test run slow (781 s against 454 s) only while
# JAX's size limit listed the whole folder before every write (removed 2026-11-27).

# Deterministic example generation so that CI runs are reproducible; set
# HYPOTHESIS_PROFILE=explore locally to search with fresh random examples.
settings.register_profile(
    "ci",
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile("explore", deadline=None, max_examples=5000)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_functions():
    """Drop JAX's in-memory compiled functions after each test module.

    Every compiled XLA function keeps its own memory mappings; over the whole suite they
    exceed the kernel's limit on mappings per process (``vm.max_map_count``, 65,530 here),
    after which the next compilation crashes the process. Recompiling in a later module is
    cheap: the persistent compilation cache (safestab/_cache.py) serves it from disk.
    """
    yield
    jax.clear_caches()
