"""Export controllers as dependency-free C99 and call them natively from Python.

* :func:`export_c` translates a controller's fused step to ``<name>.c`` and ``<name>.h``;
* :class:`NativeController` compiles that code and calls it through cffi, with the same
  ``step`` / ``__call__`` as :class:`~safestab.UniversalController`;
* :func:`jax_function` runs exported C inside JAX as one XLA custom call (jit, vmap);
  :func:`native_step` so runs a :class:`~safestab.SafetyFilter`'s step, with derivatives;
* :func:`write_harness` writes a C test program with recorded states and expected outputs.

See ``docs/export.md``.
"""

from .exporter import PRIMITIVES, ExportedC, Leaf, export_c, export_function
from .harness import write_harness
from .jax_filter import native_step
from .jax_kernel import jax_function
from .native import NativeController, NativeFunction, compile_native

__all__ = [
    "PRIMITIVES",
    "ExportedC",
    "Leaf",
    "NativeController",
    "NativeFunction",
    "compile_native",
    "export_c",
    "export_function",
    "jax_function",
    "native_step",
    "write_harness",
]
