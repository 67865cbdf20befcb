"""The network stage (roco_env.comm): delays, losses, budgets, asynchronous sensors and the
ego's buffers; what the agents observe of it; its errors on bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import episode_digest, run_python

import roco_env
from roco_env.comm import Payload, decode, encode, fit_budget, payload_bytes, received_maps
from roco_env.comm.delay import FixedDelay, FixedDelayParams, OpenCOODDelay, OpenCOODDelayParams
from roco_env.comm.loss import GilbertElliottLoss
from roco_env.env import METRIC_INFO_KEYS, NETWORK_INFO_KEYS
from roco_env.pipeline import Pipeline
from roco_env.scenario import MESSAGE_HEADER_BYTES, ConfigError, load_scenario

SCENE = "highway_dense"
DT = 0.1  # highway_dense's traffic.dt


def _frames(steps: int, seed: int = 4, **overrides) -> list:
    """The pipeline's frames of ``steps`` + 1 steps of highway_dense (3 CAVs)."""
    pipeline = Pipeline(load_scenario(SCENE, cavs=3, **overrides))
    frames = [pipeline.reset(np.random.default_rng(seed))]
    frames += [pipeline.advance() for _ in range(steps)]
    return frames


def _slot(view, sender: int) -> int:
    return view.collaborators.index(sender)


MODELS = (
    {"delay": "fixed", "delay_ms": 100},
    {"delay": "uniform", "delay_ms": 300},
    {"delay": "opencood"},
    {"delay": "distance"},
    {"loss": "bernoulli", "loss_rate": 0.3},
    {"loss": "gilbert_elliott", "loss_rate": 0.3},
    {"comm.budget_bytes": 400},
    {"comm.sensor_offset_ms": {"cav_1": 40.0}},
    {"delay": "fixed", "delay_ms": 200, "comm.compensation": "track"},
)


@pytest.mark.parametrize("overrides", MODELS, ids=lambda o: "-".join(map(str, o.values())))
def test_every_comm_model_is_deterministic(overrides):
    first = episode_digest(SCENE, {"cavs": 3, **overrides}, 2, 4)
    assert episode_digest(SCENE, {"cavs": 3, **overrides}, 2, 4) == first


def test_a_zero_delay_gives_the_episode_of_the_network_off():
    off = roco_env.parallel_env(SCENE, max_cycles=4, cavs=3)
    on = roco_env.parallel_env(SCENE, max_cycles=4, cavs=3, delay="fixed", delay_ms=0)
    observed = [off.reset(seed=3)[0], on.reset(seed=3)[0]]
    while off.agents:
        zeros = {a: np.zeros((off.config.max_collaborators, 3)) for a in off.agents}
        (obs_off, rewards_off, *_), (obs_on, rewards_on, *_) = off.step(zeros), on.step(zeros)
        assert rewards_on == rewards_off
        observed = [obs_off, obs_on]
        for agent, seen in obs_off.items():
            for key, value in seen.items():
                np.testing.assert_array_equal(obs_on[agent][key], value)
            assert np.all(obs_on[agent]["collab_age"] == 0.0)
            np.testing.assert_array_equal(obs_on[agent]["collab_new"], seen["collab_mask"])
    assert set(observed[1]["cav_0"]) - set(observed[0]["cav_0"]) == {"collab_age", "collab_new"}
    assert on.observation_space("cav_0").contains(observed[1]["cav_0"])


def test_the_network_draws_no_number_of_the_other_stages():
    off, late = _frames(3), _frames(3, delay="uniform", delay_ms=400)
    for a, b in zip(off, late, strict=True):
        np.testing.assert_array_equal(a.reported_poses, b.reported_poses)
        np.testing.assert_array_equal(a.state.object_boxes, b.state.object_boxes)
        for da, db in zip(a.detections, b.detections, strict=True):
            np.testing.assert_array_equal(da.boxes, db.boxes)


