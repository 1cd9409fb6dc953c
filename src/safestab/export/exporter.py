"""Export a controller step (or any function of one state) as a dependency-free C99 file.

The function is traced to a jaxpr for one state of shape (n,); calls are inlined, everything
known at export time is folded into literals and ``static const`` tables, and each remaining
equation becomes one C statement (see :mod:`safestab.export._primitives`). Every leaf of the
output pytree becomes a field of the ``<name>_info`` struct, named after its pytree path
(``terms.a`` -> ``terms_a``); the leaf ``u`` (or the first leaf) is the function's array
argument.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DimensionError, ParameterError
from ._cgen import Emitter, c_identifier
from ._ir import Program, Val, check_dtype, live_statements
from ._primitives import RULES, fold_exact

__all__ = ["ExportedC", "Leaf", "PRIMITIVES", "export_c", "export_function"]

#: Names of the primitives with a C translation (calls such as ``jit``, ``custom_jvp_call``
#: and ``custom_vjp_call`` are inlined and not listed).
PRIMITIVES = tuple(sorted(RULES))

#: Bits of the value returned by the exported functions.
STATUS_BITS = {"NONFINITE_STATE": 1, "NONFINITE_OUTPUT": 2}

#: Compiler flags the exported code is written for (results match XLA's to rounding).
C_FLAGS = ("-std=c99", "-O2", "-ffp-contract=off")


@dataclasses.dataclass(frozen=True)
class Leaf:
    """One output of the exported function.

    Attributes
    ----------
    name : str
        The C field (or argument) name.
    path : str
        Its path in the output pytree, e.g. ``"terms.a"``.
    shape : tuple of int
        Shape for one state.
    dtype : numpy dtype
        The JAX dtype (float64 leaves are ``float`` in the float precision).
    doc : str
        One line from the output class's docstring, if found.
    """

    name: str
    path: str
    shape: tuple[int, ...]
    dtype: np.dtype
    doc: str

    @property
    def size(self) -> int:
        """Number of elements for one state."""
        return math.prod(self.shape)


@dataclasses.dataclass(frozen=True)
class ExportedC:
    """The C translation of a function of one state.

    Attributes
    ----------
    name : str
        Prefix of every C name (``<name>_step``, ``<name>_info``).
    n_states : int
    precision : {"double", "float"}
    source, header : str
        Contents of ``<name>.c`` and ``<name>.h``.
    cdef : str
        The header's declarations in the form cffi parses.
    leaves : tuple of Leaf
        The outputs in pytree order.
    primary : int
        Index in ``leaves`` of the output passed as the array argument (``u``).
    treedef : jax.tree_util.PyTreeDef
        Structure of the outputs (to rebuild the pytree from the leaves).
    stack_bytes : int
        Bytes of temporaries in the step function (an upper bound on its stack frame, which
        the compiler usually shrinks).
    """

    name: str
    n_states: int
    precision: str
    source: str
    header: str
    cdef: str
    leaves: tuple[Leaf, ...]
    primary: int
    treedef: Any
    stack_bytes: int

    def write(self, out_dir: str | Path) -> tuple[Path, Path]:
        """Write ``<name>.c`` and ``<name>.h`` into ``out_dir`` (created if needed).

        Returns
        -------
        (Path, Path)
            The absolute paths of the source and the header.
        """
        out = Path(out_dir).absolute()  # the paths returned stay valid after a chdir
        out.mkdir(parents=True, exist_ok=True)
        paths = (out / f"{self.name}.c", out / f"{self.name}.h")
        for path, text in zip(paths, (self.source, self.header), strict=True):
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(text)
            tmp.replace(path)  # atomic: never a half-written file under the final name
        return paths


def check_name(name: str) -> str:
    """``name`` if it is a C identifier of at most 41 characters; else ParameterError."""
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,40}", name):
        raise ParameterError(
            f"name must be a C identifier (letters, digits, underscores; at most 41 "
            f"characters), got {name!r}"
        )
    return name


def check_precision(precision: str) -> str:
    """``precision`` if it is ``'double'`` or ``'float'``; else ParameterError."""
    if precision not in ("double", "float"):
        raise ParameterError(f"precision must be 'double' or 'float', got {precision!r}")
    return precision


# --------------------------------------------------------------------------------------
# output leaves: names and documentation


def _key_name(key: Any) -> str:
    for attr in ("name", "key", "idx"):
        if hasattr(key, attr):
            val = getattr(key, attr)
            return f"y{val}" if isinstance(val, int) else str(val)
    return str(key)


def _attribute_docs(obj: Any) -> dict[str, str]:
    """First description line of each entry in a NumPy-style ``Attributes`` section."""
    doc = inspect.getdoc(type(obj)) or ""
    m = re.search(r"^Attributes\n-+\n(.*?)(?:\n\S[^\n]*\n-+\n|\Z)", doc, re.S | re.M)
    if not m:
        return {}
    out: dict[str, str] = {}
    current = None
    for line in m.group(1).splitlines():
        if line and not line.startswith(" "):
            current = line.split(":")[0].strip()
            out[current] = ""
        elif current and line.strip() and not out[current]:
            out[current] = line.strip()
    return out


def _leaves(out_shape: Any) -> tuple[list[Leaf], Any]:
    flat, treedef = jax.tree_util.tree_flatten_with_path(out_shape)
    leaves: list[Leaf] = []
    used: set[str] = set()
    for path, sds in flat:
        parent, doc = out_shape, ""
        for key in path:
            docs = _attribute_docs(parent)
            doc = docs.get(_key_name(key), "")
            try:
                parent = _child(parent, key)
            except (AttributeError, KeyError, IndexError, TypeError):
                parent = None
        dotted = ".".join(_key_name(k) for k in path) or "y"
        name = c_identifier(dotted.replace(".", "_"))
        while name in used:
            name += "_"
        used.add(name)
        leaves.append(Leaf(name, dotted, tuple(sds.shape), np.dtype(sds.dtype), doc))
    return leaves, treedef


def _child(parent: Any, key: Any) -> Any:
    if hasattr(key, "name"):
        return getattr(parent, key.name)
    if hasattr(key, "key"):
        return parent[key.key]
    return parent[key.idx]


# --------------------------------------------------------------------------------------
# the translation


def export_function(
    fn: Callable[[jax.Array], Any],
    n_states: int,
    name: str,
    *,
    precision: str = "double",
    description: str = "",
    layout: str = "host",
) -> ExportedC:
    """Translate a function of one state to C99.

    Parameters
    ----------
    fn : callable
        A JAX function from a state of shape (n_states,) to a pytree of arrays.
    n_states : int
        The state dimension.
    name : str
        Prefix of the C names; a C identifier.
    precision : {"double", "float"}
        The C type of float64 values.
    description : str
        Text for the header comment (what the function computes, units).
    layout : {"host", "embedded"}
        How matrix products are written: ``"host"`` (default) loops innermost over an output
        axis that a desktop compiler vectorises; ``"embedded"`` sums each output element in
        a register over contiguous constants, for cores without SIMD (fewer instructions on a
        Cortex-M), and places arrays that are never live at once in one work array (a
        smaller stack). The same bits either way.

    Returns
    -------
    ExportedC

    Raises
    ------
    UnsupportedPrimitiveError
        If ``fn`` uses a primitive without a C translation (the message names the primitive
        and the ``file:line`` that produced it) or a dtype the C code cannot hold.
    ParameterError
        If ``name`` is not a C identifier or ``precision`` is unknown.
    DimensionError
        If ``n_states`` is not a positive integer.
    """
    check_name(name)
    check_precision(precision)
    if layout not in ("host", "embedded"):
        raise ParameterError(f"layout must be 'host' or 'embedded', got {layout!r}")
    if not isinstance(n_states, int | np.integer) or int(n_states) < 1:
        raise DimensionError(f"n_states must be a positive integer, got {n_states!r}")
    n = int(n_states)
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(
        jax.ShapeDtypeStruct((n,), jnp.float64)
    )
    leaves, treedef = _leaves(out_shape)
    for leaf in leaves:
        check_dtype(leaf.dtype, f"output {leaf.path}", "the function's result")
    program = Program()
    program.rules = RULES
    program.exact_fold = fold_exact
    program.layout = layout
    x = Val((n,), np.float64, param="x")
    outs = program.run(closed.jaxpr, closed.consts, [x])
    primary = next((i for i, leaf in enumerate(leaves) if leaf.path == "u"), 0)
    from ._assemble import assemble

    source, header, cdef, stack = assemble(
        name=name,
        precision=precision,
        n_states=n,
        leaves=leaves,
        outs=outs,
        primary=primary,
        stmts=live_statements(program, outs),
        emitter=Emitter(precision),
        description=description,
        version=_version(),
        share_work=layout == "embedded",
    )
    return ExportedC(
        name, n, precision, source, header, cdef, tuple(leaves), primary, treedef, stack
    )


def _version() -> str:
    from .._version import __version__

    return __version__


def _describe_controller(controller: Any) -> str:
    """The exact formula variant of a UniversalController, for the header."""
    p = controller.params
    names = {"SontagFormula": "Sontag's CLF formula (eq. (3))",
             "CBFFormula": "the CBF formula (eq. (6))"}  # fmt: skip
    kind = names.get(
        type(controller.formula).__name__,
        f"relaxed formula (Theorem 3), slack_weight = {controller.slack_weight!r}"
        if controller.slack_weight is not None
        else "combined hard-constraint formula (Theorem 1)",
    )
    rates = [
        f"{what} = {'none (no ' + cert_kind + ')' if cert is None else repr(cert.rate)}"
        for what, cert, cert_kind in (
            ("CLF rate lambda", controller.clf, "CLF"),
            ("CBF rate beta", controller.cbf, "CBF"),
        )
    ]
    lines = [
        f"Controller: {controller!r}",
        f"System '{controller.system.name}': n_states = {controller.system.n_states}, "
        f"n_inputs = {controller.system.n_inputs}.",
        f"Formula: {kind}; kappa = {p['kappa']!r}, rho = {p['rho']!r}, phi = {p['phi']!r}, "
        f"varphi = {p['varphi']!r}, parallel_rtol = {controller.parallel_rtol!r}.",
        "; ".join(rates) + ".",
    ]
    if getattr(controller, "sample_time", None) is not None:
        lines.append(
            f"Sampled-data margin: sample_time = {float(controller.sample_time)!r} s, ddh_bound "
            f"= {float(controller.ddh_bound)!r}: the CBF condition is shifted by "
            "M T / 2 + max(0, alpha(h) - h / T) (docs/deployed.md)."
        )
    if getattr(controller, "cbf_margin", None) is not None:
        lines.append(
            f"CBF margin {float(controller.cbf_margin)!r}: the formula enforces c + d.u >= "
            "rho Gamma + margin; cbf_satisfied reports c + d.u - rho Gamma >= margin / 2."
        )
    if controller.u_min is not None:
        lines.append(
            f"Input limits u_min = {np.asarray(controller.u_min).tolist()}, "
            f"u_max = {np.asarray(controller.u_max).tolist()}, enforced by "
            + (
                "projection (eq. (26))"
                if controller.saturation == "project"
                else "safety-first saturation"
            )
            + "."
        )
    else:
        lines.append("No input limits.")
    if controller.uncertainty is not None:
        unc = controller.uncertainty
        extra = ""
        if hasattr(unc, "n_inducing_"):
            extra = (
                f" (inducing points per component {np.asarray(unc.n_inducing_).tolist()}; its "
                f"band contains the exact band for beta >= {getattr(unc, 'min_beta', 1.0)})"
            )
        lines.append(
            f"GP-robust Lie terms (Lemma 3, Theorem 2) from {type(unc).__name__}{extra}, "
            f"beta = {np.asarray(controller.gp_beta).tolist()}."
        )
        lines += _layer_lines(controller)
    return "\n".join(lines)


def _layer_lines(obj: Any) -> list[str]:
    """The header's line on a boundary layer on the robust CLF term(s), if there is one."""
    layer = getattr(obj, "robust_clf_layer", None)
    if layer is None:
        return []
    return [
        f"Boundary layer on the robust CLF term, eps = {float(layer)!r}: the term is "
        "multiplied by |dV/dx| / sqrt(|dV/dx|^2 + eps^2) (docs/learning.md)."
    ]


