"""What a message weighs: its byte layout, encoder and decoder, and the budget rule.

A message is little-endian bytes (docs/network.md, "Payload"):

* header, :data:`~roco_env.scenario.MESSAGE_HEADER_BYTES` = 44 bytes: sender index
  (uint32), scan time (float64, s), reported pose x, y (float64, m) and yaw (float64,
  rad), box count n (uint32), feature codec (uint32: 0 = no map, 1 + its index in
  :data:`~roco_env.scenario.FEATURE_CODECS`);
* n boxes, 44 bytes each: the boxes (n, 7), then their uncertainties (n, 3), then their
  scores (n,), all float32;
* a feature map (C, H, W) when the codec is not 0: C, H, W (3 x uint32), then
  ``dense``: every value; ``sparse``: the count m of cells sent (uint32), their flat
  indices h * W + w (m x uint32) and their C values each (m x C); values float32
  (``_f32``) or float16 (``_f16``). A sparse map sends the cells with any non-zero
  channel.

The budget rule (:func:`fit_budget`): the header always; then boxes, highest score first
(ties: the earlier box), as many as fit; then the feature map: a dense one whole if it
fits in what is left, else not at all; a sparse one cell by cell, largest magnitude
(the L2 norm of its channels) first (ties: the lower index), as many as fit.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from roco_env.scenario import FEATURE_CODECS, MESSAGE_HEADER_BYTES

__all__ = ["BOX_BYTES", "Payload", "decode", "encode", "fit_budget", "payload_bytes"]

_HEADER = struct.Struct("<Id3dII")
_FEATURE_SHAPE = struct.Struct("<3I")
_COUNT = struct.Struct("<I")
_INDEX_BYTES = 4
BOX_BYTES = 11 * 4  # 7 box values, 3 uncertainties, 1 score as float32
_VALUE_DTYPES = {"f32": np.dtype("<f4"), "f16": np.dtype("<f2")}


def _codec(codec: str) -> tuple[bool, np.dtype]:
    """(sparse, value dtype) of a codec name; ValueError naming comm.feature_codec."""
    if codec not in FEATURE_CODECS:
        raise ValueError(f"comm.feature_codec must be one of {list(FEATURE_CODECS)}; "
                         f"got {codec!r}")
    layout, bits = codec.split("_")
    return layout == "sparse", _VALUE_DTYPES[bits]


@dataclass(frozen=True)
class Payload:
    """One message's content: sender index, scan time (s), reported pose (3,) (x m, y m,
    yaw rad), boxes (n, 7), uncertainty (n, 3), scores (n,) in the sender's frame; features
    (C, H, W) float32 or None, sent with ``codec``."""

    sender: int
    time: float
    pose: np.ndarray
    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray
    features: np.ndarray | None = None
    codec: str = "dense_f32"


def payload_bytes(n_boxes: int, feature_shape: tuple[int, int, int] | None = None,
                  codec: str = "dense_f32", cells: int | None = None) -> int:
    """Bytes of a message with ``n_boxes`` boxes and, when ``feature_shape`` (C, H, W) is
    given, a map sent with ``codec`` (``cells``: the cells a sparse map sends)."""
    size = MESSAGE_HEADER_BYTES + BOX_BYTES * int(n_boxes)
    if feature_shape is None:
        return size
    sparse, dtype = _codec(codec)
    channels, height, width = feature_shape
    size += _FEATURE_SHAPE.size
    if not sparse:
        return size + channels * height * width * dtype.itemsize
    if cells is None:
        raise ValueError("payload_bytes: a sparse map needs the number of cells it sends")
    return size + _COUNT.size + int(cells) * (_INDEX_BYTES + channels * dtype.itemsize)


def _sent_cells(features: np.ndarray) -> np.ndarray:
    """Flat indices of the cells a sparse map sends (any channel non-zero), ascending."""
    return np.flatnonzero(np.any(features != 0, axis=0))


def encode(payload: Payload) -> bytes:
    """The message's bytes (module docstring); ``len`` equals :func:`payload_bytes`."""
    boxes = np.asarray(payload.boxes, dtype="<f4").reshape(-1, 7)
    n = boxes.shape[0]
    codec = 0 if payload.features is None else 1 + FEATURE_CODECS.index(payload.codec)
    parts = [_HEADER.pack(payload.sender, payload.time, *map(float, payload.pose), n, codec),
             boxes.tobytes(), np.asarray(payload.uncertainty, dtype="<f4").reshape(n, 3).tobytes(),
             np.asarray(payload.scores, dtype="<f4").reshape(n).tobytes()]
    if payload.features is not None:
        sparse, dtype = _codec(payload.codec)
        features = np.asarray(payload.features)
        channels, height, width = features.shape
        parts.append(_FEATURE_SHAPE.pack(channels, height, width))
        if sparse:
            cells = _sent_cells(features)
            flat = features.reshape(channels, height * width)
            parts += [_COUNT.pack(cells.size), cells.astype("<u4").tobytes(),
                      np.ascontiguousarray(flat[:, cells].T).astype(dtype).tobytes()]
        else:
            parts.append(features.astype(dtype).tobytes())
    return b"".join(parts)