@pytest.mark.parametrize("k", [1, 3])
def test_a_fixed_delay_of_k_frames_delivers_the_scan_of_k_steps_before(k):
    frames = _frames(6, delay="fixed", delay_ms=1000 * k * DT)
    checked = 0
    for step, frame in enumerate(frames):
        for view in frame.views:
            if step < k:
                assert view.collaborators == ()  # nothing has arrived yet
                continue
            np.testing.assert_allclose(view.collab_age, k * DT, atol=1e-12)
            assert view.collab_new.all()
            earlier = frames[step - k]
            for slot, sender in enumerate(view.collaborators):
                sent = earlier.detections[sender]
                np.testing.assert_array_equal(view.collab_boxes[slot], sent.boxes)
                np.testing.assert_array_equal(view.collab_scores[slot], sent.scores)
                np.testing.assert_array_equal(view.collab_poses[slot],
                                              earlier.reported_poses[sender])
                checked += 1
    assert checked > 10


class _Scripted:
    """A delay or loss model following a script: step -> delay (s) or lost (bool) of every
    message sent at that step (steps counted by calls)."""

    script: dict = {}

    def __init__(self, config=None):
        self.calls = 0

    def reset(self):
        self.calls = 0

    def draw(self, rng, payload_bytes, distances, frame_s):
        self.calls += 1
        return np.full(len(payload_bytes), self.script.get(self.calls - 1, 0.0))

    def lost(self, rng, links):
        self.calls += 1
        return np.full(len(links), self.script.get(self.calls - 1, False))


def test_a_lost_message_is_never_fused(registered):
    class Lossy(_Scripted):
        script = {1: True, 2: True, 4: True}

    registered("loss", "scripted", Lossy)
    frames = _frames(5, loss="scripted")
    for step, frame in enumerate(frames):
        for view in frame.views:
            for slot, sender in enumerate(view.collaborators):
                held = step if step not in Lossy.script else max(
                    s for s in range(step) if s not in Lossy.script)
                np.testing.assert_array_equal(view.collab_boxes[slot],
                                              frames[held].detections[sender].boxes)
                assert view.collab_new[slot] == (step not in Lossy.script)
    assert frames[2].views[0].network["messages_lost"] == len(frames[2].views[0].collaborators)


def test_out_of_order_messages_keep_the_newest(registered):
    class Jumbled(_Scripted):
        # step 0's scan arrives at step 3, step 1's at step 2, later ones never
        script = {0: 3 * DT, 1: DT, 2: 99.0, 3: 99.0, 4: 99.0}

    registered("delay", "scripted", Jumbled)
    frames = _frames(4, delay="scripted", **{"comm.max_age_ms": 60000.0})
    view = frames[2].views[0]
    assert view.collab_new.all()
    np.testing.assert_allclose(view.collab_age, DT)  # step 1's scan
    sender = view.collaborators[0]
    later = frames[3].views[0]
    slot = _slot(later, sender)
    np.testing.assert_array_equal(later.collab_boxes[slot], frames[1].detections[sender].boxes)
    assert not later.collab_new[slot]  # step 0's scan came, older: dropped
    np.testing.assert_allclose(later.collab_age[slot], 2 * DT)


def test_messages_older_than_the_max_age_are_dropped():
    frames = _frames(4, delay="fixed", delay_ms=200, **{"comm.max_age_ms": 150.0})
    assert all(view.collaborators == () for frame in frames for view in frame.views)


def test_reset_clears_every_buffer():
    pipeline = Pipeline(load_scenario(SCENE, cavs=3, delay="fixed", delay_ms=200,
                                      loss="gilbert_elliott", loss_rate=0.5))
    first = [pipeline.reset(np.random.default_rng(1))]
    first += [pipeline.advance() for _ in range(4)]
    again = pipeline.reset(np.random.default_rng(1))
    assert all(view.collaborators == () for view in again.views)  # nothing held, nothing late
    assert not pipeline.network._held
    assert {scan.sent for _, _, scan in pipeline.network._pending} == {0.0}  # sent just now
    second = [again] + [pipeline.advance() for _ in range(4)]
    for a, b in zip(first, second, strict=True):
        for va, vb in zip(a.views, b.views, strict=True):
            assert va.collaborators == vb.collaborators
            np.testing.assert_array_equal(va.collab_age, vb.collab_age)
            for ba, bb in zip(va.collab_boxes, vb.collab_boxes, strict=True):
                np.testing.assert_array_equal(ba, bb)


