"""Adaptive cruise control, the paper's Section IV (eq. (27), Table I), with TOML presets.

State ``x = (v_f, v_l, D)``: follower speed (m/s), lead speed (m/s), gap distance (m).
Dynamics::

    v_f' = (-F_r(v_f) + F) / M,   F_r(v) = f0 + f1 v + f2 v^2   (N)
    v_l' = a_L(t)                                                (m/s^2, exogenous)
    D'   = v_l - v_f

Input ``F``: wheel force in newtons (``input_units = "newton"``), or ``F / (M g)``
(``"normalized"``, dimensionless). CLF ``V = (v_f - v_d)^2`` with rate ``lam``; CBF
``h = D - tau v_f`` (m) with rate ``beta``. The lead acceleration is known to the simulator
but not part of ``f``: it does not enter ``a, b, c, d`` because neither ``V`` nor ``h``
depends on ``v_l``.
"""

from __future__ import annotations

import dataclasses
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import jax.numpy as jnp

from ..certificates import CBF, CLF, LieTerms
from ..errors import ScenarioError
from ..systems import ControlAffineSystem

__all__ = ["ACCScenario", "load_scenario", "PRESETS"]

PRESETS = ("paper", "stress")


@dataclasses.dataclass(frozen=True)
class Drag:
    """Rolling and aerodynamic resistance ``F_r = f0 + f1 v + f2 v^2`` (N, N s/m, N s^2/m^2)."""

    f0: float
    f1: float
    f2: float


@dataclasses.dataclass(frozen=True)
class ACCScenario:
    """All parameters of one ACC study; built from a TOML file by :func:`load_scenario`.

    Units: masses kg, speeds m/s, distances m, times s, forces N.
    """

    name: str
    mass: float  # kg
    gravity: float  # m/s^2
    drag_true: Drag
    drag_nominal: Drag
    v_f0: float  # m/s
    v_l0: float  # m/s
    D0: float  # m
    lead_profile: tuple[tuple[float, float], ...]  # (end time s, acceleration m/s^2)
    v_d: float  # m/s
    tau: float  # s
    lam: float  # 1/s
    beta: float  # 1/s
    kappa: float
    rho: float
    phi: float
    varphi: float
    slack_weight: float
    input_units: str  # "newton" | "normalized"
    input_limit: float | None  # fraction of M g, or None for no limits
    t_final: float  # s
    dt: float  # s
    n_samples: int
    sample_rate: float  # Hz
    sample_horizon: float  # s
    noise_std: float  # m/s^2
    gp_beta: float
    kernel: str
    x0_low: tuple[float, ...]  # (v_f, v_l, D)
    x0_high: tuple[float, ...]
    excitation_limit: float  # fraction of M g spanned by the excitation
    hyper_subset: int  # rows used to fit GP hyperparameters (then conditioned on all)
    seed: int

    # -- model ------------------------------------------------------------------------

    @property
    def input_scale(self) -> float:
        """Newtons per input unit: 1 for ``"newton"``, ``M g`` for ``"normalized"``."""
        return 1.0 if self.input_units == "newton" else self.mass * self.gravity

    def system(self, which: str = "true") -> ControlAffineSystem:
        """The ACC model with the ``"true"`` or ``"nominal"`` drag coefficients."""
        drag = self.drag_true if which == "true" else self.drag_nominal
        M, k = self.mass, self.input_scale

        def f(x):
            fr = drag.f0 + drag.f1 * x[0] + drag.f2 * x[0] ** 2
            return jnp.array([-fr / M, 0.0, x[1] - x[0]])

        def g(x):
            return jnp.array([[k / M], [0.0], [0.0]])

        return ControlAffineSystem(f, g, 3, name=f"acc-{which}")

    def certificates(self) -> tuple[CLF, CBF]:
        """CLF ``(v_f - v_d)^2`` and CBF ``D - tau v_f``."""
        v_d, tau = self.v_d, self.tau
        clf = CLF(lambda x: (x[0] - v_d) ** 2, lam=self.lam)
        cbf = CBF(lambda x: x[2] - tau * x[0], beta=self.beta)
        return clf, cbf

    def hand_lie_terms(self, x: Any, which: str = "true") -> LieTerms:
        """The Lie terms written out by hand (with the corrections of NOTES.md section 3).

        ``a = -2 (v_f - v_d) F_r/M + lam V``, ``b = 2 (v_f - v_d) k/M``,
        ``c = v_l - v_f + tau F_r/M + beta h``, ``d = -tau k/M`` with ``k`` the input scale.
        The paper prints an extra factor ``F_r`` in ``b`` and writes ``b, d`` as 3-vectors.
        """
        drag = self.drag_true if which == "true" else self.drag_nominal
        x = jnp.asarray(x, dtype=float)
        vf, vl, D = x[..., 0], x[..., 1], x[..., 2]
        fr = drag.f0 + drag.f1 * vf + drag.f2 * vf**2
        M, k = self.mass, self.input_scale
        V = (vf - self.v_d) ** 2
        h = D - self.tau * vf
        a = -2 * (vf - self.v_d) * fr / M + self.lam * V
        b = (2 * (vf - self.v_d) * k / M)[..., None]
        c = vl - vf + self.tau * fr / M + self.beta * h
        d = jnp.broadcast_to(-self.tau * k / M, vf.shape)[..., None]
        return LieTerms(a, b, c, d)

    def lead_acceleration(self, t: Any) -> Any:
        """``a_L(t)`` from the piecewise-constant profile, m/s^2 (0 after the last segment)."""
        t = jnp.asarray(t, dtype=float)
        out = jnp.zeros_like(t)
        start = 0.0
        for end, acc in self.lead_profile:
            # the paper's first segment is t <= 8 s; later ones are (start, end]
            inside = (t > start) & (t <= end) if start > 0 else (t <= end)
            out = jnp.where(inside, acc, out)
            start = end
        return out

    def exogenous(self, t: Any) -> Any:
        """The known term ``e(t) = (0, a_L(t), 0)`` of the true dynamics."""
        return jnp.array([0.0, 1.0, 0.0]) * self.lead_acceleration(t)

    def omega(self, x: Any) -> Any:
        """The true model error ``omega(x) = f_true(x) - f_nominal(x)`` (m/s^2 in v_f)."""
        x = jnp.asarray(x, dtype=float)
        vf = x[..., 0]
        dt, dn = self.drag_true, self.drag_nominal
        d0, d1, d2 = dt.f0 - dn.f0, dt.f1 - dn.f1, dt.f2 - dn.f2
        w = -(d0 + d1 * vf + d2 * vf**2) / self.mass
        return jnp.stack([w, jnp.zeros_like(w), jnp.zeros_like(w)], -1)

    @property
    def x0(self) -> tuple[float, float, float]:
        """Initial state ``(v_f, v_l, D)``."""
        return (self.v_f0, self.v_l0, self.D0)

    def input_limits(self) -> tuple[list[float], list[float]] | tuple[None, None]:
        """``(u_min, u_max)`` in input units, or ``(None, None)``."""
        if self.input_limit is None:
            return None, None
        lim = self.input_limit * self.mass * self.gravity / self.input_scale
        return [-lim], [lim]


