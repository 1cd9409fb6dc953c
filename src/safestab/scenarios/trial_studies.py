"""The Monte Carlo protocol of the ACC and obstacle scenarios: what a trial study needs.

:func:`safestab.montecarlo.run_montecarlo` runs any scenario whose ``trial_study(spec)``
returns an object with the members of :class:`safestab.montecarlo.protocol.TrialStudy`: its
systems, certificates and controller settings, its GP settings, how it collects data, how it
draws a trial's initial state and per-trial data, and the known exogenous term of its true
dynamics. :class:`ScenarioTrials` provides what the two scenarios share (their field names
agree); :class:`ACCTrials` adds the lead vehicle, :class:`ObstacleTrials` the start grid.
A new scenario subclasses :class:`ScenarioTrials` (or writes the protocol's members) and
gives its scenario class a ``trial_study`` method: docs/architecture.md.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ..controllers import UniversalController
from ..errors import ParameterError
from ..learning import collect_data
from ._mc_schema import MonteCarloSpec
from .acc_braking import check_lead_bound

__all__ = ["ACCTrials", "ObstacleTrials", "ScenarioTrials", "lead_acceleration"]


@dataclasses.dataclass(frozen=True)
class ScenarioTrials:
    """A scenario and its Monte Carlo spec, as the trial study of the Monte Carlo runner.

    Frozen and hashable (the runner keys its compiled loop on it) and picklable (the Ray
    backend ships it to workers). The scenario must have the fields and methods the ACC and
    obstacle scenarios share: ``system(which)``, ``certificates()``, ``input_limits()``,
    ``omega(x)``, ``kappa``, ``rho``, ``phi``, ``varphi``, ``slack_weight``, ``t_final``,
    ``dt``, ``n_samples``, ``kernel``, ``hyper_subset``, ``gp_beta``, ``noise_std``,
    ``sample_rate``, ``sample_horizon``, ``x0_low``, ``x0_high``.

    Raises
    ------
    ParameterError
        If ``spec`` is not a MonteCarloSpec, or its initial-state vectors do not have one
        entry per state (``montecarlo.initial.*``).
    """

    scenario: Any
    spec: MonteCarloSpec

    #: Unit of the CBF ``h`` (the summary's and the figure's min-h unit).
    h_unit: ClassVar[str] = ""
    #: Names of the state components, for messages.
    state_names: ClassVar[str] = ""

    def __post_init__(self) -> None:
        if not isinstance(self.spec, MonteCarloSpec):
            raise ParameterError(f"spec must be a MonteCarloSpec, got {type(self.spec).__name__}")
        n = self.n_states
        for key in ("low", "high", "mean", "std"):
            value = getattr(self.spec, f"initial_{key}")
            if value is not None and len(value) != n:
                raise ParameterError(
                    f"montecarlo.initial.{key} must have {n} entries ({self.state_names}) for "
                    f"the {self.kind} scenario {self.name!r}, got {list(value)!r}"
                )

    # -- what the runner reads ----------------------------------------------------------
    kind: ClassVar[str] = ""

    @property
    def name(self) -> str:
        """The scenario's name (output file names)."""
        return self.scenario.name

    @property
    def n_states(self) -> int:
        """State dimension ``n``."""
        return self.scenario.system("true").n_states

    @property
    def n_steps(self) -> int:
        """Closed-loop steps per trial, ``round(t_final / dt)``."""
        return int(round(self.scenario.t_final / self.scenario.dt))

    @property
    def dt(self) -> float:
        """Step, s."""
        return self.scenario.dt

    @property
    def t_final(self) -> float:
        """Horizon, s."""
        return self.scenario.t_final

    def systems(self) -> tuple[Any, Any]:
        """``(true, nominal)`` control-affine systems (the same objects at every call)."""
        return self._systems

    @functools.cached_property
    def _systems(self) -> tuple[Any, Any]:
        # built once per study: the compiled data collection is cached per system object
        return self.scenario.system("true"), self.scenario.system("nominal")

    def __getstate__(self) -> dict[str, Any]:
        # a copy (a Ray worker's) builds its own systems
        return {k: v for k, v in self.__dict__.items() if k != "_systems"}

    def certificates(self) -> tuple[Any, Any]:
        """``(clf, cbf)``."""
        return self.scenario.certificates()

    def controller_options(self) -> dict[str, Any]:
        """Keyword arguments of every compared :class:`~safestab.UniversalController`."""
        sc = self.scenario
        u_min, u_max = sc.input_limits()
        margin = (
            {}
            if self.spec.ddh_bound is None
            else {"sample_time": sc.dt, "ddh_bound": self.spec.ddh_bound}
        )
        return dict(
            kappa=sc.kappa, rho=sc.rho, phi=sc.phi, varphi=sc.varphi,
            slack_weight=sc.slack_weight, u_min=u_min, u_max=u_max, **margin,
        )  # fmt: skip

    def controller_settings(self) -> dict[str, Any]:
        """The compared controllers' settings, as the study's JSON documents record them.

        :meth:`controller_options` as numbers and lists (the limits in the scenario's input
        units), how the input limits are kept
        (``limit_method``: ``"projection"`` onto the box, eq. (26), or ``"filter"``, a
        :class:`~safestab.SafetyFilter` with the box as rows; None without limits) and the
        GP-robust controllers' :meth:`robust_options`.
        """
        options = {
            k: v if v is None or isinstance(v, bool | str) else np.asarray(v).tolist()
            for k, v in self.controller_options().items()
        }
        limited = options.get("u_min") is not None or options.get("u_max") is not None
        return {
            **options,
            "limit_method": self.limit_method() if limited else None,
            "robust": self.robust_options(),
        }

    def limit_method(self) -> str:
        """How the compared controllers keep the input limits: projection onto the box."""
        return "projection"

    def robust_options(self) -> dict[str, Any]:
        """Extra keyword arguments of the GP-robust controllers.

        The scenario's boundary layer on the CLF's robust term
        (``controller.robust_clf_layer``), where it has one > 0.
        """
        layer = float(getattr(self.scenario, "robust_clf_layer", 0.0))  # ACC: none
        return {"robust_clf_layer": layer} if layer > 0 else {}

    def omega(self, x: Any) -> Any:
        """The true model error the GP learns, shape (..., n)."""
        return self.scenario.omega(x)

    def gp_settings(self) -> dict[str, Any]:
        """``n_samples`` (Q), ``kernel``, ``hyper_subset``, ``gp_beta``, ``input_gain``.

        ``gp_beta`` is the chosen beta; ``input_gain`` is ``"nominal"`` unless the scenario
        learns it.
        """
        sc = self.scenario
        return dict(
            n_samples=sc.n_samples, kernel=sc.kernel, hyper_subset=sc.hyper_subset,
            gp_beta=sc.gp_beta, input_gain=self.input_gain(),
        )  # fmt: skip

    def input_gain(self) -> str:
        """``learning.input_gain``: the ACC scenarios trust the nominal input matrix."""
        return "nominal"

    def calibration_shape(self) -> tuple[int, int]:
        """``(states per excitation trajectory, thinning stride)``: one state per second."""
        sc = self.scenario
        per_traj = max(1, int(round(sc.sample_horizon * sc.sample_rate)))
        return per_traj, max(1, int(round(sc.sample_rate)))

    def excitation_span(self) -> float:
        """Half-width of the excitation inputs, in input units."""
        raise NotImplementedError

    def collect(self, n_samples: int, seed: int) -> Any:
        """``collect_data`` with the scenario's true and nominal models and excitation."""
        sc = self.scenario
        span = self.excitation_span()
        noise = sc.noise_std if self.spec.noise_std is None else self.spec.noise_std
        return collect_data(
            *self.systems(),
            x0=(sc.x0_low, sc.x0_high), u_low=-span, u_high=span,
            n_samples=n_samples, rate=sc.sample_rate, horizon=sc.sample_horizon,
            noise_std=noise, seed=seed,
        )  # fmt: skip

    # -- trials -------------------------------------------------------------------------
    #: ``e(t, x, params) -> (n,)``: a known term of the true dynamics, or None.
    exogenous: ClassVar[Any] = None

    def fixed_start(self, index: jax.Array) -> jax.Array:
        """The initial state of trial ``index`` under ``initial.distribution = "fixed"``."""
        raise NotImplementedError

    def trial_data(self, key: jax.Array) -> Any:
        """Per-trial data (a pytree) for ``exogenous``, from the trial's key."""
        return {}

    def draw_trials(self, seed: int, indices: Any) -> tuple[jax.Array, Any]:
        """Initial states (B, n) and per-trial data of the trials ``indices``, from ``(seed, i)``.

        Trial ``i``'s key is ``fold_in(PRNGKey(seed), i)``, split into three: the initial
        state's, and two for :meth:`trial_data`.
        """
        return _draw(self, jnp.asarray(seed, jnp.uint32), jnp.asarray(indices))

    def _draw_one(self, seed: jax.Array, i: jax.Array) -> tuple[jax.Array, Any]:
        spec, n = self.spec, self.n_states
        key = jax.random.fold_in(jax.random.PRNGKey(seed), i)
        k_x, k_d, k_a = jax.random.split(key, 3)
        if spec.initial_distribution == "box":
            low, high = jnp.asarray(spec.initial_low), jnp.asarray(spec.initial_high)
            x0 = jax.random.uniform(k_x, (n,), minval=low, maxval=high)
        elif spec.initial_distribution == "normal":
            std = jnp.asarray(spec.initial_std)
            x0 = jnp.asarray(spec.initial_mean) + std * jax.random.normal(k_x, (n,))
        else:
            x0 = self.fixed_start(i)
        return x0, self.trial_data(jnp.stack([k_d, k_a]))


