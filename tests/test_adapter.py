"""The observation adapter of the array aligners: compact <-> observation positions and
the per-call hook."""

import numpy as np

from roco_env.policies.adapter import ArrayAlignmentPolicy, unpack_observation
from roco_env.policies.base import AlignmentResult


def _observation(rng):
    """Ego with 6 box slots (4 used), 3 collaborator slots (slot 1 empty)."""
    boxes = rng.normal(size=(6, 7))
    collab_boxes = rng.normal(size=(3, 5, 7))
    return {
        "pose": np.array([1.0, 2.0, 0.3]),
        "boxes": boxes,
        "uncertainty": np.abs(rng.normal(size=(6, 3))),
        "box_mask": np.array([1, 0, 1, 1, 0, 1]),
        "collab_mask": np.array([1, 0, 1]),
        "collab_rel_poses": rng.normal(size=(3, 3)),
        "collab_boxes": collab_boxes,
        "collab_uncertainty": np.abs(rng.normal(size=(3, 5, 3))),
        "collab_box_mask": np.array([[0, 1, 1, 0, 1], [1, 1, 1, 1, 1], [1, 0, 0, 1, 0]]),
    }


def test_expand_maps_compact_pairs_to_observation_slots_and_boxes():
    view = unpack_observation(_observation(np.random.default_rng(0)))
    assert view.slots.tolist() == [0, 2]
    # Compact rows: (slot_a, box_a, slot_b, box_b), slot -1 = ego, 0/1 = filled slots 0/2.
    pairs = np.array([[-1, 0, 0, 2], [-1, 3, 1, 1], [0, 0, 1, 0], [-1, 2, 0, 1]])
    result = AlignmentResult(
        corrected=np.ones((2, 3)), applied=np.array([True, False]), matched_pairs=pairs,
        slot_reasons=("", "too few"),
    )
    expanded = view.expand(result)
    ego_used, slot0_used, slot2_used = [0, 2, 3, 5], [1, 2, 4], [0, 3]
    expected = [
        [-1, ego_used[0], 0, slot0_used[2]],
        [-1, ego_used[3], 2, slot2_used[1]],
        [0, slot0_used[0], 2, slot2_used[0]],
        [-1, ego_used[2], 0, slot0_used[1]],
    ]
    assert expanded.matched_pairs.tolist() == expected
    assert expanded.applied.tolist() == [True, False, False]
    assert expanded.slot_reasons == ("", "", "too few")
    np.testing.assert_array_equal(expanded.corrected[[0, 2]], np.ones((2, 3)))
    np.testing.assert_array_equal(expanded.corrected[1], np.zeros(3))


def test_align_view_is_the_per_call_hook():
    seen = []

    class Recording(ArrayAlignmentPolicy):
        def align_view(self, view, observation, info):
            seen.append((view.slots.tolist(), info["agent"], observation["pose"][2]))
            return AlignmentResult(corrected=view.reported + [0.5, 0.0, 0.0],
                                   applied=np.ones(view.slots.size, dtype=bool))

    observation = _observation(np.random.default_rng(1))
    policy = Recording(lambda *a, **k: None, None, {})
    action = policy(observation, {"agent": "cav_0"})
    assert seen == [([0, 2], "cav_0", 0.3)]
    assert policy.last_result.applied.tolist() == [True, False, True]
    np.testing.assert_allclose(action[[0, 2], 0], 0.5, atol=1e-6)
    np.testing.assert_array_equal(action[1], np.zeros(3))
