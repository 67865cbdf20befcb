"""The compiled hypothesis votes and evidence against the numpy path they replace.

``numpy_*`` below are the array implementations of roco_antialias's hypothesis search and
evidence as they were before the loops were compiled; the compiled path does the same
arithmetic in the same order, so that the hypotheses refined, the scores compared with
``min_margin`` and hence every decision stay the same. Decisions, counts and vote peaks
compare exactly; float results (hypothesis poses, scores, gains, margins) to rounding
(``assert_equal_to_rounding``): numpy's exp / sin / cos are CPU-specific SIMD versions on
AVX-512 machines, an ulp off libm's that numba calls.
"""

import numpy as np
import pytest
from conftest import assert_equal_to_rounding
from scipy.spatial import cKDTree

from roco_env.policies.hypotheses import (
    EvidenceParams,
    box_set,
    evidence_terms,
    generate_hypotheses,
    score_hypotheses,
    translation_peaks,
)
from roco_env.policies.hypothesis_kernels import best_pair_gains, close_pairs, pairwise_sum
from roco_env.policies.landmarks import UncertaintyParams, prepare_inputs
from roco_env.policies.pose_kernels import pair_information
from roco_env.testing.constructed_scenes import (
    benchmark_scene,
    make_scene,
    parking_rows,
    pose_error,
)


def numpy_map(pose, poses):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    out = np.empty_like(poses)
    out[:, 0] = c * poses[:, 0] - s * poses[:, 1] + pose[0]
    out[:, 1] = s * poses[:, 0] + c * poses[:, 1] + pose[1]
    out[:, 2] = poses[:, 2] + pose[2]
    return out


def numpy_half_turn(angle):
    return np.mod(angle + np.pi / 2, np.pi) - np.pi / 2


def numpy_size_chi2(ego, collab, i, j, p):
    diff = ego.log_sizes[i] - collab.log_sizes[j]
    return (diff * diff).sum(axis=1) / (2.0 * p.size_sigma**2)


def numpy_vote_peak(values, weight, half, cell):
    bins = int(np.ceil(2 * half / cell))
    votes = np.bincount(
        np.minimum(((values + half) / cell).astype(np.int64), bins - 1), weight, bins
    )
    smooth = np.convolve(votes, np.ones(5), mode="same")
    return -half + (int(np.argmax(smooth)) + 0.5) * cell if smooth.max() > 0 else 0.0


def numpy_generate_hypotheses(ego, collab, reported, p):
    half = np.deg2rad(p.search_yaw_deg)
    mapped = numpy_map(reported, collab.poses)
    i, j = close_pairs(ego.poses[:, :2], mapped[:, :2], float(p.search_radius + 2.0))
    if i.size == 0:
        return np.zeros((0, 3))
    size_weight = (np.exp(-0.5 * numpy_size_chi2(ego, collab, i, j, p)) if p.use_size
                   else np.ones(i.size))
    dyaw = numpy_half_turn(ego.poses[i, 2] - mapped[j, 2])
    use = np.abs(dyaw) <= half
    rotation = numpy_vote_peak(dyaw[use], size_weight[use], half, np.deg2rad(0.25))
    return numpy_translation_peaks(ego, collab, reported + np.array([0.0, 0.0, rotation]), p)