@functools.partial(jax.jit, static_argnames=("study",))
def _draw(study: ScenarioTrials, seed: jax.Array, indices: jax.Array) -> tuple[jax.Array, Any]:
    """The trials' draws, one program per study (its static argument)."""
    return jax.vmap(study._draw_one, in_axes=(None, 0))(seed, indices)


def lead_acceleration(t: jax.Array, x: jax.Array, params: dict[str, jax.Array]) -> jax.Array:
    """``e(t, x) = (0, a_L, 0)``: the segment containing ``t``, 0 after the last.

    Segments are ``t <= ends[0]``, then ``(ends[j-1], ends[j]]`` (the scenario file's
    convention). A lead that has stopped (``v_l <= 0``) does not brake further: it stops
    rather than reverses (a choice; docs/montecarlo.md).
    """
    ends, acc = params["ends"], params["acc"]
    # the segment index is the number of ends before t (ends increase: the scenario file's
    # profile is validated so, random ones are sums of positive durations); a count fuses
    # with the rest, where searchsorted was a while loop per RK4 stage
    j = jnp.sum(ends < t)
    a = jnp.where(j < ends.shape[0], acc[jnp.minimum(j, ends.shape[0] - 1)], 0.0)
    a = jnp.where((x[1] <= 0.0) & (a < 0.0), 0.0, a)
    return jnp.array([0.0, 1.0, 0.0]) * a


