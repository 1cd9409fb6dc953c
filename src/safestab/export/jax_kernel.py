"""Call exported C from inside JAX: an XLA foreign-function custom call on the CPU.

:func:`jax_function` compiles an :class:`~safestab.export.ExportedC` (the C99 step that
:func:`~safestab.export.export_c` writes) together with a small C++ handler against XLA's
foreign function interface (the headers of ``jax.ffi.include_dir()``), loads it and registers
it with XLA. The result is a JAX function of states ``(..., n)`` that composes with
``jax.jit`` and ``jax.vmap`` (a batch is one loop in C, one thread) and runs the same machine
code as :class:`~safestab.export.NativeController`: one XLA custom call instead of the
hundreds of small operations XLA makes of the solver's loop. The built shared object is kept
on disk under the compilation cache's folder (:mod:`._so_cache`), so a later process loads it
instead of compiling.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from ._so_cache import build_key, load_or_build
from .exporter import ExportedC
from .native import compile_object, find_compiler, find_tool, requested_flags, run_tool

__all__ = ["jax_function", "find_cxx_compiler", "MAX_STACK_BYTES"]

#: Exported steps with more temporaries than this are refused: the custom call runs on a
#: thread of XLA's, whose stack is not ours to size (the exported code keeps its temporaries
#: on the stack; the header states how many bytes).
MAX_STACK_BYTES = 2**20

_XLA_TYPE = {"float64": "F64", "float32": "F32", "int32": "S32", "bool": "PRED", "uint8": "U8"}
_C_TYPE = {"F64": "double", "F32": "float", "S32": "int", "PRED": "unsigned char",
           "U8": "unsigned char"}  # fmt: skip
_LOCK = threading.Lock()
#: Loaded libraries by the hash of their sources (kept alive: XLA holds their handlers).
_LOADED: dict[str, tuple[Any, str]] = {}


def find_cxx_compiler(compiler: str | None = None) -> str:
    """The C++ compiler for the handler: ``compiler``, else ``$CXX``, ``c++``, ``g++``, ``clang++``.

    Raises
    ------
    CompilationError
        If none is found.
    """
    return find_tool(
        compiler, "CXX", ("c++", "g++", "clang++"),
        "no C++ compiler found (tried {tried}) for the XLA custom call; install one (on "
        "Debian or Ubuntu: apt-get install g++) or set CXX",
    )  # fmt: skip


def _handler_source(exported: ExportedC, symbol: str) -> tuple[str, list[int]]:
    """C++ of the XLA handler calling ``<name>_step_columns``; and the leaves it returns."""
    real = "double" if exported.precision == "double" else "float"
    used = [i for i, leaf in enumerate(exported.leaves) if leaf.size > 0]
    params, args, rets, ctypes_ = [], [], [], []
    for i in used:
        leaf = exported.leaves[i]
        xt = "F64" if leaf.dtype == np.float64 else _XLA_TYPE.get(leaf.dtype.name)
        if xt is None:  # pragma: no cover - the exporter only writes these dtypes
            raise ParameterError(f"output {leaf.path} has dtype {leaf.dtype}, not supported")
        if exported.precision == "float" and xt == "F64":
            xt = "F32"
        params.append(f"ffi::ResultBuffer<ffi::{xt}> r{i}")
        ctypes_.append(f"{_C_TYPE[xt]} *")
        args.append(f"reinterpret_cast<{_C_TYPE[xt]} *>(r{i}->typed_data())")
        rets.append(f".Ret<ffi::Buffer<ffi::{xt}>>()")
    xt_in = "F64" if exported.precision == "double" else "F32"
    name, n = exported.name, exported.n_states
    lines = [
        '#include "xla/ffi/api/ffi.h"',
        "namespace ffi = xla::ffi;",
        f'extern "C" int {name}_step_columns(long count, const {real} *x, '
        + ", ".join(ctypes_)
        + ");",
        f"static ffi::Error {symbol}_impl(ffi::Buffer<ffi::{xt_in}> x, {', '.join(params)}) {{",
        f"    long count = static_cast<long>(x.element_count() / {n});",
        f"    {name}_step_columns(count, x.typed_data(), {', '.join(args)});",
        "    return ffi::Error::Success();",
        "}",
        f"XLA_FFI_DEFINE_HANDLER_SYMBOL({symbol}, {symbol}_impl, ffi::Ffi::Bind()"
        f".Arg<ffi::Buffer<ffi::{xt_in}>>(){''.join(rets)});",
        "",
    ]
    return "\n".join(lines), used


#: The C++ compiler's flags for the handler (and the link with the step's object).
HANDLER_FLAGS = ("-std=c++17", "-O2", "-fPIC", "-shared")


def _build(exported: ExportedC, cc: str, cxx: str, march_native: bool) -> tuple[Any, str, list]:
    """Load the step with its handler, built or from the disk cache; register it with XLA.

    Once per process and build. The shared object is looked up in :mod:`._so_cache` first
    (no compiler is run then), else compiled, linked and stored there.
    """
    ident = exported.source + cc + cxx + str(march_native)
    digest = hashlib.sha1(ident.encode()).hexdigest()[:16]
    symbol = f"safestab_ffi_{exported.name}_{digest}"
    handler, used = _handler_source(exported, symbol)
    with _LOCK:
        if digest in _LOADED:
            return _LOADED[digest][0], symbol, used
        key = build_key(
            [exported.source, exported.header, handler], [cc, cxx],
            [*requested_flags(march_native=march_native), "|", *HANDLER_FLAGS],
        )  # fmt: skip

        def build(folder: Path) -> Path:
            exported.write(folder)
            obj = compile_object(exported, cc, folder, march_native=march_native)
            src = folder / "handler.cc"
            src.write_text(handler)
            lib_path = folder / f"lib{symbol}.so"
            run_tool(
                [cxx, *HANDLER_FLAGS, f"-I{jax.ffi.include_dir()}", str(src), str(obj),
                 "-lm", "-o", str(lib_path)],
                folder,
            )  # fmt: skip
            return lib_path

        lib = load_or_build(key, symbol, build)
        jax.ffi.register_ffi_target(symbol, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
        _LOADED[digest] = (lib, symbol)
    return lib, symbol, used


def jax_function(
    exported: ExportedC,
    *,
    compiler: str | None = None,
    cxx_compiler: str | None = None,
    march_native: bool = True,
) -> Callable[[jax.Array], Any]:
    """A JAX function running exported C as one XLA custom call on the CPU.

    Parameters
    ----------
    exported : ExportedC
        The exported step (``export_c(controller)`` or ``export_function(fn, n, name)``), in
        double precision.
    compiler, cxx_compiler : str, optional
        The C compiler (default ``$CC`` or ``cc``) and the C++ compiler of the handler
        (default ``$CXX`` or ``c++``).
    march_native : bool
        Compile for this machine's CPU (default True; results are unchanged).

    Returns
    -------
    callable
        ``fn(x)`` for states ``x`` of shape (..., n), float64, returning the exported
        function's output pytree with leaves of shape (..., *leaf_shape), as the JAX function
        that was exported. Composes with ``jax.jit`` and ``jax.vmap`` (a batch is one loop in
        C). It is not differentiable by itself: see :func:`safestab.export.native_step`
        for a filter with derivatives.

    Raises
    ------
    CompilationError
        If a compiler is missing or rejects the code.
    ParameterError
        If ``exported`` is in float precision or needs more than :data:`MAX_STACK_BYTES` of
        stack.

    Notes
    -----
    The built code is stored in ``native/`` under the compilation cache's folder
    (:func:`safestab.compilation_cache_dir`), keyed by a SHA-256 of the sources, the
    compilers, their flags, JAX's and jaxlib's versions and the CPU; a later process loads it
    without running a compiler. ``SAFESTAB_COMPILATION_CACHE=off`` builds afresh each time.
    """
    if not isinstance(exported, ExportedC):
        raise ParameterError(f"exported must be an ExportedC, got {type(exported).__name__}")
    if exported.precision != "double":
        raise ParameterError(
            f"jax_function needs an export in double precision, got {exported.precision!r}"
        )
    if exported.stack_bytes > MAX_STACK_BYTES:
        raise ParameterError(
            f"the exported step needs about {exported.stack_bytes} bytes of stack, more than "
            f"{MAX_STACK_BYTES} that a custom call may take on XLA's threads; use the JAX step"
        )
    cc, cxx = find_compiler(compiler), find_cxx_compiler(cxx_compiler)
    _, symbol, used = _build(exported, cc, cxx, march_native)
    leaves, n = exported.leaves, exported.n_states

    def fn(x: Any) -> Any:
        x = jnp.asarray(x, jnp.float64)
        if x.ndim < 1 or x.shape[-1] != n:
            from ..errors import DimensionError

            raise DimensionError(f"x must have shape (..., {n}), got shape {x.shape}")
        batch = x.shape[:-1]
        shapes = [jax.ShapeDtypeStruct(batch + leaves[i].shape, leaves[i].dtype) for i in used]
        outs = jax.ffi.ffi_call(symbol, shapes, vmap_method="broadcast_all")(x)
        full: list[Any] = [None] * len(leaves)
        for i, val in zip(used, outs, strict=True):
            full[i] = val
        for i, leaf in enumerate(leaves):
            if full[i] is None:
                full[i] = jnp.zeros(batch + leaf.shape, leaf.dtype)
        return exported.treedef.unflatten(full)

    return fn