def numpy_translation_peaks(ego, collab, rotated, p, most=None):
    """The array path of hypotheses.translation_peaks."""
    most = p.max_hypotheses if most is None else most
    mapped = numpy_map(rotated, collab.poses)
    i, j = close_pairs(ego.poses[:, :2], mapped[:, :2], float(p.search_radius * np.sqrt(2.0)))
    size_weight = (np.exp(-0.5 * numpy_size_chi2(ego, collab, i, j, p)) if p.use_size
                   else np.ones(i.size))
    dx = ego.poses[i, 0] - mapped[j, 0]
    dy = ego.poses[i, 1] - mapped[j, 1]
    dyaw = numpy_half_turn(ego.poses[i, 2] - mapped[j, 2])
    use = (np.abs(dx) <= p.search_radius) & (np.abs(dy) <= p.search_radius)
    weight = (size_weight * np.exp(-0.5 * (dyaw / np.deg2rad(3.0)) ** 2))[use]
    n = int(np.ceil(2 * p.search_radius / p.vote_bin))
    ix = np.minimum(((dx[use] + p.search_radius) / p.vote_bin).astype(np.int64), n - 1)
    iy = np.minimum(((dy[use] + p.search_radius) / p.vote_bin).astype(np.int64), n - 1)
    grid = np.bincount(ix * n + iy, weight, n * n).reshape(n, n)
    padded = np.zeros((n + 2, n + 2))
    padded[1:-1, 1:-1] = grid
    smooth = sum(padded[a : a + n, b : b + n] for a in range(3) for b in range(3))
    peaks = []
    suppress = (1.25 / p.vote_bin) ** 2
    floor = max(p.vote_floor * smooth.max(), 0.0)
    for flat in np.argsort(-smooth, axis=None):
        if len(peaks) == most or smooth.flat[flat] <= floor:
            break
        a, b = divmod(int(flat), n)
        if all((a - c) ** 2 + (b - d) ** 2 > suppress for c, d in peaks):
            peaks.append((a, b))
    if not peaks:
        return np.zeros((0, 3))
    offsets = (np.array(peaks, dtype=float) + 0.5) * p.vote_bin - p.search_radius
    out = np.tile(rotated, (offsets.shape[0], 1))
    out[:, :2] += offsets
    return out


def numpy_best_gains(ego, collab, pose, p):
    """k-d tree pairs within the radius where a pair can still gain, chi2 per pair,
    np.maximum.at per box."""
    mapped = numpy_map(pose, collab.poses)
    slack_t, slack_r = p.pose_slack_t**2, np.deg2rad(p.pose_slack_r_deg) ** 2
    widest = ego.var_t.max(initial=0.0) + collab.var_t.max(initial=0.0) + slack_t
    found = cKDTree(ego.poses[:, :2]).sparse_distance_matrix(
        cKDTree(mapped[:, :2]), float(np.sqrt(p.outlier_chi2 * widest)), output_type="ndarray")
    i, j = found["i"].astype(np.int64), found["j"].astype(np.int64)
    dx, dy = ego.poses[i, 0] - mapped[j, 0], ego.poses[i, 1] - mapped[j, 1]
    dyaw = numpy_half_turn(ego.poses[i, 2] - mapped[j, 2])
    chi2 = (dx * dx + dy * dy) / (ego.var_t[i] + collab.var_t[j] + slack_t)
    chi2 += dyaw * dyaw / (ego.var_r[i] + collab.var_r[j] + slack_r)
    if p.use_size:
        chi2 += numpy_size_chi2(ego, collab, i, j, p)
    gain = p.outlier_chi2 - chi2
    keep = gain > 0
    forward, backward = np.zeros(collab.poses.shape[0]), np.zeros(ego.poses.shape[0])
    np.maximum.at(forward, j[keep], gain[keep])
    np.maximum.at(backward, i[keep], gain[keep])
    return forward, backward


def compiled_best_gains(ego, collab, pose, p):
    return best_pair_gains(ego.terms, collab.terms, numpy_map(pose, collab.poses),
                           evidence_terms(p))