def decode(data: bytes) -> Payload:
    """The payload of a message's bytes (float32 values; a map as float32 (C, H, W),
    zero where a sparse map sent no cell)."""
    sender, time, x, y, yaw, n, codec_id = _HEADER.unpack_from(data, 0)
    at = _HEADER.size

    def read(count: int, dtype: str | np.dtype) -> np.ndarray:
        nonlocal at
        values = np.frombuffer(data, dtype=dtype, count=count, offset=at)
        at += values.nbytes
        return values

    boxes = read(7 * n, "<f4").reshape(n, 7)
    uncertainty = read(3 * n, "<f4").reshape(n, 3)
    scores = read(n, "<f4")
    features, codec = None, "dense_f32"
    if codec_id:
        codec = FEATURE_CODECS[codec_id - 1]
        sparse, dtype = _codec(codec)
        channels, height, width = _FEATURE_SHAPE.unpack_from(data, at)
        at += _FEATURE_SHAPE.size
        if sparse:
            (count,) = _COUNT.unpack_from(data, at)
            at += _COUNT.size
            cells = read(count, "<u4").astype(np.int64)
            flat = np.zeros((channels, height * width), dtype=np.float32)
            flat[:, cells] = read(count * channels, dtype).reshape(count, channels).T
            features = flat.reshape(channels, height, width)
        else:
            features = read(channels * height * width, dtype).astype(np.float32).reshape(
                channels, height, width)
    if at != len(data):
        raise ValueError(f"decode: {len(data) - at} bytes left after the message")
    return Payload(sender, time, np.array([x, y, yaw]), boxes, uncertainty, scores, features,
                   codec)


def fit_budget(scores: np.ndarray, features: np.ndarray | None, codec: str,
               budget: int | None) -> tuple[np.ndarray, np.ndarray | None, int]:
    """What of a message fits ``budget`` bytes (None: everything), by the module's rule.

    scores (n,): the boxes' scores; features (C, H, W) or None. Returns the indices of
    the boxes kept (ascending), the map as sent (float32: cells left out zeroed, values
    rounded to the codec's precision; None when the message carries no map: none given,
    or too little room left for it) and the message's bytes.
    """
    scores = np.asarray(scores, dtype=float).reshape(-1)
    room = np.inf if budget is None else budget - MESSAGE_HEADER_BYTES
    if room < 0:
        raise ValueError(f"comm.budget_bytes={budget} is smaller than a message header "
                         f"({MESSAGE_HEADER_BYTES} bytes)")
    n_boxes = int(min(scores.shape[0], room // BOX_BYTES))
    kept = np.sort(np.argsort(-scores, kind="stable")[:n_boxes])
    size = payload_bytes(n_boxes)
    if features is None:
        return kept, None, size
    room -= BOX_BYTES * n_boxes
    sparse, dtype = _codec(codec)
    sent = np.asarray(features, dtype=np.float32).astype(dtype).astype(np.float32)
    channels = sent.shape[0]
    if not sparse:
        extra = payload_bytes(0, sent.shape, codec) - MESSAGE_HEADER_BYTES
        return (kept, sent, size + extra) if extra <= room else (kept, None, size)
    cells = _sent_cells(sent)
    per_cell = _INDEX_BYTES + channels * dtype.itemsize
    fit = int(min(cells.size, max(room - _FEATURE_SHAPE.size - _COUNT.size, -1) // per_cell))
    if fit < 0:
        return kept, None, size
    if fit < cells.size:
        flat = sent.reshape(channels, -1)
        magnitude = np.linalg.norm(flat[:, cells], axis=0)
        dropped = cells[np.argsort(-magnitude, kind="stable")[fit:]]
        flat[:, dropped] = 0.0
    return kept, sent, payload_bytes(n_boxes, sent.shape, codec, fit)