def test_traffic_infos_count_every_link_and_the_bytes_of_what_was_sent():
    frame = _frames(0, **{"comm.budget_bytes": 1000})[0]
    n_links = {k: 0 for k in range(len(frame.views))}
    for view in frame.views:
        for sender in view.collaborators:
            n_links[sender] += 1
    for agent, view in enumerate(frame.views):
        size = payload_bytes(min(len(frame.detections[agent].scores), 21))
        assert view.network["bytes_sent"] == n_links[agent] * size
        assert view.network["bytes_received"] == sum(
            payload_bytes(len(s)) for s in view.collab_scores)
        assert view.network["messages_lost"] == 0


def test_a_sensor_offset_shows_the_world_of_that_earlier_instant():
    offset = 0.08
    off = _frames(2, detector="ideal")[-1]
    late = _frames(2, detector="ideal", **{"comm.sensor_offset_ms": {"cav_1": 1000 * offset}})[-1]
    state = late.state
    sent = off.detections[1]
    ego = late.views[0]
    slot = _slot(ego, 1)
    np.testing.assert_allclose(ego.collab_age[slot], offset)
    own = state.object_velocities[list(state.object_ids).index(state.agent_object_ids[1])]
    np.testing.assert_allclose(ego.collab_poses[slot][:2], off.reported_poses[1][:2] - own * offset)
    then = state.agent_poses[1].copy()
    then[:2] -= own * offset
    for box, object_id in zip(ego.collab_boxes[slot], sent.object_ids, strict=True):
        row = list(state.object_ids).index(object_id)
        world = state.object_boxes[row, :2] - state.object_velocities[row] * offset
        c, s = np.cos(then[2]), np.sin(then[2])
        local = np.array([[c, s], [-s, c]]) @ (world - then[:2])
        np.testing.assert_allclose(box[:2], local, atol=1e-6)
    np.testing.assert_array_equal(ego.collab_boxes[_slot(ego, 2)],
                                  off.detections[2].boxes)  # no offset, unchanged


def test_bytes_per_message_match_the_payload_exactly():
    rng = np.random.default_rng(0)
    boxes, unc, scores = rng.random((9, 7)), rng.random((9, 3)), rng.random(9)
    features = rng.random((4, 6, 5)).astype(np.float32)
    features[:, rng.random((6, 5)) < 0.6] = 0.0
    cells = int(np.any(features != 0, axis=0).sum())
    for codec, carried in [("dense_f32", None), ("dense_f32", features),
                           ("dense_f16", features), ("sparse_f32", features),
                           ("sparse_f16", features)]:
        payload = Payload(3, 1.25, np.array([1.0, -2.0, 0.3]), boxes, unc, scores, carried,
                          codec)
        data = encode(payload)
        shape = None if carried is None else carried.shape
        assert len(data) == payload_bytes(9, shape, codec, cells)
        back = decode(data)
        assert (back.sender, back.time, back.codec) == (3, 1.25, codec)
        np.testing.assert_array_equal(back.pose, payload.pose)
        np.testing.assert_array_equal(back.boxes, boxes.astype(np.float32))
        np.testing.assert_array_equal(back.scores, scores.astype(np.float32))
        if carried is not None:
            exact = codec.endswith("f32")
            np.testing.assert_allclose(back.features, features, rtol=0 if exact else 1e-3)
    assert payload_bytes(0) == MESSAGE_HEADER_BYTES


def test_the_budget_drops_the_lowest_scores_then_the_weakest_feature_cells():
    scores = np.array([0.5, 0.9, 0.1, 0.7])
    kept, sent, size = fit_budget(scores, None, "dense_f32", MESSAGE_HEADER_BYTES + 2 * 44 + 43)
    np.testing.assert_array_equal(kept, [1, 3])
    assert size == payload_bytes(2)
    features = np.zeros((2, 2, 3), dtype=np.float32)
    features[:, 0, 0], features[:, 1, 2], features[:, 0, 1] = 3.0, 1.0, 2.0
    room = payload_bytes(4, features.shape, "sparse_f32", 2)
    given = features.copy()
    kept, sent, size = fit_budget(scores, features, "sparse_f32", room + 11)
    assert kept.size == 4 and size == room
    np.testing.assert_array_equal(np.flatnonzero(sent[0]), [0, 1])  # the two largest cells
    np.testing.assert_array_equal(features, given)  # the sender's map is left alone
    kept, sent, size = fit_budget(scores, features, "dense_f32", room)
    assert sent is None and size == payload_bytes(4)  # a dense map fits whole or not at all
    assert len(encode(Payload(0, 0.0, np.zeros(3), np.zeros((4, 7)), np.zeros((4, 3)), scores,
                              sent))) == size