def numpy_mutual_detection(ego, collab, pose, ego_unexplained, collab_unexplained, p):
    total = 0.0
    c, s = np.cos(pose[2]), np.sin(pose[2])
    inverse = np.array([-c * pose[0] - s * pose[1], s * pose[0] - c * pose[1], -pose[2]])
    slack_t, slack_r = p.pose_slack_t**2, np.deg2rad(p.pose_slack_r_deg) ** 2
    for boxes, target, unexplained in ((ego, pose, ego_unexplained),
                                       (collab, inverse, collab_unexplained)):
        if boxes.poses.shape[0] == 0:
            continue
        d = boxes.poses[:, :2] - target[:2]
        dyaw = numpy_half_turn(boxes.poses[:, 2] - target[2])
        chi2 = (d * d).sum(axis=1) / (boxes.var_t + slack_t) + dyaw * dyaw / (boxes.var_r + slack_r)
        gains = np.where(unexplained, np.maximum(p.outlier_chi2 - chi2, 0.0), 0.0)
        total += float(gains.max())
    return total


def numpy_score_hypotheses(ego, collab, poses, p):
    forward_set = np.ones(collab.poses.shape[0], dtype=bool)
    backward_set = np.ones(ego.poses.shape[0], dtype=bool)
    for pose in poses:
        mapped = numpy_map(pose, collab.poses)
        forward_set &= np.hypot(mapped[:, 0], mapped[:, 1]) <= ego.range
        backward_set &= np.hypot(*(ego.poses[:, :2] - pose[:2]).T) <= collab.range
    scores = np.zeros(poses.shape[0])
    for h, pose in enumerate(poses):
        forward, backward = compiled_best_gains(ego, collab, pose, p)
        scores[h] = float(forward[forward_set].sum())
        if p.use_free_space:
            scores[h] += float(backward[backward_set].sum())
            unexplained = backward_set & (backward == 0)
            scores[h] -= p.free_space_penalty * float(np.count_nonzero(unexplained))
        if p.use_mutual_detection:
            scores[h] += numpy_mutual_detection(ego, collab, pose, backward == 0, forward == 0, p)
    return scores


def _scenes():
    """Benchmark scenes (random layouts) and a parking lot (repetitive rows, aliasing)."""
    rng = np.random.default_rng(5)
    for seed, agents, objects, error in ((0, 5, 60, 0.8), (1, 10, 200, 0.8), (2, 4, 40, 5.0)):
        yield benchmark_scene(np.random.default_rng(seed), agents, objects, error, error)
    lot = parking_rows(3, 50, origin=(-60.0, 0.0), jitter=(0.1, 0.1, 1.0), rng=rng)
    agents = np.array([[0.0, 3.5, 0.0], [14.0, 3.5, 0.1], [-9.0, 10.5, 3.0]])
    yield make_scene(lot, agents, [pose_error(1.6, 0.3, np.pi), pose_error(3.0, 1.0, 0.5)],
                     sensor_range=30.0, noise=(0.05, 0.05, 0.01), rng=rng)


def _box_sets(scene):
    inputs = prepare_inputs(*scene.args(), UncertaintyParams())
    boxes = [scene.ego_boxes, *scene.collab_boxes]
    return [box_set(b, inputs.poses[a], inputs.information[a]) for a, b in enumerate(boxes)]


PARAMS = [EvidenceParams(), EvidenceParams(use_size=False), EvidenceParams(use_free_space=False),
          EvidenceParams(use_mutual_detection=False), EvidenceParams(vote_bin=0.3, search_radius=4.0,
                                                                    search_yaw_deg=3.0)]


@pytest.mark.parametrize("p", PARAMS, ids=range(len(PARAMS)))
def test_hypotheses_and_scores_match_the_numpy_path(p):
    rng = np.random.default_rng(9)
    checked = 0
    for scene in _scenes():
        sets = _box_sets(scene)
        for j, reported in enumerate(scene.reported):
            got = generate_hypotheses(sets[0], sets[j + 1], reported, p)
            assert_equal_to_rounding(got, numpy_generate_hypotheses(sets[0], sets[j + 1],
                                                                     reported, p))
            for most in (None, 1):  # the votes at the reported rotation itself
                assert_equal_to_rounding(
                    translation_peaks(sets[0], sets[j + 1], reported, p, most),
                    numpy_translation_peaks(sets[0], sets[j + 1], reported, p, most))
            # Hypotheses near the truth and the reported pose, as _decide scores them.
            poses = np.vstack([got, scene.true[j], reported,
                               scene.true[j] + rng.normal(0.0, [1.5, 1.5, 0.02], (3, 3))])
            assert_equal_to_rounding(score_hypotheses(sets[0], sets[j + 1], poses, p),
                                     numpy_score_hypotheses(sets[0], sets[j + 1], poses, p))
            checked += got.shape[0]
    assert checked > 10  # the scenes produce hypotheses to compare


