"""The filter's QP solver, written in C, as XLA's CPU kernel of its primitive.

On the CPU, XLA runs the solver's JAX loop as a sequence of small operations, each with its
own overhead: a problem of a few hundred flops costs a hundred microseconds or more. The
primitive :data:`~safestab.formulas._dual_active_set.dual_qp_p` is therefore lowered on the
CPU to one XLA foreign-function call (``jax.ffi``) into the solver written in C
(:mod:`safestab.export._dual_qp`, the same function the C export writes), with a C++
handler that loops over a batch in C. The JAX step, the native controller and the exported
C then run the same solver. Other backends (GPU) keep the JAX implementation.

The shared object is built with the system compilers on first use, once per machine: it is
stored in ``native/`` under the compilation cache's folder (:mod:`._so_cache`) and loaded by
later processes without a compiler. Where no C or C++ compiler is found or the build fails,
a warning names why and the JAX implementation runs instead (the same answers to rounding,
slower). ``SAFESTAB_NATIVE_SOLVER=off`` chooses the JAX implementation on the CPU too.
"""

from __future__ import annotations

import os
import threading
import warnings
from pathlib import Path
from typing import Any

import jax

from ..errors import CompilationError
from ._dual_qp import c_work_sizes, source
from ._so_cache import build_key, load_or_build

__all__ = ["ENV", "TARGET", "enabled", "ensure", "failure"]

#: The environment variable that turns the native solver off (``off``, ``0``, ``false``, ``no``).
ENV = "SAFESTAB_NATIVE_SOLVER"
#: The name of the XLA custom-call target.
TARGET = "safestab_dual_qp"
_SYMBOL = "safestab_dual_qp_ffi"
_LOCK = threading.Lock()
_STATE: dict[str, Any] = {"target": None, "error": None, "lib": None}

#: Flags of the handler; the solver's C takes the native builds' flags
#: (:func:`~safestab.export.native.native_flags`: no fast-math, no contraction, so its bits
#: are those of the exported C compiled for this machine).
CXX_FLAGS = ("-std=c++17", "-O2", "-fPIC")

_HANDLER = r"""
#include <cstdint>
#include <vector>
#include "xla/ffi/api/ffi.h"
namespace ffi = xla::ffi;
extern "C" void ss_dual_qp(int n, int cols, int dim, const double *G, const double *r,
                           const double *w0, const int *use, int max_iter, const double *slack,
                           int slack_row, double add_tol, double dep_tol, double cert_tol,
                           double eps, double *work, int *iwork, double *w, double *mult,
                           int *active, int *status, int *iters, double *cond, int *certified);
static ffi::Error solve(ffi::Buffer<ffi::F64> G, ffi::Buffer<ffi::F64> r,
                        ffi::Buffer<ffi::F64> w0, ffi::Buffer<ffi::PRED> use,
                        ffi::Buffer<ffi::S32> max_iter, ffi::Buffer<ffi::F64> slack, double add,
                        double dep, double cert, double eps, int64_t slack_row,
                        ffi::ResultBuffer<ffi::F64> w, ffi::ResultBuffer<ffi::F64> mult,
                        ffi::ResultBuffer<ffi::PRED> active, ffi::ResultBuffer<ffi::S32> status,
                        ffi::ResultBuffer<ffi::S32> iters, ffi::ResultBuffer<ffi::F64> cond,
                        ffi::ResultBuffer<ffi::PRED> cert_ok)
{
    const auto dims = G.dimensions(), wdims = w0.dimensions();
    const int n = static_cast<int>(dims[dims.size() - 2]);
    const int cols = static_cast<int>(dims[dims.size() - 1]);
    const int dim = static_cast<int>(wdims[wdims.size() - 1]), k = dim - cols;
    const int64_t count = static_cast<int64_t>(max_iter.element_count());
    std::vector<double> work(WORK_REALS);
    std::vector<int> uw(n), aw(n), iwork(WORK_INTS);
    const bool *u = use.typed_data();
    bool *aout = active->typed_data(), *okout = cert_ok->typed_data();
    for (int64_t b = 0; b < count; ++b) {
        for (int i = 0; i < n; ++i) uw[i] = u[b * n + i] ? 1 : 0;
        int st = 0, it = 0, ok = 0;
        ss_dual_qp(n, cols, dim, G.typed_data() + b * n * cols, r.typed_data() + b * n,
                   w0.typed_data() + b * dim, uw.data(), max_iter.typed_data()[b],
                   slack.typed_data() + b * k, static_cast<int>(slack_row), add, dep, cert, eps,
                   work.data(), iwork.data(), w->typed_data() + b * dim,
                   mult->typed_data() + b * n, aw.data(), &st, &it, cond->typed_data() + b, &ok);
        for (int i = 0; i < n; ++i) aout[b * n + i] = aw[i] != 0;
        status->typed_data()[b] = st;
        iters->typed_data()[b] = it;
        okout[b] = ok != 0;
    }
    return ffi::Error::Success();
}
XLA_FFI_DEFINE_HANDLER_SYMBOL(
    safestab_dual_qp_ffi, solve,
    ffi::Ffi::Bind()
        .Arg<ffi::Buffer<ffi::F64>>().Arg<ffi::Buffer<ffi::F64>>().Arg<ffi::Buffer<ffi::F64>>()
        .Arg<ffi::Buffer<ffi::PRED>>().Arg<ffi::Buffer<ffi::S32>>().Arg<ffi::Buffer<ffi::F64>>()
        .Attr<double>("add").Attr<double>("dep").Attr<double>("cert").Attr<double>("eps")
        .Attr<int64_t>("slack_row")
        .Ret<ffi::Buffer<ffi::F64>>().Ret<ffi::Buffer<ffi::F64>>().Ret<ffi::Buffer<ffi::PRED>>()
        .Ret<ffi::Buffer<ffi::S32>>().Ret<ffi::Buffer<ffi::S32>>().Ret<ffi::Buffer<ffi::F64>>()
        .Ret<ffi::Buffer<ffi::PRED>>());
"""