# -- TOML -------------------------------------------------------------------------------

_SCHEMA: dict[str, dict[str, type | tuple[type, ...]]] = {
    "vehicle": {"mass": float, "gravity": float},
    "drag.true": {"f0": float, "f1": float, "f2": float},
    "drag.nominal": {"f0": float, "f1": float, "f2": float},
    "initial": {"v_f": float, "v_l": float, "D": float},
    "lead": {"profile": list},
    "certificates": {"v_d": float, "tau": float, "lam": float, "beta": float},
    "controller": {
        "kappa": float,
        "rho": float,
        "phi": float,
        "varphi": float,
        "slack_weight": float,
        "input_units": str,
        "input_limit": (float, bool),
    },
    "simulation": {"t_final": float, "dt": float},
    "learning": {
        "n_samples": int,
        "sample_rate": float,
        "sample_horizon": float,
        "noise_std": float,
        "gp_beta": float,
        "kernel": str,
        "x0_low": list,
        "x0_high": list,
        "excitation_limit": float,
        "hyper_subset": int,
        "seed": int,
    },
}
_POSITIVE = {"vehicle.mass", "vehicle.gravity", "simulation.t_final", "simulation.dt",
             "learning.n_samples", "learning.sample_rate", "learning.sample_horizon",
             "learning.hyper_subset",
             "controller.slack_weight", "certificates.tau"}  # fmt: skip
_NONNEGATIVE = {"certificates.lam", "certificates.beta", "controller.kappa", "controller.rho",
                "controller.phi", "controller.varphi", "learning.noise_std", "learning.gp_beta",
                "learning.excitation_limit"}  # fmt: skip


def _get(doc: dict, section: str, source: str) -> dict:
    node: Any = doc
    for part in section.split("."):
        if not isinstance(node, dict) or part not in node:
            raise ScenarioError(f"{source}: missing table [{section}]")
        node = node[part]
    return node