def test_no_box_pair_means_no_hypothesis():
    scene = next(_scenes())
    sets = _box_sets(scene)
    far = scene.reported[0] + np.array([500.0, 0.0, 0.0])
    assert generate_hypotheses(sets[0], sets[1], far, EvidenceParams()).shape == (0, 3)


def test_pairwise_sum_is_ndarray_sum_to_the_bit():
    """Exact on purpose: what is tested is the order of the additions (no elementary
    function, no BLAS), and IEEE-754 rounds each addition alike on every CPU; numpy's 8
    accumulators keep its order whatever SIMD width sums them."""
    rng = np.random.default_rng(4)
    for n in [*range(0, 300), 1000, 4099, 70001]:
        values = rng.standard_normal(n) * rng.uniform(0.0, 1e3, n)
        assert pairwise_sum(values, 0, n) == values.sum()
        if n > 3:
            assert pairwise_sum(values, 3, n - 3) == values[3:].sum()


@pytest.mark.parametrize("use_size", [True, False])
def test_best_pair_gains_match_the_numpy_path(use_size):
    rng = np.random.default_rng(21)
    p = EvidenceParams(use_size=use_size)
    for _ in range(10):
        ego_boxes = np.column_stack([rng.uniform(-30, 30, (40, 2)), rng.normal(size=40),
                                     rng.uniform(1, 5, (40, 3)), rng.uniform(-3, 3, 40)])
        collab_boxes = ego_boxes[rng.choice(40, 25, replace=False)].copy()
        collab_boxes[:, [0, 1, 6]] += rng.normal(size=(25, 3)) * [0.3, 0.3, 0.05]
        sets = []
        for boxes in (ego_boxes, collab_boxes):
            poses = boxes[:, [0, 1, 6]]
            sigma = rng.uniform(0.1, 0.6, (boxes.shape[0], 3))
            info = np.zeros((boxes.shape[0], 3, 3))
            info[:, [0, 1, 2], [0, 1, 2]] = sigma**-2
            sets.append(box_set(boxes, poses, info))
        pose = rng.normal(size=3) * [0.3, 0.3, 0.02]
        forward, backward = compiled_best_gains(sets[0], sets[1], pose, p)
        expected = numpy_best_gains(sets[0], sets[1], pose, p)
        assert_equal_to_rounding(forward, expected[0])
        assert_equal_to_rounding(backward, expected[1])
        assert np.count_nonzero(forward) > 5  # the case exercises gaining pairs


