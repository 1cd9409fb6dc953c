import os

# Each xdist worker is one of several processes that fill the CPUs: BLAS (OpenBLAS, NumPy's,
# SciPy's and JAX's CPU LAPACK) gets one thread there, as Ray's workers and the studies give
# it (safestab.learning.batched.one_blas_thread). OpenBLAS's threads spin while they wait for
# each other on cores that another worker holds: a GP fit (test_fast's std_tol test) took 50 s
# against 6 s with one thread, both cores busy (2 CPUs, 2026-11-28). Subprocesses inherit it;
# a test that needs more threads raises the limit itself (threadpoolctl).
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import matplotlib

matplotlib.use("Agg")

# the tests fit their GPs afresh (the fit cache, safestab/learning/_fit_cache.py, is tested
# on its own folder in tests/test_fit_cache.py); set SAFESTAB_FIT_CACHE to a folder to use it
os.environ.setdefault("SAFESTAB_FIT_CACHE", "off")

import jax  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

import safestab  # noqa: E402,F401  (enables float64 before any test builds arrays)

if os.environ.get("PYTEST_XDIST_WORKER"):  # in case a plugin loaded BLAS before the above
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")

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


@pytest.fixture(scope="module")
def tools():
    """The Arm toolchain (arm-none-eabi-gcc, newlib, qemu-system-arm), or skip naming it."""
    from safestab.errors import CompilationError
    from safestab.export import embedded

    try:
        return embedded.find_toolchain(install=True)
    except CompilationError as exc:
        pytest.skip(str(exc))


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


# -- the count of XLA programs a run needs (printed at the end of the run) ----------------
# JAX's backend_compile event marks every program a process builds, compiled by XLA or
# loaded from the persistent cache (its cache_hits event marks those). A program is looked up
# in the persistent cache by its key before it is built (jax._src.compilation_cache's
# get_executable_and_time, wrapped below), so the keys looked up are the run's distinct
# programs, the same count with a cold or a warm cache. Each xdist worker counts its own and
# hands them to the controller (workeroutput), which prints the sums and the distinct count:
# the figures the compile-once work is measured by.
_PROGRAMS = {"built": 0, "loaded": 0}
_KEYS: set[str] = set()


def _count_build(event: str, duration: float, **kw) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _PROGRAMS["built"] += 1


def _count_hit(event: str, **kw) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _PROGRAMS["loaded"] += 1


def _record_keys() -> None:
    from jax._src import compilation_cache

    lookup = compilation_cache.get_executable_and_time

    sites = os.environ.get("SAFESTAB_PROGRAM_SITES")  # a file: where each program came from

    def recorded(cache_key, *args, **kwargs):
        if sites and cache_key not in _KEYS:
            _write_site(sites, cache_key)
        _KEYS.add(cache_key)
        return lookup(cache_key, *args, **kwargs)

    compilation_cache.get_executable_and_time = recorded


def _write_site(path: str, cache_key: str) -> None:
    """Append ``key<TAB>library frame<TAB>test frame`` (the innermost of each) to ``path``."""
    import traceback

    lib = test = ""
    for frame in traceback.extract_stack():
        where = f"{frame.filename.rsplit('/', 1)[-1]}:{frame.lineno}:{frame.name}"
        if "/src/safestab/" in frame.filename:
            lib = where
        elif "/tests/" in frame.filename and "conftest" not in frame.filename:
            test = where
    with open(path, "a") as out:
        out.write(f"{cache_key.rsplit('-', 1)[0]}\t{lib}\t{test}\n")


jax.monitoring.register_event_duration_secs_listener(_count_build)
jax.monitoring.register_event_listener(_count_hit)
_record_keys()


def pytest_sessionfinish(session, exitstatus):
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:  # an xdist worker: report to the controller
        workeroutput["safestab_programs"] = dict(_PROGRAMS)
        workeroutput["safestab_program_keys"] = sorted(_KEYS)


def pytest_testnodedown(node, error):
    output = getattr(node, "workeroutput", {})
    for key, value in output.get("safestab_programs", {}).items():
        _PROGRAMS[key] += value
    _KEYS.update(output.get("safestab_program_keys", ()))


def pytest_terminal_summary(terminalreporter):
    built, loaded = _PROGRAMS["built"], _PROGRAMS["loaded"]
    terminalreporter.write_line(
        f"XLA programs: {built} built, {built - loaded} compiled by XLA and {loaded} loaded "
        "from the persistent compilation cache (counted by tests/conftest.py)"
    )
    if not _KEYS:  # the persistent cache is off (SAFESTAB_COMPILATION_CACHE=off)
        return
    names: dict[str, int] = {}
    for key in _KEYS:  # "<module name>-<hash>"
        name = key.rsplit("-", 1)[0]
        names[name] = names.get(name, 0) + 1
    top = sorted(names.items(), key=lambda item: -item[1])[:6]
    terminalreporter.write_line(
        f"distinct XLA programs: {len(_KEYS)} (most: "
        + ", ".join(f"{name} {count}" for name, count in top)
        + ")"
    )