def test_a_map_the_codec_and_budget_leave_whole_is_sent_without_a_copy():
    torch = pytest.importorskip("torch")
    features = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    assert fit_budget(np.ones(2), features, "dense_f32", None)[1] is features
    assert fit_budget(np.ones(2), features, "sparse_f32", None)[1] is features
    tensor = torch.from_numpy(features)  # a detector's map, on any device: only its shape read
    _, sent, size = fit_budget(np.ones(2), tensor, "dense_f32", None)
    assert sent is tensor and size == payload_bytes(2, (2, 3, 4))
    _, sent, _ = fit_budget(np.ones(2), features, "dense_f16", None)
    assert sent is not features and sent.dtype == np.float32
    np.testing.assert_array_equal(sent, features.astype(np.float16))


def test_maps_left_out_by_the_budget_fuse_as_zeros():
    torch = pytest.importorskip("torch")

    @dataclasses.dataclass
    class Maps:
        maps: object
        grid: object = None

    from roco_env.comm.delivery import Delivery, Scan

    def delivery(sender, encoder_map):
        scan = Scan(sender, 0.0, 0.0, np.zeros(3), np.zeros(3), np.zeros((0, 7)),
                    np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), encoder_map, 44)
        return Delivery(scan, 0.1, True)

    own = torch.ones((2, 3, 4, 5))
    sent = np.full((3, 4, 5), 7.0, dtype=np.float32)
    held = delivery(1, sent)  # two egos hold agent 1's scan: one row
    maps, rows = received_maps(Maps(own), [[held], [delivery(0, None), held]])
    assert rows == [(2,), (3, 2)] and maps.maps.shape[0] == 4
    assert torch.equal(maps.maps[2], torch.from_numpy(sent))
    assert not maps.maps[3].any()


def test_the_opencood_delay_is_whole_frames_of_overhead_transfer_and_processing():
    model = OpenCOODDelay(OpenCOODDelayParams(overhead_ms=0.0, bandwidth_mbps=27.0,
                                              processing_ms=10.0))
    bytes_250ms = 27e6 / 8 * 0.25
    delays = model.draw(np.random.default_rng(0), np.array([0, bytes_250ms, 27e6 / 8 * 0.095]),
                        np.zeros(3), 0.1)
    np.testing.assert_allclose(delays, [0.0, 0.2, 0.1])


def test_gilbert_elliott_losses_come_in_bursts_at_the_asked_rate():
    model = GilbertElliottLoss(loss_rate=0.2, burst_length=4.0)
    rng = np.random.default_rng(0)
    lost = np.concatenate([model.lost(rng, [(0, 1)]) for _ in range(40000)])
    assert abs(lost.mean() - 0.2) < 0.02
    starts = np.flatnonzero(np.diff(lost.astype(int)) == 1)
    assert abs(lost.sum() / starts.size - 4.0) < 0.4  # mean burst length
    with pytest.raises(ConfigError, match="loss_rate=0.9 cannot be reached with comm.loss_params"
                                            ".burst_length=2.0"):
        load_scenario(SCENE, loss="gilbert_elliott", loss_rate=0.9,
                      **{"comm.loss_params.burst_length": 2.0})


