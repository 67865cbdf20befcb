"""The `realistic` preset's defaults give a plausible AP and a visible cooperative gain.

Integration check on the `urban_intersection` scenario (synthetic traffic,
project AP). Single agent: own detections against the objects it sees itself.
Cooperative: late fusion with TRUE relative poses against the collaboration's
ground truth, compared with the ego's own detections on that same ground truth.
"""

from __future__ import annotations

import numpy as np

from roco_env.evaluation import ground_truth
from roco_env.fusion.late import late_fusion
from roco_env.geometry import se2_relative
from roco_env.metrics import APAccumulator, in_range_mask
from roco_env.scenario import load_scenario
from roco_env.sensing import compute_visibility, make_detector, select_collaborators
from roco_env.traffic import make_traffic_source


def test_realistic_preset_ap_range_and_cooperative_gain():
    config = load_scenario("urban_intersection")
    ranges = (config.evaluation.x_range, config.evaluation.y_range)
    detector = make_detector(config.detector)
    single, alone, fused = APAccumulator(), APAccumulator(), APAccumulator()
    for seed in range(3):
        traffic = make_traffic_source(config)
        state = traffic.reset(np.random.default_rng(seed))
        rng = np.random.default_rng(100 + seed)
        for _ in range(6):
            for _ in range(5):
                state = traffic.step(config.traffic.dt)
            vis = compute_visibility(state)
            dets = detector.detect(state, vis, rng)
            for ego in range(state.num_agents):
                collab = select_collaborators(state, ego, config.max_collaborators)
                own_gt, _ = ground_truth(state, vis.visible, ego, [], *ranges)
                coop_gt, _ = ground_truth(state, vis.visible, ego, collab, *ranges)
                keep = in_range_mask(dets[ego].boxes, *ranges)
                single.add_frame(dets[ego].boxes[keep], dets[ego].scores[keep], own_gt)
                alone.add_frame(dets[ego].boxes[keep], dets[ego].scores[keep], coop_gt)
                rel = se2_relative(state.agent_poses[ego][None], state.agent_poses[collab])
                out = late_fusion(dets[ego].boxes, dets[ego].scores,
                                  [dets[j].boxes for j in collab],
                                  [dets[j].scores for j in collab], rel.reshape(-1, 3))
                keep = in_range_mask(out.boxes, *ranges)
                fused.add_frame(out.boxes[keep], out.scores[keep], coop_gt)
    ap_single, ap_alone, ap_fused = single.ap(), alone.ap(), fused.ap()
    assert 0.5 <= ap_single[0.7] <= 0.8
    assert ap_single[0.5] > ap_single[0.7]
    assert ap_fused[0.7] > ap_alone[0.7] + 0.1
    assert ap_fused[0.5] > ap_alone[0.5] + 0.1