@dataclasses.dataclass(frozen=True)
class ACCTrials(ScenarioTrials):
    """The ACC's trials: the lead vehicle's profile is the per-trial data.

    ``initial.distribution = "fixed"`` starts every trial at the scenario's ``x0``;
    ``lead.kind = "random"`` draws ``lead.segments`` segments per trial (``"fixed"``: the
    scenario's profile).
    """

    h_unit: ClassVar[str] = "m"
    state_names: ClassVar[str] = "v_f m/s, v_l m/s, D m"
    kind: ClassVar[str] = "ACC"
    exogenous: ClassVar[Any] = staticmethod(lead_acceleration)

    def __post_init__(self) -> None:
        super().__post_init__()
        # a spec passed in (not the file's, checked at load) must keep the barrier's lead
        check_lead_bound(self.scenario, self.spec, f"ACC scenario {self.name!r}", ParameterError)

    def build_controller(self, system: Any, clf: Any, cbf: Any, **options: Any) -> Any:
        """One compared controller, on :meth:`~safestab.scenarios.ACCScenario.controller_system`.

        The model ``system`` itself with the headway barrier; with the braking barrier, the
        model whose lead brakes as hard as the barrier allows (its condition then holds for
        every admissible lead).
        """
        return UniversalController(self.scenario.controller_system(system), clf, cbf, **options)

    def excitation_span(self) -> float:
        """``excitation_limit`` of ``M g``, in input units."""
        sc = self.scenario
        return sc.excitation_limit * sc.mass * sc.gravity / sc.input_scale

    def fixed_start(self, index: jax.Array) -> jax.Array:
        """The scenario's ``x0`` for every trial."""
        return jnp.asarray(self.scenario.x0, float)

    def trial_data(self, keys: jax.Array) -> dict[str, jax.Array]:
        """The lead profile: ``ends`` (S,) segment end times, s; ``acc`` (S,) m/s^2."""
        spec, g = self.spec, self.scenario.gravity
        if spec.lead_kind == "random":
            s = spec.lead_segments
            durations = jax.random.uniform(
                keys[0], (s,), minval=spec.lead_duration_min, maxval=spec.lead_duration_max
            )
            acc = jax.random.uniform(
                keys[1], (s,), minval=-spec.lead_decel_max * g, maxval=spec.lead_accel_max * g
            )
            return {"ends": jnp.cumsum(durations), "acc": acc}
        profile = np.asarray(self.scenario.lead_profile, float).reshape(-1, 2)
        return {"ends": jnp.asarray(profile[:, 0]), "acc": jnp.asarray(profile[:, 1])}