def _describe_policy(ctrl: Any) -> str:
    """What a PolicyController's step computes, for the header."""
    name = getattr(ctrl.policy, "__name__", type(ctrl.policy).__name__)
    limits = (
        f"projected onto u_min = {np.asarray(ctrl.u_min).tolist()}, u_max = "
        f"{np.asarray(ctrl.u_max).tolist()}"
        if ctrl.u_min is not None
        else "no input limits"
    )
    return "\n".join([
        f"Policy controller on system '{ctrl.system.name}': n_states = "
        f"{ctrl.system.n_states}, n_inputs = {ctrl.system.n_inputs}.",
        f"The user's law '{name}' passes through unchanged ({limits}); nothing is enforced. "
        f"Its {len(ctrl.cbfs)} CBF condition(s) and {len(ctrl.clfs)} CLF condition(s) are "
        "evaluated at that input and the status names where a barrier's fails.",
    ])  # fmt: skip


def _describe_filter(filt: Any) -> str:
    """The problem a SafetyFilter solves, for the header."""
    p = filt.params
    k, n_clf = len(filt.cbfs), len(filt.clfs)
    lines = [
        f"Safety filter on system '{filt.system.name}': n_states = {filt.system.n_states}, "
        f"n_inputs = {filt.system.n_inputs}; {k} CBF(s), {n_clf} CLF(s).",
        "Solves min 1/2 (u - u_nom)' H (u - u_nom) + 1/2 m sum chi_j^2 over the CBF rows, the "
        "CLF rows and the input limits exactly (a dual active-set method with a fixed "
        "iteration bound); formula_status says SOLVED only where its KKT certificate holds.",
        f"kappa = {p['kappa']!r}, rho = {p['rho']!r}, phi = {p['phi']!r}, "
        f"varphi = {p['varphi']!r}; CLF slack weight = {filt.slack_weight!r}; "
        f"H = {'identity' if filt.H is None else np.asarray(filt.H).tolist()}.",
        "CBF rates beta = " + ", ".join(repr(cb.rate) for cb in filt.cbfs) + ".",
    ]
    if filt.u_min is not None:
        lines.append(
            f"Input limits u_min = {np.asarray(filt.u_min).tolist()}, "
            f"u_max = {np.asarray(filt.u_max).tolist()} (inside the problem)."
        )
    else:
        lines.append("No input limits.")
    if filt.uncertainty is not None:
        lines.append(
            f"GP-robust rows (Lemma 3) from {type(filt.uncertainty).__name__}, "
            f"beta = {np.asarray(filt.gp_beta).tolist()}."
        )
        lines += _layer_lines(filt)
    if getattr(filt, "cbf_margin", None) is not None:
        lines.append(
            f"CBF margin {float(filt.cbf_margin)!r}: every CBF row enforces c + d.u >= "
            "rho Gamma + margin, and cbf_satisfied reports it with half the margin."
        )
    if getattr(filt, "precision", "double") != "double":
        lines.append(
            f"Solver and flag tolerances for {filt.precision} precision (the same multiples "
            "of its rounding as float64's)."
        )
    return "\n".join(lines)


