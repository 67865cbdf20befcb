"""Delay models of the network stage (roco_env.stages kind ``delay``, scenario keys
``comm.delay`` and ``comm.delay_params``; docs/network.md).

A model gives every message (one per link and step) its delay in seconds, from the
message's payload size (bytes), the true distance between sender and receiver when it
is sent (m) and the frame length (s); draws come from the generator passed in:

* ``none`` (default): no delay;
* ``fixed``: ``delay_ms`` for every message;
* ``uniform``: U(0, ``delay_ms``) per message;
* ``opencood``: OpenCOOD's "real" latency: U(0, ``overhead_ms``) + payload bits /
  ``bandwidth_mbps`` + ``processing_ms``, rounded down to whole frames;
* ``distance``: ``delay_ms`` + ``ms_per_m`` x the distance.

The factory of each is called with the scenario's :class:`~roco_env.scenario.CommConfig`
and reads ``delay_params`` through the model's parameter dataclass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from roco_env.scenario import CommConfig
from roco_env.schema import build, spec

__all__ = ["DelayModel", "DistanceDelayParams", "FixedDelayParams", "OpenCOODDelayParams",
           "UniformDelayParams"]

_MAX_MS = 60000.0


class DelayModel(Protocol):
    """What a delay stage's factory returns."""

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        """Delays (n,) in seconds (>= 0) of n messages of ``payload_bytes`` (n,) bytes, sent
        over ``distances`` (n,) m, with frames of ``frame_s`` s."""


@dataclass
class FixedDelayParams:
    """``fixed``: one delay for every message."""

    delay_ms: float = spec(100.0, low=0.0, high=_MAX_MS, doc="delay of every message, ms")


@dataclass
class UniformDelayParams:
    """``uniform``: each message's delay drawn uniformly."""

    delay_ms: float = spec(100.0, low=0.0, high=_MAX_MS,
                           doc="largest delay, ms: each message's is U(0, delay_ms)")


@dataclass
class OpenCOODDelayParams:
    """``opencood``: OpenCOOD's "real" asynchronous mode."""

    overhead_ms: float = spec(100.0, low=0.0, high=_MAX_MS,
                              doc="largest random overhead, ms: U(0, overhead_ms) per message")
    bandwidth_mbps: float = spec(27.0, low=0.0, high=1e6, low_open=True,
                                 doc="link rate, Mbit/s: the payload takes its bits / rate")
    processing_ms: float = spec(10.0, low=0.0, high=_MAX_MS, doc="processing time, ms")


@dataclass
class DistanceDelayParams:
    """``distance``: a delay that grows with the range between sender and receiver."""

    delay_ms: float = spec(10.0, low=0.0, high=_MAX_MS, doc="delay at zero range, ms")
    ms_per_m: float = spec(1.0, low=0.0, high=1000.0, doc="growth with the range, ms per m")


def _params(cls: type, config: CommConfig):
    return build(cls, dict(config.delay_params), where="comm", prefix="comm.delay_params.")


class NoDelay:
    """``none``: every message arrives in the step it is sent."""

    @classmethod
    def from_config(cls, config: CommConfig) -> NoDelay:
        return cls()

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        return np.zeros(len(payload_bytes))


class FixedDelay:
    """``fixed``: ``delay_ms`` for every message."""

    PARAMS = FixedDelayParams

    def __init__(self, delay_ms: float) -> None:
        self.delay_s = delay_ms / 1000.0

    @classmethod
    def from_config(cls, config: CommConfig) -> FixedDelay:
        return cls(_params(cls.PARAMS, config).delay_ms)

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        return np.full(len(payload_bytes), self.delay_s)


class UniformDelay(FixedDelay):
    """``uniform``: U(0, ``delay_ms``) per message."""

    PARAMS = UniformDelayParams

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        return rng.uniform(0.0, self.delay_s, len(payload_bytes))


class OpenCOODDelay:
    """``opencood``: (U(0, overhead) + payload bits / rate + processing) ms, rounded down to
    whole frames (OpenCOOD's ``time_delay_calculation``, whose frames are 100 ms)."""

    def __init__(self, params: OpenCOODDelayParams) -> None:
        self.params = params

    @classmethod
    def from_config(cls, config: CommConfig) -> OpenCOODDelay:
        return cls(_params(OpenCOODDelayParams, config))

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        p = self.params
        transfer_ms = np.asarray(payload_bytes, dtype=float) * 8.0 / (p.bandwidth_mbps * 1e3)
        total_ms = rng.uniform(0.0, p.overhead_ms, len(payload_bytes)) + transfer_ms \
            + p.processing_ms
        frame_ms = frame_s * 1000.0
        return np.floor(total_ms / frame_ms + 1e-9) * frame_s


class DistanceDelay:
    """``distance``: ``delay_ms`` + ``ms_per_m`` x the sender-receiver distance."""

    def __init__(self, delay_ms: float, ms_per_m: float) -> None:
        self.delay_ms, self.ms_per_m = delay_ms, ms_per_m

    @classmethod
    def from_config(cls, config: CommConfig) -> DistanceDelay:
        params = _params(DistanceDelayParams, config)
        return cls(params.delay_ms, params.ms_per_m)

    def draw(self, rng: np.random.Generator, payload_bytes: np.ndarray, distances: np.ndarray,
             frame_s: float) -> np.ndarray:
        return (self.delay_ms + self.ms_per_m * np.asarray(distances, dtype=float)) / 1000.0


def frames_late(delays_s: np.ndarray, frame_s: float) -> np.ndarray:
    """(n,) int: the frames after its own that a message sent with ``delays_s`` reaches an
    ego that fuses once per frame: ceil(delay / frame) (a delay of exactly k frames is k)."""
    return np.ceil(np.asarray(delays_s, dtype=float) / frame_s - 1e-9).astype(np.int64).clip(0)