@dataclasses.dataclass(frozen=True)
class ObstacleTrials(ScenarioTrials):
    """The obstacle's trials: no per-trial data; the start grid under ``"fixed"``.

    ``initial.distribution = "fixed"`` starts trial ``i`` at start ``i mod S`` of the
    scenario's grid (:meth:`~safestab.scenarios.ObstacleScenario.start_states`, ``S``
    starts), so ``N = S`` trials visit each start once. The compared controllers run with
    the scenario's input limits (``controller.input_limit``), kept as its
    ``controller.limit_method`` says (:meth:`build_controller`). The scenario has no lead
    vehicle: ``lead.*`` keys are refused.
    """

    h_unit: ClassVar[str] = "m^2"
    state_names: ClassVar[str] = "x1 m, x2 m"
    kind: ClassVar[str] = "obstacle"

    def input_gain(self) -> str:
        """``learning.input_gain`` of the scenario file."""
        return self.scenario.input_gain

    def limit_method(self) -> str:
        """``controller.limit_method`` of the scenario file (``"projection"`` or ``"filter"``)."""
        return self.scenario.limit_method

    def build_controller(self, system: Any, clf: Any, cbf: Any, **options: Any) -> Any:
        """One compared controller, as ``controller.limit_method`` says.

        ``"filter"``: a :class:`~safestab.SafetyFilter` with the box as constraints; else a
        :class:`~safestab.UniversalController` projecting onto it (eq. (26)).
        """
        return self.scenario.limited_controller(system, clf, cbf, **options)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.spec.lead_kind != "fixed":
            raise ParameterError(
                f"montecarlo.lead.kind must be 'fixed' for the obstacle scenario {self.name!r} "
                f"(it has no lead vehicle), got {self.spec.lead_kind!r}"
            )

    def excitation_span(self) -> float:
        """``learning.excitation_limit``, m/s per component."""
        return self.scenario.excitation_limit

    def fixed_start(self, index: jax.Array) -> jax.Array:
        """Start ``index mod S`` of the start grid."""
        with jax.ensure_compile_time_eval():  # the grid is a constant, not traced
            starts = np.asarray(self.scenario.start_states())
        return jnp.asarray(starts)[index % starts.shape[0]]
