"""The controllers the studies compare: one name each, and what each one is.

Every study, table, figure, metrics key and command-line option names a controller by the
strings defined here, and every module that needs the list imports it from here. Old names are
still read for one release (:data:`RENAMED`): :func:`current_name` and :class:`NameMap` accept
them with a :class:`DeprecationWarning` that names the new name. The module imports nothing
of the package, so every layer that names a controller (the studies, the figures, the
command line) imports it from below.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

__all__ = [
    "CONTROLLERS",
    "DESCRIPTIONS",
    "EXPORT_CHOICES",
    "GP_CONTROLLERS",
    "GP_MEAN",
    "GP_ROBUST",
    "GP_ROBUST_CONFORMAL",
    "GP_ROBUST_LEMMA2",
    "MISMATCHED_MODEL",
    "MODEL_CONTROLLERS",
    "MODEL_OF",
    "RENAMED",
    "STUDY_CONTROLLERS",
    "TRUE_MODEL",
    "NameMap",
    "build_compared",
    "current_name",
    "export_choice",
    "read_renamed",
]

TRUE_MODEL = "true model"
MISMATCHED_MODEL = "mismatched model"
GP_MEAN = "GP mean"
GP_ROBUST = "GP-robust"
GP_ROBUST_LEMMA2 = "GP-robust Lemma 2"
GP_ROBUST_CONFORMAL = "GP-robust conformal"

#: What each compared controller is, in the order tables report them.
DESCRIPTIONS: dict[str, str] = {
    TRUE_MODEL: "the universal formula on the true model: the reference, not available in practice",
    MISMATCHED_MODEL: "the universal formula on the nominal (mismatched) model, no learning",
    GP_MEAN: "the nominal model plus the GP mean (beta = 0: no margin)",
    GP_ROBUST: "the GP-robust Lie terms (Lemma 3, Theorem 2) with the scenario's chosen beta",
    GP_ROBUST_LEMMA2: "the GP-robust Lie terms with Lemma 2's beta (Theorem 3)",
    GP_ROBUST_CONFORMAL: "the GP-robust Lie terms with a split conformal beta "
    "(needs safestab.learning.conformal_beta)",
}
#: Every compared controller, in the order tables report them.
CONTROLLERS = tuple(DESCRIPTIONS)
#: The controllers built on a model alone (no data).
MODEL_CONTROLLERS = (TRUE_MODEL, MISMATCHED_MODEL)
#: The controllers that use the learned model of ``omega``.
GP_CONTROLLERS = (GP_MEAN, GP_ROBUST, GP_ROBUST_LEMMA2, GP_ROBUST_CONFORMAL)
#: The three controllers of a single study (the paper's Fig. 4; the obstacle study).
STUDY_CONTROLLERS = (TRUE_MODEL, MISMATCHED_MODEL, GP_ROBUST)
#: ``safestab export --controller``'s short names.
EXPORT_CHOICES = {"gp": GP_ROBUST, "nominal": MISMATCHED_MODEL, "true": TRUE_MODEL}
#: Old names, read for one release: old name -> current name.
RENAMED = {"GP-corrected": GP_ROBUST}
#: The model each compared controller stands on: ``"true"``, ``"nominal"`` or ``"learned"``
#: (the nominal model, with the learned input gain where a study estimates one).
MODEL_OF: dict[str, str] = {
    TRUE_MODEL: "true",
    MISMATCHED_MODEL: "nominal",
    **{name: "learned" for name in GP_CONTROLLERS},
}

_V = TypeVar("_V")


def _warn(what: str, old: str, new: str, where: str | None, stacklevel: int) -> None:
    source = f"{where}: " if where else ""
    warnings.warn(
        f"{source}the {what} {old!r} is deprecated; use {new!r} "
        "(the old name is read for one release only)",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def read_renamed(
    name: Any,
    renamed: Mapping[str, str],
    what: str,
    where: str | None = None,
    stacklevel: int = 4,
) -> Any:
    """``name``, or its current name where ``renamed`` maps it (with a DeprecationWarning).

    The one reading of old names: the controllers' (:func:`current_name`) and the swarm's
    modes (:func:`~safestab.scenarios.swarm.current_mode`).

    Parameters
    ----------
    name : str
        A name; anything else is returned as it is (the caller checks it).
    renamed : mapping of str to str
        Old name -> current name.
    what : str
        What the name names, for the warning (``"controller name"``).
    where : str, optional
        Where the name came from, for the warning (a file and key, a command-line option).
    stacklevel : int
        The warning's frame, counted from the function that issues it: 4 is the caller of
        the function that called this one.

    Returns
    -------
    str
        The current name.
    """
    if isinstance(name, str) and name in renamed:
        _warn(what, name, renamed[name], where, stacklevel)
        return renamed[name]
    return name


def current_name(name: Any, where: str | None = None) -> Any:
    """``name``, or its current name if it is an old one (with a DeprecationWarning).

    Parameters
    ----------
    name : str
        A controller name; anything else is returned as it is (the caller checks it).
    where : str, optional
        Where the name came from, for the warning (a file and key, a command-line option).

    Returns
    -------
    str
        The current name.

    Warns
    -----
    DeprecationWarning
        If ``name`` is a key of :data:`RENAMED`.
    """
    return read_renamed(name, RENAMED, "controller name", where)


class NameMap(dict[str, _V]):
    """A dict keyed by controller names that also finds a value by an old name.

    ``m["GP-corrected"]`` returns ``m["GP-robust"]`` with a DeprecationWarning; the keys
    themselves are the current names. Made from a mapping whose keys may be old names (a
    metrics file written before a rename), it renames them, with the same warning.
    """

    def __init__(self, items: Mapping[str, _V] | Iterable[tuple[str, _V]] = (), /,
                 where: str | None = None) -> None:  # fmt: skip
        pairs = items.items() if isinstance(items, Mapping) else items
        super().__init__((current_name(k, where), v) for k, v in pairs)

    def __missing__(self, key: str) -> _V:
        if isinstance(key, str) and key in RENAMED and RENAMED[key] in self:
            _warn("controller name", key, RENAMED[key], None, stacklevel=3)
            return self[RENAMED[key]]
        raise KeyError(key)


def build_compared(
    name: str,
    build: Callable[..., _V],
    models: Mapping[str, Any],
    *,
    uncertainty: Any = None,
    gp_beta: Any = None,
    robust_options: Mapping[str, Any] | None = None,
    **options: Any,
) -> _V:
    """The compared controller ``name``: the one factory of every study and the Monte Carlo.

    ``build(model, **options)`` on the model the controller stands on (:data:`MODEL_OF`); a
    controller that uses the learned model (:data:`GP_CONTROLLERS`) also gets
    ``uncertainty``, ``gp_beta`` and ``robust_options``.

    Parameters
    ----------
    name : str
        One of :data:`CONTROLLERS` (an old name is read, with a DeprecationWarning).
    build : callable
        ``build(model, **kwargs) -> controller``: the study's controller class with its
        certificates bound (``UniversalController``, a filter, a limited variant).
    models : mapping of str to system
        The models by :data:`MODEL_OF`'s values; only the one ``name`` stands on is read.
    uncertainty : uncertainty model, optional
        Required by the GP controllers.
    gp_beta : float or array, optional
        The GP controllers' beta.
    robust_options : mapping, optional
        Extra keyword arguments of the GP controllers only.
    **options
        Keyword arguments of every controller (kappa, rho, limits, ...).

    Returns
    -------
    controller

    Raises
    ------
    ValueError
        If ``name`` is not a controller, or a GP controller gets no ``uncertainty``.
    """
    name = current_name(name)
    if name not in MODEL_OF:
        raise ValueError(f"controller must be one of {list(CONTROLLERS)}, got {name!r}")
    model = models[MODEL_OF[name]]
    if name not in GP_CONTROLLERS:
        return build(model, **options)
    if uncertainty is None:
        raise ValueError(f"the {name} controller needs an uncertainty model")
    return build(
        model, uncertainty=uncertainty, gp_beta=gp_beta, **options, **(robust_options or {})
    )


def export_choice(name: Any) -> Any:
    """``safestab export --controller``'s short name (:data:`EXPORT_CHOICES`) for ``name``.

    A short name is returned as it is, a study controller's name (current or old, with a
    DeprecationWarning) as its short name, so the export takes the names every other command
    takes; anything else is returned as it is (the caller checks it).
    """
    name = current_name(name)
    return {full: short for short, full in EXPORT_CHOICES.items()}.get(name, name)