def _parse(doc: dict, name: str, source: str) -> ACCScenario:
    known_top = {s.split(".")[0] for s in _SCHEMA} | {"name"}
    for key in doc:
        if key not in known_top:
            raise ScenarioError(
                f"{source}: unknown key {key!r}; expected one of {sorted(known_top)}"
            )
    values: dict[str, Any] = {}
    for section, fields in _SCHEMA.items():
        table = _get(doc, section, source)
        extra = set(table) - set(fields)
        if extra:
            raise ScenarioError(f"{source}: unknown key {section}.{sorted(extra)[0]}")
        for key, typ in fields.items():
            full = f"{section}.{key}"
            if key not in table:
                raise ScenarioError(f"{source}: missing key {full}")
            val = table[key]
            if typ is float and isinstance(val, int) and not isinstance(val, bool):
                val = float(val)
            ok = isinstance(val, typ) and not (typ in (int, float) and isinstance(val, bool))
            if typ == (float, bool):
                ok = val is False or (isinstance(val, int | float) and not isinstance(val, bool))
                val = None if val is False else float(val)
            if not ok:
                raise ScenarioError(
                    f"{source}: {full} must be {getattr(typ, '__name__', typ)}, got {val!r}"
                )
            if full in _POSITIVE and not val > 0:
                raise ScenarioError(f"{source}: {full} must be > 0, got {val!r}")
            if full in _NONNEGATIVE and not val >= 0:
                raise ScenarioError(f"{source}: {full} must be >= 0, got {val!r}")
            values[full] = val
    if values["controller.input_units"] not in ("newton", "normalized"):
        raise ScenarioError(
            f"{source}: controller.input_units must be 'newton' or 'normalized', "
            f"got {values['controller.input_units']!r}"
        )
    if values["learning.kernel"] not in ("se", "matern52"):
        raise ScenarioError(
            f"{source}: learning.kernel must be 'se' or 'matern52', "
            f"got {values['learning.kernel']!r}"
        )
    lim = values["controller.input_limit"]
    if lim is not None and not lim > 0:
        raise ScenarioError(f"{source}: controller.input_limit must be > 0 or false, got {lim!r}")
    profile = values["lead.profile"]
    try:
        prof = tuple((float(e), float(a)) for e, a in profile)
    except (TypeError, ValueError):
        raise ScenarioError(
            f"{source}: lead.profile must be a list of [end_time, acceleration] pairs"
        ) from None
    if any(b[0] <= a[0] for a, b in zip(prof, prof[1:], strict=False)):
        raise ScenarioError(f"{source}: lead.profile end times must increase")
    for key in ("learning.x0_low", "learning.x0_high"):
        v = values[key]
        if len(v) != 3 or not all(isinstance(e, int | float) for e in v):
            raise ScenarioError(
                f"{source}: {key} must be a list of 3 numbers (v_f, v_l, D), got {v!r}"
            )
    if any(
        lo > hi
        for lo, hi in zip(values["learning.x0_low"], values["learning.x0_high"], strict=True)
    ):
        raise ScenarioError(f"{source}: learning.x0_low must be <= learning.x0_high")
    v = values
    return ACCScenario(
        name=str(doc.get("name", name)),
        mass=v["vehicle.mass"],
        gravity=v["vehicle.gravity"],
        drag_true=Drag(v["drag.true.f0"], v["drag.true.f1"], v["drag.true.f2"]),
        drag_nominal=Drag(v["drag.nominal.f0"], v["drag.nominal.f1"], v["drag.nominal.f2"]),
        v_f0=v["initial.v_f"],
        v_l0=v["initial.v_l"],
        D0=v["initial.D"],
        lead_profile=prof,
        v_d=v["certificates.v_d"],
        tau=v["certificates.tau"],
        lam=v["certificates.lam"],
        beta=v["certificates.beta"],
        kappa=v["controller.kappa"],
        rho=v["controller.rho"],
        phi=v["controller.phi"],
        varphi=v["controller.varphi"],
        slack_weight=v["controller.slack_weight"],
        input_units=v["controller.input_units"],
        input_limit=lim,
        t_final=v["simulation.t_final"],
        dt=v["simulation.dt"],
        n_samples=v["learning.n_samples"],
        sample_rate=v["learning.sample_rate"],
        sample_horizon=v["learning.sample_horizon"],
        noise_std=v["learning.noise_std"],
        gp_beta=v["learning.gp_beta"],
        kernel=v["learning.kernel"],
        x0_low=tuple(float(e) for e in v["learning.x0_low"]),
        x0_high=tuple(float(e) for e in v["learning.x0_high"]),
        excitation_limit=v["learning.excitation_limit"],
        hyper_subset=v["learning.hyper_subset"],
        seed=v["learning.seed"],
    )


def load_scenario(name_or_path: str | Path) -> ACCScenario:
    """Load a preset by name (``"paper"``, ``"stress"``) or a TOML file by path.

    Raises
    ------
    ScenarioError
        If the file does not exist, is not valid TOML, or a key is missing, unknown, of the
        wrong type or out of range; the message names the key.
    """
    text: str
    if str(name_or_path) in PRESETS:
        name = str(name_or_path)
        text = resources.files(__package__).joinpath(f"{name}.toml").read_text()
        source = f"preset {name!r}"
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise ScenarioError(
                f"scenario {str(name_or_path)!r} is neither a preset {PRESETS} nor a file"
            )
        text, name, source = path.read_text(), path.stem, str(path)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: invalid TOML: {exc}") from None
    return _parse(doc, name, source)
