"""With the network off (``comm.delay: none``, the default) episodes are those of the code
before the network stage existed.

How that survives a change of CPU: tests/data/network_off.npz holds four seeded episodes
(every observation, reward and info, flattened to arrays by path; per episode one
lzma-compressed buffer of them all and its layout as JSON, read without pickle), and
the test compares
a new run with them: discrete values (ints, bools, texts, the structure of every dict
and list) exactly, floats to rounding (numpy's SIMD exp / sin / cos differ by CPU in the
last bit, and an episode carries that through its chain of poses, boxes and metrics:
relative 1e-9 for float64, 1e-6, a few ulps, for float32). The arrays are that code's
episodes because the script writing them (``python tests/test_network_off.py``) refuses
unless every episode's sha256 digest (conftest.episode_digest: every byte) equals the
one in tests/data/network_off.json, recorded with the code before the network stage
(re-recorded once since: the privileged info gained the attack stage's truth,
``attacker`` and ``collab_attackers``; with those two entries left out the digests were
those of the first record). Bytes compare only on the CPU that recorded them, so only
that script compares digests. The comm stage's own random stream is spawned after the
other three, so turning it on changes no draw of traffic, noise or sensing either.

Regenerate only for a deliberate, documented change of results, on a CPU whose digests
match (``--new-digests`` re-records the digests too: a deliberate change).
"""

from __future__ import annotations

import json
import lzma
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_equal_to_rounding, episode_digest

import roco_env

DATA = Path(__file__).parent / "data"
RECORD, ARRAYS = DATA / "network_off.json", DATA / "network_off.npz"
# (scenario, overrides, seed, steps): an RSU crossing, a dense highway, the realistic
# detector with pose noise, and select mode (which runs the env's aligners).
CASES = (
    ("urban_intersection", {}, 3, 4),
    ("highway_dense", {"sigma_t": 0.4, "sigma_r": 0.4}, 5, 4),
    ("crowded_intersection", {"noise_model": "ar1", "cavs": 3}, 1, 3),
    ("v2x_crossroad", {"action.mode": "select"}, 2, 3),
)
RTOL = {np.dtype(np.float64): 1e-9, np.dtype(np.float32): 1e-6}


def _key(case: tuple) -> str:
    scenario, overrides, seed, steps = case
    return f"{scenario}|{json.dumps(overrides, sort_keys=True)}|seed={seed}|steps={steps}"


def _flat(value: object, path: str, out: dict[str, np.ndarray]) -> None:
    """Every leaf of ``value`` (dicts by sorted key, lists and tuples by index) as an array
    under its path; a dict's or list's own entry holds its keys or length; a leaf that is
    not a number, bool or array is kept as its text."""
    if isinstance(value, dict):
        keys = sorted(value, key=str)
        out[path] = np.array([str(k) for k in keys])
        for key in keys:
            _flat(value[key], f"{path}/{key}", out)
    elif isinstance(value, (list, tuple)):
        out[path] = np.array(len(value))
        for index, item in enumerate(value):
            _flat(item, f"{path}/{index}", out)
    elif isinstance(value, (np.ndarray, np.generic, float, int, bool)):
        out[path] = np.asarray(value)
    else:
        out[path] = np.array(repr(value))


def episode_arrays(case: tuple) -> dict[str, np.ndarray]:
    """The episode of ``case`` (zero actions; the first choice in select mode), flattened:
    the reset's observations and infos, then each step's (observations, rewards,
    terminations, truncations, infos)."""
    scenario, overrides, seed, steps = case
    env = roco_env.parallel_env(scenario, max_cycles=steps, **overrides)
    record = [env.reset(seed=seed)]
    while env.agents:
        record.append(env.step({a: np.zeros(env.action_space(a).shape,
                                            dtype=env.action_space(a).dtype)
                                for a in env.agents}))
    out: dict[str, np.ndarray] = {}
    _flat(record, _key(case), out)
    return out


def _packed(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """An episode's arrays as its layout (JSON text: path, dtype, shape, byte offset of
    each) and one buffer of their bytes, each lzma-compressed."""
    layout, parts, at = [], [], 0
    for path, value in arrays.items():
        data = np.ascontiguousarray(value).tobytes()
        layout.append([path, value.dtype.str, list(value.shape), at])
        parts.append(data)
        at += len(data)
    return {"layout": _compressed(json.dumps(layout).encode()),
            "data": _compressed(b"".join(parts))}


def _compressed(data: bytes) -> np.ndarray:
    return np.frombuffer(lzma.compress(data, preset=9), dtype=np.uint8)


def _unpacked(layout: np.ndarray, data: np.ndarray) -> dict[str, np.ndarray]:
    raw = lzma.decompress(data.tobytes())
    return {path: np.frombuffer(raw, dtype=np.dtype(dtype), count=int(np.prod(shape)),
                                offset=at).reshape(shape)
            for path, dtype, shape, at in json.loads(lzma.decompress(layout.tobytes()))}


def _assert_same(got: np.ndarray, recorded: np.ndarray, path: str) -> None:
    assert got.dtype == recorded.dtype and got.shape == recorded.shape, path
    if recorded.dtype.kind == "f":
        assert_equal_to_rounding(got, recorded, rtol=RTOL[recorded.dtype], err_msg=path)
    else:
        np.testing.assert_array_equal(got, recorded, err_msg=path)


@pytest.mark.parametrize("case", CASES, ids=lambda case: case[0])
def test_network_off_episodes_are_the_recorded_ones(case):
    index = CASES.index(case)
    with np.load(ARRAYS, allow_pickle=False) as data:
        recorded = _unpacked(data[f"{index}/layout"], data[f"{index}/data"])
    got = episode_arrays(case)
    assert sorted(got) == sorted(recorded)  # the same structure: every key, every length
    for path, value in recorded.items():
        _assert_same(got[path], value, path)


def test_the_comparison_sees_a_change_beyond_rounding():
    recorded = np.array([1.0, 250.0])
    _assert_same(recorded * (1 + 1e-13), recorded, "rounding")
    with pytest.raises(AssertionError):
        _assert_same(recorded + [0.0, 1e-5], recorded, "a change")
    with pytest.raises(AssertionError):
        _assert_same(np.array([1, 2]), np.array([1, 3]), "a discrete change")


def _write(new_digests: bool) -> None:
    digests = json.loads(RECORD.read_text())
    arrays: dict[str, np.ndarray] = {}
    for index, case in enumerate(CASES):
        digest = episode_digest(*case)
        if digest != digests[_key(case)] and not new_digests:
            sys.exit(f"{_key(case)}: digest {digest} differs from the recorded one: this code "
                     "or CPU does not give the recorded episodes (--new-digests for a "
                     "deliberate change)")
        digests[_key(case)] = digest
        arrays.update({f"{index}/{name}": value
                       for name, value in _packed(episode_arrays(case)).items()})
    np.savez(ARRAYS, **arrays)
    RECORD.write_text(json.dumps(digests, indent=1) + "\n")
    print(f"wrote {ARRAYS} and {RECORD}")


if __name__ == "__main__":
    _write("--new-digests" in sys.argv[1:])
