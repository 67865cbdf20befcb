"""The network between the collaborators' messages and the ego (scenario section ``comm``,
docs/network.md): delays (:mod:`roco_env.comm.delay`), losses (:mod:`roco_env.comm.loss`),
message sizes and the budget (:mod:`roco_env.comm.payload`), asynchronous sensors and the
ego's buffers (:mod:`roco_env.comm.delivery`). Off by default: every message then arrives
at once, whole, and the episode is the one without this stage."""

from roco_env.comm.delivery import (
    Delivery,
    Network,
    NetworkStats,
    Scan,
    instant_inbox,
    network_active,
    received_maps,
)
from roco_env.comm.payload import Payload, decode, encode, fit_budget, payload_bytes

__all__ = ["Delivery", "Network", "NetworkStats", "Payload", "Scan", "decode", "encode",
           "fit_budget", "instant_inbox", "network_active", "payload_bytes", "received_maps"]