@pytest.mark.parametrize("overrides, names", [
    ({"delay": "fixed", "delay_ms": -5}, ["comm.delay_params.delay_ms=-5", "out of range"]),
    ({"delay": "opencood", "comm.delay_params.bandwidth_mbps": 0},
     ["comm.delay_params.bandwidth_mbps=0"]),
    ({"loss": "bernoulli", "loss_rate": -0.1}, ["comm.loss_params.loss_rate=-0.1"]),
    ({"loss": "bernoulli", "loss_rate": 1.5}, ["comm.loss_params.loss_rate=1.5", "[0.0, 1.0]"]),
    ({"comm.budget_bytes": 20}, ["comm.budget_bytes=20", f"[{MESSAGE_HEADER_BYTES}"]),
    ({"delay": "distance", "comm.delay_params.bandwidth_mbps": 10},
     ["comm.delay_params.bandwidth_mbps", "'opencood'", "not of 'distance'"]),
    ({"delay": "none", "delay_ms": 100},
     ["comm.delay_params.delay_ms", "'fixed'", "not of 'none'"]),
    ({"loss": "bernoulli", "comm.loss_params.burst_length": 3},
     ["comm.loss_params.burst_length", "'gilbert_elliott'"]),
    ({"delay": "teleport"}, ["comm.delay='teleport'", "'opencood'"]),
    ({"comm.sensor_offset_ms": {"cav_1": 900}}, ["comm.sensor_offset_ms.cav_1=900"]),
    ({"comm.sensor_offset_ms": {"cav_1": 10}, "detector": "learned", "fusion": "intermediate"},
     ["comm.sensor_offset_ms", "fusion.method='late'"]),
    ({"comm.max_age_ms": 0}, ["comm.max_age_ms=0"]),
    ({"comm.feature_codec": "jpeg"}, ["comm.feature_codec='jpeg'", "sparse_f16"]),
    ({"comm.compensation": "magic"}, ["comm.compensation='magic'", "'track'"]),
])
def test_bad_comm_input_names_the_field(overrides, names):
    with pytest.raises(ConfigError) as info:
        load_scenario(SCENE, **overrides)
    for name in names:
        assert name in str(info.value)


def test_a_sensor_offset_of_an_agent_the_scenario_lacks_names_it():
    with pytest.raises(ConfigError, match="comm.sensor_offset_ms.cav_9.*cav_0"):
        roco_env.parallel_env(SCENE, cavs=3, **{"comm.sensor_offset_ms": {"cav_9": 10}})


def test_lost_messages_cost_what_only_the_collaborators_see():
    """The ground truth is the collaboration in range now, whether its messages arrive or
    not: with every message lost, late fusion scores exactly the no-fusion reference."""
    lost = roco_env.parallel_env(SCENE, max_cycles=3, cavs=3, loss="bernoulli", loss_rate=1.0)
    alone = roco_env.parallel_env(SCENE, max_cycles=3, cavs=3, fusion="none")
    late = roco_env.parallel_env(SCENE, max_cycles=3, cavs=3, delay="fixed", delay_ms=300)
    for env in (lost, alone, late):
        env.reset(seed=6)
    while lost.agents:
        zeros = {a: np.zeros((lost.config.max_collaborators, 3)) for a in lost.agents}
        (_, r_lost, *_, i_lost), (_, r_alone, *_, i_alone), (*_, i_late) = (
            lost.step(zeros), alone.step(zeros), late.step(zeros))
        assert r_lost == r_alone
        for agent in lost.agents or i_lost:
            assert i_lost[agent]["n_gt"] == i_alone[agent]["n_gt"] == i_late[agent]["n_gt"]
            assert i_lost[agent]["n_collaborators"] == 0


def test_lean_infos_keep_the_traffic():
    env = roco_env.parallel_env(SCENE, max_cycles=2, cavs=3, info_level="metrics",
                                delay="fixed", delay_ms=100)
    env.reset(seed=0)
    _, _, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
    assert set(infos["cav_0"]) == set(METRIC_INFO_KEYS) | set(NETWORK_INFO_KEYS)


def test_only_compensation_loads_the_tracks_and_no_env_loads_filterpy():
    code = ("import sys, roco_env\n"
            "for comp in ('none', 'track'):\n"
            "    env = roco_env.parallel_env('highway_dense', max_cycles=2, delay='fixed',\n"
            "                                **{'comm.compensation': comp})\n"
            "    env.reset(seed=0)\n"
            "    print(comp, sorted(m for m in ('filterpy', 'roco_env.comm.tracking')\n"
            "                       if m in sys.modules))\n")
    assert run_python(code).splitlines() == ["none []", "track ['roco_env.comm.tracking']"]


def test_a_delay_factory_gets_its_parameters_checked(registered):
    seen = []

    def factory(config):
        seen.append(dict(config.delay_params))
        return FixedDelay.from_config(config)

    registered("delay", "watched", factory, FixedDelayParams)
    Pipeline(load_scenario(SCENE, cavs=3, delay="watched", delay_ms=200))
    assert seen == [{"delay_ms": 200.0}] and isinstance(seen[0]["delay_ms"], float)
    with pytest.raises(ConfigError, match="comm.delay_params.delay_ms"):
        Pipeline(load_scenario(SCENE, cavs=3, delay="watched", delay_ms=-1))
    assert len(seen) == 1  # refused before the factory runs
