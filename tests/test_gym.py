"""The Gymnasium wrapper (safestab.gym) on a Gymnasium environment written here.

A robot on a line (position p, speed command u in [-2, 2] m/s held for 0.1 s) must stay
0.5 m short of a wall at p = 10 m; the episode ends with a crash where p >= 10. The oracle is
the environment's own crash flag and the action mapping written by hand.
"""

import gymnasium
import jax.numpy as jnp
import numpy as np
import pytest

import safestab as ss
from safestab.gym import SafetyWrapper

SPEED = 2.0  # m/s, the actuator's limit
DT = 0.1


class Wall(gymnasium.Env):
    """p' = u (exact for a held u); the action a in [-1, 1] is u = 2 a."""

    action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (1,), np.float64)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = np.array([self.np_random.uniform(0.0, 8.0)])
        return self.x.copy(), {}

    def step(self, action):
        self.x = self.x + SPEED * float(np.clip(action[0], -1, 1)) * DT
        crashed = bool(self.x[0] >= 10.0)
        return self.x.copy(), 0.0, crashed, False, {"crashed": crashed}


ROBOT = ss.ControlAffineSystem(lambda x: jnp.zeros(1), lambda x: jnp.ones((1, 1)), 1)
# h >= 0 keeps the robot 0.5 m short of the wall (a crash is h <= -0.5); with beta dt <= 1
# the held input keeps it between the samples too (docs/deployed.md: h'' = 0 here)
STOP = ss.CBF(lambda x: 9.5 - x[0], beta=1.0)


def _episodes(env, n=8):
    crashes, interventions, statuses = 0, [], set()
    for seed in range(n):
        env.reset(seed=seed)
        for _ in range(200):
            _, _, done, _, info = env.step(np.array([1.0], np.float32))  # full throttle
            if "safestab" in info:
                interventions.append(info["safestab"]["intervention"])
                statuses.add(info["safestab"]["status"])
            if done:
                crashes += info["crashed"]
                break
    return crashes, interventions, statuses


def test_the_wrapper_keeps_a_full_throttle_policy_off_the_wall():
    assert _episodes(Wall())[0] == 8  # unfiltered, every episode crashes
    filt = ss.SafetyFilter(ROBOT, STOP, u_min=-SPEED, u_max=SPEED)
    env = SafetyWrapper(Wall(), filt, state=lambda env, obs: obs)
    crashes, interventions, statuses = _episodes(env)
    assert crashes == 0
    assert max(interventions) > 0.9 and statuses == {"OK"}  # it brakes: action 1 -> about 0


def test_the_action_maps_to_the_filters_input_and_back():
    filt = ss.SafetyFilter(ROBOT, STOP, u_min=-SPEED, u_max=SPEED)
    env = SafetyWrapper(Wall(), filt, state=lambda env, obs: obs)
    np.testing.assert_allclose(env.action_to_input([0.25]), [0.5])  # u = 2 a, by hand
    np.testing.assert_allclose(env.input_to_action([-2.0]), [-1.0])
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.5], np.float32))
    report = info["safestab"]
    np.testing.assert_allclose(report["h"], [9.5 - report["x"][0]])
    assert report["status"] == "OK" and report["intervention"] == pytest.approx(0.0, abs=1e-7)


def test_bad_wrapper_arguments_are_named():
    filt = ss.SafetyFilter(ROBOT, STOP, u_min=-SPEED, u_max=SPEED)
    with pytest.raises(ss.InputTypeError, match="safety_filter must be a SafetyFilter"):
        SafetyWrapper(Wall(), "filter", state=lambda env, obs: obs)
    with pytest.raises(ss.ParameterError, match="give input_low and input_high together"):
        SafetyWrapper(Wall(), filt, state=lambda env, obs: obs, input_low=[-1.0])
    with pytest.raises(gymnasium.error.ResetNeeded):
        SafetyWrapper(Wall(), filt, state=lambda env, obs: obs).step(np.zeros(1))


def test_a_one_sided_filter_maps_its_unbounded_side_to_the_action_space():
    # u_max alone: the upper input is the filter's 2 m/s, the lower the action space's -1
    filt = ss.SafetyFilter(ROBOT, STOP, u_max=SPEED)
    env = SafetyWrapper(Wall(), filt, state=lambda env, obs: obs)
    np.testing.assert_allclose(env.action_to_input([1.0]), [2.0])
    np.testing.assert_allclose(env.action_to_input([-1.0]), [-1.0])  # by hand: low_a = -1
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.5], np.float32))
    assert info["safestab"]["status"] == "OK"
    with pytest.raises(ss.ParameterError, match="input_high must be finite"):
        SafetyWrapper(Wall(), filt, state=lambda env, obs: obs, input_low=[-1.0],
                      input_high=[np.inf])  # fmt: skip