def numpy_decide(ego, collab, reported, track, p):
    """The Python path of antialias._decide without the diagnosis (steps 1-3 of its module
    docstring, ``use_ambiguity`` off): (pose or None, margin, refined count)."""
    import math

    from roco_env.geometry import wrap_angle
    from roco_env.policies.hypotheses import refine_terms
    from roco_env.policies.pose_kernels import refine_pose
    from roco_env.policies.prior_free import poses_distinct

    def close(a, b, tolerance):
        yaw = (float(a[2]) - float(b[2]) + math.pi) % (2.0 * math.pi) - math.pi
        return np.hypot(a[0] - b[0], a[1] - b[1]) <= tolerance and math.degrees(abs(yaw)) <= tolerance

    def prior_chi2(poses, centre, sigma_t, sigma_r):
        d = poses - centre
        yaw = wrap_angle(d[:, 2])
        return (d[:, 0] ** 2 + d[:, 1] ** 2) / sigma_t**2 + yaw**2 / sigma_r**2

    peaks = numpy_generate_hypotheses(ego, collab, reported, p)
    if peaks.shape[0] and abs(wrap_angle(peaks[0, 2] - reported[2])) > np.deg2rad(p.distinct_r_deg):
        peaks = np.concatenate([peaks, numpy_translation_peaks(ego, collab, reported, p, 1)])
    starts = [peaks]
    for seed in (reported, None if track is None else track[0]):
        if seed is not None and not any(close(seed, peak, 0.5) for peak in starts[0]):
            starts.append(seed[None])
    refined = []
    for start in np.concatenate(starts):
        pose, ok = refine_pose(start, ego.poses, collab.poses, collab.information,
                               refine_terms(p, p.robust_kernel, p.kernel_delta, p.min_matches))
        if ok and not any(close(pose, other, 0.3) for other in refined):
            refined.append(pose)
    if not refined:
        return None, float("nan"), 0
    poses = np.stack(refined)
    score = numpy_score_hypotheses(ego, collab, poses, p)
    score -= prior_chi2(poses, reported, p.prior_sigma_t, np.deg2rad(p.prior_sigma_r_deg))
    if track is not None:
        centre, age = track
        score -= prior_chi2(poses, centre, p.track_sigma_t * age,
                            np.deg2rad(p.track_sigma_r_deg) * age)
    best = int(np.argmax(score))
    distinct = poses_distinct(poses, poses[best], p)
    runner_up = float(score[distinct].max()) if distinct.any() else 0.0
    margin = float(score[best]) - runner_up
    return (None if margin < p.min_margin else poses[best]), margin, len(refined)


@pytest.mark.parametrize("with_track", [False, True])
def test_decisions_match_the_python_path(with_track):
    from roco_env.policies.antialias import AntiAliasParams, _decide

    rng = np.random.default_rng(17)
    outcomes = set()
    # The second set's margin is out of reach: every slot is left ambiguous. The diagnosis
    # (use_ambiguity) is compared in tests/test_ambiguity.py.
    for p in (AntiAliasParams(use_ambiguity=False),
              AntiAliasParams(use_free_space=False, min_margin=1e4, use_ambiguity=False)):
        for scene in _scenes():
            sets = _box_sets(scene)
            for j, reported in enumerate(scene.reported):
                track = None
                if with_track:  # a prediction near the truth or one stall off it
                    shift = rng.choice([0.0, 2.5]) + rng.normal(0.0, 0.2)
                    track = (scene.true[j] + np.array([shift, 0.0, 0.002]), float(rng.integers(1, 4)))
                got = _decide(sets[0], sets[j + 1], reported, track, p)
                pose, margin, count = numpy_decide(sets[0], sets[j + 1], reported, track, p)
                assert (got.pose is None) == (pose is None)
                if pose is not None:
                    assert_equal_to_rounding(got.pose, pose)
                assert_equal_to_rounding(got.margin, margin)  # nan == nan here
                assert got.hypotheses == count
                outcomes.add((pose is None, count))
    # Decided and ambiguous slots, one and several refined hypotheses.
    assert {ambiguous for ambiguous, _ in outcomes} == {False, True}
    assert min(count for _, count in outcomes) == 1 < max(count for _, count in outcomes)


