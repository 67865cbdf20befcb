"""Loss models of the network stage (roco_env.stages kind ``loss``, scenario keys
``comm.loss`` and ``comm.loss_params``; docs/network.md).

A model says which messages (one per link and step, links as (receiver, sender) agent
indices) are lost; draws come from the generator passed in:

* ``none`` (default): nothing is lost;
* ``bernoulli``: each message independently with probability ``loss_rate``;
* ``gilbert_elliott``: bursty loss, a two-state Markov chain per link (Gilbert's
  model: every message of the bad state is lost, none of the good state), with the
  share of lost messages ``loss_rate`` and the mean length of a loss burst
  ``burst_length`` messages: P(bad -> good) = 1 / burst_length and P(good -> bad) =
  loss_rate / ((1 - loss_rate) burst_length). A link's first message draws its state
  from the stationary law; each later one moves the chain one step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from roco_env.scenario import CommConfig
from roco_env.schema import ConfigError, build, spec

__all__ = ["BernoulliLossParams", "GilbertElliottParams", "LossModel"]


class LossModel(Protocol):
    """What a loss stage's factory returns."""

    def reset(self) -> None:
        """Forget every link's state (a new episode)."""

    def lost(self, rng: np.random.Generator, links: Sequence[tuple[int, int]]) -> np.ndarray:
        """(n,) bool: which of the messages on ``links`` ((receiver, sender) pairs, one
        message each, in this order) are lost."""


@dataclass
class BernoulliLossParams:
    """``bernoulli``: independent losses."""

    loss_rate: float = spec(0.1, low=0.0, high=1.0, doc="probability that a message is lost")


@dataclass
class GilbertElliottParams:
    """``gilbert_elliott``: bursty losses."""

    loss_rate: float = spec(0.1, low=0.0, high=1.0, high_open=True,
                            doc="share of lost messages in the long run")
    burst_length: float = spec(3.0, low=1.0, high=1e6,
                               doc="mean number of messages a loss burst lasts")

    def __post_init__(self) -> None:
        """The rule joining the two: a good spell lasts at least one message."""
        if self.loss_rate > self.burst_length / (1.0 + self.burst_length):
            raise ConfigError(
                f"comm.loss_params.loss_rate={self.loss_rate!r} cannot be reached with "
                f"comm.loss_params.burst_length={self.burst_length!r}: a good spell lasts at "
                "least one message, so the loss rate is at most burst_length / (burst_length "
                f"+ 1) = {self.burst_length / (1.0 + self.burst_length):.4g}; lengthen the "
                "bursts or lower the rate")


class NoLoss:
    """``none``: every message arrives."""

    @classmethod
    def from_config(cls, config: CommConfig) -> NoLoss:
        return cls()

    def reset(self) -> None:
        """Nothing to forget."""

    def lost(self, rng: np.random.Generator, links: Sequence[tuple[int, int]]) -> np.ndarray:
        return np.zeros(len(links), dtype=bool)


class BernoulliLoss(NoLoss):
    """``bernoulli``: each message lost with probability ``loss_rate``."""

    def __init__(self, loss_rate: float) -> None:
        self.loss_rate = loss_rate

    @classmethod
    def from_config(cls, config: CommConfig) -> BernoulliLoss:
        params = build(BernoulliLossParams, dict(config.loss_params), where="comm",
                       prefix="comm.loss_params.")
        return cls(params.loss_rate)

    def lost(self, rng: np.random.Generator, links: Sequence[tuple[int, int]]) -> np.ndarray:
        return rng.random(len(links)) < self.loss_rate


class GilbertElliottLoss:
    """``gilbert_elliott``: a two-state chain per link (module docstring)."""

    def __init__(self, loss_rate: float, burst_length: float) -> None:
        GilbertElliottParams(loss_rate, burst_length)  # the rule joining the two
        self.loss_rate = loss_rate
        self.recover = 1.0 / burst_length  # P(bad -> good)
        self.fail = loss_rate * self.recover / (1.0 - loss_rate)  # P(good -> bad)
        self._bad: dict[tuple[int, int], bool] = {}

    @classmethod
    def from_config(cls, config: CommConfig) -> GilbertElliottLoss:
        params = build(GilbertElliottParams, dict(config.loss_params), where="comm",
                       prefix="comm.loss_params.")
        return cls(params.loss_rate, params.burst_length)

    def reset(self) -> None:
        self._bad.clear()

    def lost(self, rng: np.random.Generator, links: Sequence[tuple[int, int]]) -> np.ndarray:
        draws = rng.random(len(links))
        out = np.zeros(len(links), dtype=bool)
        for k, (link, u) in enumerate(zip(links, draws.tolist(), strict=True)):
            bad = self._bad.get(link)
            if bad is None:
                bad = u < self.loss_rate
            else:
                bad = u >= self.recover if bad else u < self.fail
            self._bad[link] = out[k] = bad
        return out
