"""What the environment computes: determinism, fusion AP under noise, AP bookkeeping, options."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.evaluation import UNDEFINED, filled_rpe_rows, info_frame_stats
from roco_env.geometry import bev_iou, se2_relative
from roco_env.metrics import APAccumulator, frame_ap
from roco_env.policies import make_policy

FAST = dict(scenario="urban_intersection", density=1.5, max_boxes=24)


def run_episode(policy_name: str, steps: int, seed: int = 3, **overrides):
    """(initial infos, per-step (obs, rewards, infos)) of one episode."""
    env = roco_env.parallel_env(**{**FAST, **overrides}, max_cycles=steps)
    policy = make_policy(policy_name)
    obs, infos = env.reset(seed=seed)
    first, history = infos, []
    while env.agents:
        obs, rewards, _, _, infos = env.step({a: policy(obs[a], infos[a]) for a in env.agents})
        history.append((obs, rewards, infos))
    return first, history


def assert_same(a, b, where="root"):
    """Exact structural equality, NaN equal to NaN."""
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, float):
        assert a == b or (np.isnan(a) and np.isnan(b)), where
    else:
        assert a == b, where


def rollout_random(seed: int, steps: int):
    """An episode driven by seeded random corrections (exercises the action path)."""
    env = roco_env.parallel_env(**FAST, max_cycles=steps, sigma_t=0.5, sigma_r=0.5)
    rng = np.random.default_rng(99)
    out = [env.reset(seed=seed)]
    while env.agents:
        actions = {a: rng.normal(0.0, 0.3, (5, 3)) for a in env.agents}
        out.append(env.step(actions))
    return out


def test_whole_episode_is_deterministic():
    steps = 200
    first, second = rollout_random(7, steps), rollout_random(7, steps)
    assert len(first) == steps + 1
    assert_same(first, second)
    other = rollout_random(8, 3)
    assert not np.array_equal(other[1][0]["cav_0"]["boxes"], first[1][0]["cav_0"]["boxes"])


def test_unseeded_reset_continues_the_seeded_sequence():
    env = roco_env.parallel_env(**FAST)
    first, _ = env.reset(seed=5)
    next_, _ = env.reset()
    again, _ = env.reset(seed=5)
    assert_same(first, again)
    assert not np.array_equal(first["cav_0"]["boxes"], next_["cav_0"]["boxes"])


def test_zero_noise_identity_equals_oracle():
    _, identity = run_episode("identity", 8, sigma_t=0.0, sigma_r=0.0)
    _, oracle = run_episode("oracle", 8, sigma_t=0.0, sigma_r=0.0)
    for (_, rew_i, info_i), (_, rew_o, info_o) in zip(identity, oracle, strict=True):
        for agent in info_i:
            for key in ("ap30", "ap50", "ap70", "n_pred"):
                assert_same(info_i[agent][key], info_o[agent][key], f"{agent}.{key}")
            assert rew_i[agent] == rew_o[agent]
            np.testing.assert_allclose(info_o[agent]["fused_boxes"], info_i[agent]["fused_boxes"],
                                       atol=1e-9)


@pytest.mark.parametrize("policy", ["identity", "oracle"])
def test_ideal_detector_on_clean_poses_scores_exactly_one(policy):
    """Every GT object is detected (ideal detector, K above the visible count) and every
    fused box is a GT object: collaborators' views of the ego's own car (which the GT
    leaves out) are dropped by the fusion, so AP is exactly 1 at every threshold."""
    env = roco_env.parallel_env(**{**FAST, "max_boxes": 96}, detector="ideal", sigma_t=0.0,
                                sigma_r=0.0, max_cycles=6)
    chooser = make_policy(policy)
    obs, infos = env.reset(seed=1)
    n_cav = env.config.agents.cavs
    ego_car_seen_by_collaborators = 0
    while env.agents:
        frame = env.unwrapped._frame
        assert all(int(o["box_mask"].sum()) < 96 for o in obs.values())  # nothing cut by K
        obs, _, _, _, infos = env.step({a: chooser(obs[a], infos[a]) for a in env.agents})
        for k, agent in enumerate(env.possible_agents):
            info = infos[agent]
            assert info["n_gt"] > 0 and info["n_pred"] == info["n_gt"]
            assert [info["ap30"], info["ap50"], info["ap70"]] == [1.0, 1.0, 1.0]
            assert info["frame_tp"][:, info["fused_mask"]].all()
            footprint = frame.footprints[k]
            assert (footprint is None) == (k >= n_cav)
            if footprint is not None:
                assert np.all(bev_iou(info["fused_boxes"][info["fused_mask"]],
                                      footprint[None]) == 0.0)
                own_car = frame.state.object_ids == frame.state.agent_object_ids[k]
                collaborators = list(frame.views[k].collaborators)
                ego_car_seen_by_collaborators += int(
                    frame.visibility.visible[collaborators][:, own_car].any())
    assert ego_car_seen_by_collaborators > 0  # the drop was exercised


def test_oracle_beats_identity_under_heavy_noise():
    def mean_ap70(policy):
        _, steps = run_episode(policy, 12, sigma_t=0.8, sigma_r=0.8)
        return np.mean([info["ap70"] for _, _, infos in steps for info in infos.values()
                        if info["ap70"] != UNDEFINED])

    identity, oracle = mean_ap70("identity"), mean_ap70("oracle")
    assert oracle > identity + 0.2, (identity, oracle)
    _, steps = run_episode("oracle", 3, sigma_t=0.8, sigma_r=0.8)
    for _, _, infos in steps:
        for info in infos.values():
            done = info["rpe_after"][:, 0] != UNDEFINED
            assert np.all(info["rpe_after"][done] < 1e-3)
            assert np.all(info["rpe_before"][done].sum(axis=1) > 0)


def test_ap_accumulated_from_infos_equals_direct_accumulation():
    _, steps = run_episode("identity", 10, sigma_t=0.4, sigma_r=0.4)
    from_infos, direct = APAccumulator(), APAccumulator()
    for _, _, infos in steps:
        for info in infos.values():
            from_infos.add_stats(info_frame_stats(info))
            assert info["gt_mask"].sum() == info["n_gt"]  # nothing cut at this size
            fused = info["fused_boxes"][info["fused_mask"]], info["fused_scores"][info["fused_mask"]]
            direct.add_frame(*fused, info["gt_boxes"][info["gt_mask"]])
            per_step = frame_ap(*fused, info["gt_boxes"][info["gt_mask"]])
            assert_same([np.nan if info[k] == UNDEFINED else info[k]
                         for k in ("ap30", "ap50", "ap70")],
                        [per_step[0.3], per_step[0.5], per_step[0.7]])
    assert from_infos.n_gt == direct.n_gt > 0
    assert from_infos.ap() == direct.ap()
    assert 0.0 < direct.ap()[0.7] < 1.0


def test_privileged_truth_describes_the_returned_observation():
    env = roco_env.parallel_env(**FAST, sigma_t=0.5, sigma_r=0.5)
    obs, infos = env.reset(seed=4)
    obs, _, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
    state = env.unwrapped._frame.state
    ids = list(state.agent_ids)
    for agent, info in infos.items():
        slots = [ids.index(c) for c in info["collaborators"]]
        true = se2_relative(state.agent_poses[ids.index(agent)][None], state.agent_poses[slots])
        np.testing.assert_allclose(info["privileged"]["true_relative_poses"][: len(slots)],
                                   true.reshape(-1, 3), atol=1e-9)
        reported = se2_relative(obs[agent]["pose"][None].astype(float),
                                obs[agent]["collab_poses"][: len(slots)].astype(float))
        np.testing.assert_allclose(info["privileged"]["reported_relative_poses"][: len(slots)],
                                   reported, atol=1e-3)
        masked = obs[agent]["box_mask"] == 0
        assert np.all(info["privileged"]["box_object_ids"][masked] == -1)


def test_evaluated_agents_restrict_scoring():
    _, steps = run_episode("identity", 2, **{"agents.evaluated": ["cav_1"]})
    _, rewards, infos = steps[-1]
    assert infos["cav_1"]["evaluated"] and "ap70" in infos["cav_1"]
    for agent in ("cav_0", "cav_2", "cav_3", "rsu_0"):
        assert rewards[agent] == 0.0 and not infos[agent]["evaluated"]
        assert "ap70" not in infos[agent] and "frame_tp" not in infos[agent]
        assert infos[agent]["rpe_after"].shape == (5, 2)


def test_perturb_ego_false_reports_the_clean_own_pose():
    env = roco_env.parallel_env(**FAST, sigma_t=1.0, sigma_r=1.0,
                                **{"noise.perturb_ego": False})
    obs, infos = env.reset(seed=0)
    state = env.unwrapped._frame.state
    true = dict(zip(state.agent_ids, state.agent_poses, strict=True))
    for agent in state.agent_ids:
        np.testing.assert_allclose(obs[agent]["pose"], true[agent], atol=1e-4)
        collaborators = infos[agent]["collaborators"]
        if collaborators:  # the collaborators' reported poses stay noisy
            truth = np.array([true[c] for c in collaborators])
            assert np.abs(obs[agent]["collab_poses"][: len(collaborators)] - truth).max() > 1e-2


@pytest.mark.parametrize("kind", ["ap30", "ap50", "ap70", "neg_rpe"])
def test_reward_kinds(kind):
    _, steps = run_episode("identity", 2, sigma_t=0.5, sigma_r=0.5, reward=kind)
    _, rewards, infos = steps[-1]
    for agent, value in rewards.items():
        info = infos[agent]
        if kind == "neg_rpe":
            rows = filled_rpe_rows(info["rpe_after"])
            assert value == pytest.approx(-rows.sum(axis=1).mean() if len(rows) else 0.0)
        else:
            assert value == (0.0 if info[kind] == UNDEFINED else info[kind])


def test_bring_your_own_frames():
    from roco_env.traffic.frames import Frame

    ids = np.arange(4)
    frames = [Frame(object_ids=ids,
                    object_boxes=[[t, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0], [t + 12.0, 0.0, 0.8, 4.5, 1.9,
                                                                      1.6, 0.0],
                                  [t + 6.0, 5.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                                  [t + 20.0, -5.0, 0.8, 4.5, 1.9, 1.6, 0.0]],
                    cav_object_ids=[0, 1]) for t in (0.0, 1.0, 2.0)]
    scene = {k: v for k, v in FAST.items() if k != "density"}  # the frames set the traffic
    env = roco_env.parallel_env(**scene, frames=frames, max_cycles=2, cavs=2, rsus=0,
                                detector="ideal", sigma_t=0.0, sigma_r=0.0,
                                **{"traffic.source": "frames"})
    obs, infos = env.reset(seed=0)
    assert env.agents == ["cav_0", "cav_1"] and infos["cav_0"]["collaborators"] == ["cav_1"]
    np.testing.assert_allclose(obs["cav_1"]["pose"], [12.0, 0.0, 0.0], atol=1e-6)
    _, rewards, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
    assert infos["cav_0"]["n_gt"] == 3 and rewards["cav_0"] == 1.0


def test_no_fusion_scores_the_egos_own_boxes_against_the_collaborations_truth():
    """fusion='none': no action changes the scores (no collaborator box is fused), the
    ground truth is late fusion's (the objects the collaboration sees), and late fusion
    with clean poses scores above it (it adds what only collaborators see)."""
    def frames(policy, fusion, sigma):
        _, steps = run_episode(policy, 6, fusion=fusion, sigma_t=sigma, sigma_r=sigma)
        return [(info["ap70"], info["n_gt"]) for _, _, infos in steps
                for info in infos.values()]

    alone = frames("identity", "none", 0.8)
    assert frames("oracle", "none", 0.8) == alone
    late = frames("oracle", "late", 0.8)
    assert [n for _, n in late] == [n for _, n in alone]
    defined = [(a, b) for (a, _), (b, _) in zip(alone, late, strict=True) if a != UNDEFINED]
    assert np.mean([b for _, b in defined]) > np.mean([a for a, _ in defined]) + 0.05