def numpy_pair_information(ego, collab, pose, gate, slack_t, slack_r):
    """The array path of pose_kernels.pair_information: (information (3, 3), pairs)."""
    if ego.poses.shape[0] == 0:
        return np.zeros((3, 3)), 0
    mapped = numpy_map(pose, collab.poses)
    distance = np.hypot(mapped[:, None, 0] - ego.poses[None, :, 0],
                        mapped[:, None, 1] - ego.poses[None, :, 1])
    nearest = np.argmin(distance, axis=1)
    paired = distance[np.arange(mapped.shape[0]), nearest] < gate
    q, p = np.nonzero(paired)[0], nearest[paired]
    w_t = 1.0 / (ego.var_t[p] + collab.var_t[q] + slack_t)
    w_r = 1.0 / (ego.var_r[p] + collab.var_r[q] + slack_r)
    lever = np.column_stack([-(mapped[q, 1] - pose[1]), mapped[q, 0] - pose[0]])
    info = np.zeros((3, 3))
    info[0, 0] = info[1, 1] = w_t.sum()
    info[0, 2] = info[2, 0] = (w_t * lever[:, 0]).sum()
    info[1, 2] = info[2, 1] = (w_t * lever[:, 1]).sum()
    info[2, 2] = (w_t * (lever**2).sum(axis=1)).sum() + w_r.sum()
    return info, int(q.size)


def test_pair_information_matches_the_numpy_path():
    rng = np.random.default_rng(23)
    counts = set()
    for scene in _scenes():
        sets = _box_sets(scene)
        for j, true in enumerate(scene.true):
            for pose in (true, true + rng.normal(size=3) * [0.4, 0.4, 0.01], scene.reported[j]):
                args = (sets[0], sets[j + 1], pose, 1.0, 0.01, 3e-5)
                info, count = pair_information(
                    (sets[0].poses, sets[0].var_t, sets[0].var_r),
                    (sets[j + 1].poses, sets[j + 1].var_t, sets[j + 1].var_r), pose, *args[3:])
                expected, expected_count = numpy_pair_information(*args)
                assert count == expected_count
                assert_equal_to_rounding(info, expected, rtol=1e-10)
                counts.add(count)
    assert 0 in counts and max(counts) > 20  # unmatched and well matched poses both occur


def test_box_sets_in_one_pass_are_the_per_agent_sets():
    from roco_env.policies.hypotheses import box_sets

    for scene in _scenes():
        boxes = [scene.ego_boxes, *scene.collab_boxes]
        unc = [scene.ego_unc, *scene.collab_unc]
        for agent in {1, len(boxes) - 1}:  # agents without boxes, between others and last
            boxes[agent], unc[agent] = boxes[agent][:0], unc[agent][:0]
        inputs = prepare_inputs(boxes[0], unc[0], boxes[1:], unc[1:], scene.reported,
                                UncertaintyParams())
        expected = [box_set(b, inputs.poses[a], inputs.information[a]) for a, b in enumerate(boxes)]
        got = box_sets(boxes, inputs)
        assert len(got) == len(expected)
        for one, other in zip(got, expected, strict=True):
            for field in ("poses", "log_sizes", "information", "var_r", "range"):
                np.testing.assert_array_equal(getattr(one, field), getattr(other, field))
            # From the 3x3 and the 2x2 inverses (LAPACK's arithmetic may differ by CPU):
            # to rounding, each box's variance (> 0) at its own magnitude.
            assert_equal_to_rounding(one.var_t / other.var_t, np.ones_like(other.var_t))


def test_centre_covariance_is_the_inverse_of_the_xy_information():
    """box_sets reads the centres' covariances from the 3x3 inverses RoCo computes; with no
    xy-yaw information terms they equal the 2x2 inverses box_set takes, to rounding (each
    entry at the magnitude of its matrix)."""
    from roco_env.policies.landmarks import box_information

    rng = np.random.default_rng(6)
    poses = np.column_stack([rng.uniform(-80, 80, (20000, 2)), rng.uniform(-4, 4, 20000)])
    sigma = np.exp(rng.uniform(-5, 1, (20000, 3)))
    sigma[::3, 1] = sigma[::3, 0]  # isotropic centres too
    info = box_information(poses, sigma, 0.01, 0.001, (0.5, 0.5, 0.05))
    got, expected = np.linalg.inv(info)[:, :2, :2], np.linalg.inv(info[:, :2, :2])
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)  # each matrix's magnitude
    assert_equal_to_rounding(got / scale, expected / scale)