def export_c(
    controller: Any,
    name: str = "controller",
    out_dir: str | Path | None = None,
    *,
    precision: str = "double",
    description: str = "",
    layout: str = "host",
) -> ExportedC:
    """Export a controller's whole step (Lie terms, GP, formula, limits, flags) as C99.

    Parameters
    ----------
    controller : Controller
        The controller (:class:`~safestab.UniversalController`,
        :class:`~safestab.SafetyFilter`, :class:`~safestab.PolicyController`); its fused step
        ``controller.step_fn`` is traced for one state. A
        :class:`~safestab.SafetyFilter` is exported with its solver (loops in C; at most
        :data:`~safestab.formulas._dual_active_set.UNROLL` whitened coordinates are written
        without LAPACK-style helpers, beyond that a Householder QR and triangular solves in
        plain C).
    name : str
        Prefix of the C names: ``<name>_step``, ``<name>_info``, files ``<name>.c/.h``.
    out_dir : path, optional
        When given, ``<name>.c`` and ``<name>.h`` are written there.
    precision : {"double", "float"}
        The C type of real numbers (``float`` for small processors without a double FPU).
    description : str
        Extra text for the header, e.g. the units of the state and the input.
    layout : {"host", "embedded"}
        See :func:`export_function`.

    Returns
    -------
    ExportedC

    Raises
    ------
    UnsupportedPrimitiveError
        If the system, certificates or uncertainty model use a primitive without a C
        translation; the message names it and the ``file:line`` it came from.
    ParameterError
        If ``name`` or ``precision`` is invalid, or the controller takes run-time
        parameters (not exported yet).
    """
    if getattr(controller, "params_spec", None) is not None:
        raise ParameterError(
            "export_c does not support controllers with run-time parameters (params=...); "
            "build the controller with the values fixed in its functions to export it"
        )
    from ..filters import SafetyFilter
    from ..policy import PolicyController

    if isinstance(controller, PolicyController):
        text = _describe_policy(controller)
    elif isinstance(controller, SafetyFilter):
        text = _describe_filter(controller)
    else:
        text = _describe_controller(controller)
    if description:
        text += "\n" + description
    exported = export_function(
        controller.step_fn,
        controller.system.n_states,
        name,
        precision=precision,
        description=text,
        layout=layout,
    )
    if out_dir is not None:
        exported.write(out_dir)
    return exported
