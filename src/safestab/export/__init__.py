"""Export controllers as dependency-free C99 and call them natively from Python.

* :func:`export_c` translates a controller's fused step to ``<name>.c`` and ``<name>.h``;
* :class:`NativeController` compiles that code and calls it through cffi, with the same
  ``step`` / ``__call__`` as :class:`~safestab.UniversalController`;
* :func:`write_harness` writes a C test program with recorded states and expected outputs.

See ``docs/export.md``.
"""

from .exporter import PRIMITIVES, ExportedC, Leaf, export_c, export_function
from .harness import write_harness
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
    "write_harness",
]
