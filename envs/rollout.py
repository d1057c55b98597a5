"""One way to run an episode: ``rollout(env, policy, spec)``.

Every place that drives a whole episode (data collection, evaluation, the preview, benchmarks and tests) goes
through here, so the order of reset, policy reset, the planner's ``bind`` and the step loop is written once.

A policy is anything with ``reset(seed)`` and ``act(obs, info) -> action``; one that also has ``bind(env)`` (the
privileged planner) is handed the env after every reset, because it reads the true state.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np


class Policy(Protocol):
    name: str

    def reset(self, seed: int | None = None) -> None: ...

    def act(self, obs: dict, info: dict) -> np.ndarray: ...


@dataclass
class Episode:
    """What an episode ended with: the last ``info`` (its ``outcome`` is the paper's metrics), and how it ended."""

    info: dict
    terminated: bool
    steps: int

    @property
    def outcome(self) -> dict:
        return self.info["outcome"]


StepHook = Callable[[dict, np.ndarray, float, dict], Any]
ResetHook = Callable[[dict, dict], Any]


def rollout(
    env,
    policy: Policy,
    spec,
    on_step: StepHook | None = None,
    max_steps: int | None = None,
    on_reset: ResetHook | None = None,
) -> Episode:
    """Replay scenario ``spec`` under ``policy`` until the env ends the episode (or ``max_steps`` steps).

    ``on_reset(obs, info)`` sees the first observation; ``on_step(obs, action, reward, info)`` sees every
    transition after it happened (e.g. to record frames).
    """
    obs, info = env.reset(options={"scenario": spec})
    if on_reset is not None:
        on_reset(obs, info)
    policy.reset(spec.seed)
    bind = getattr(policy, "bind", None)
    if bind is not None:
        bind(env)
    steps, terminated = 0, False
    while True:
        action = policy.act(obs, info)
        obs, reward, terminated, truncated, info = env.step(action)
        steps += 1
        if on_step is not None:
            on_step(obs, action, reward, info)
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            return Episode(info=info, terminated=bool(terminated), steps=steps)