def _sources() -> tuple[str, str]:
    """The solver's C (an exported function, not static) and the C++ handler."""
    solver = source("ss_dual_qp", "double", True, None)
    solver = "#include <math.h>\n" + solver.replace("static void ss_dual_qp(", "void ss_dual_qp(")
    reals, ints = c_work_sizes()  # C++ expressions of n and dim
    handler = _HANDLER.replace("WORK_REALS", reals).replace("WORK_INTS", ints)
    return solver, handler


def enabled() -> bool:
    """Whether the native solver is asked for (``SAFESTAB_NATIVE_SOLVER`` is not off)."""
    return os.environ.get(ENV, "on").strip().lower() not in ("off", "0", "false", "no")


def failure() -> Exception | None:
    """Why the native solver could not be built in this process (None: it was, or not tried)."""
    return _STATE["error"]


def ensure() -> str | None:
    """The registered custom-call target, built or loaded once per process; None if unavailable.

    None where :func:`enabled` is false, or where the build failed (warned once, with why;
    :func:`failure` returns it).
    """
    if not enabled():
        return None
    with _LOCK:
        if _STATE["target"] is not None or _STATE["error"] is not None:
            return _STATE["target"]
        try:
            _STATE["lib"] = _load()
        except (CompilationError, OSError, AttributeError) as exc:
            _STATE["error"] = exc
            warnings.warn(
                "the filter's native solver could not be built, so XLA runs its JAX loop on "
                f"the CPU (the same answers, slower; set {ENV}=off to choose that and silence "
                f"this): {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
                RuntimeWarning,
                stacklevel=3,
            )
            return None
        capsule = jax.ffi.pycapsule(getattr(_STATE["lib"], _SYMBOL))
        jax.ffi.register_ffi_target(TARGET, capsule, platform="cpu")
        _STATE["target"] = TARGET
        return TARGET


def _load() -> Any:
    """The shared object from the disk cache, or built and stored there."""
    from .jax_kernel import find_cxx_compiler
    from .native import find_compiler, native_flags, run_tool

    cc, cxx = find_compiler(None), find_cxx_compiler(None)
    c_flags = [*native_flags(cc), "-fPIC"]
    solver, handler = _sources()
    key = build_key([solver, handler], [cc, cxx], [*c_flags, "|", *CXX_FLAGS])

    def build(folder: Path) -> Path:
        (folder / "solver.c").write_text(solver)
        (folder / "handler.cc").write_text(handler)
        run_tool([cc, *c_flags, "-c", "solver.c", "-o", "solver.o"], folder)
        lib_path = folder / "libsafestab_solver.so"
        run_tool(
            [cxx, *CXX_FLAGS, "-shared", f"-I{jax.ffi.include_dir()}", "handler.cc",
             "solver.o", "-lm", "-o", str(lib_path)],
            folder,
        )  # fmt: skip
        return lib_path

    return load_or_build(key, _SYMBOL, build)
