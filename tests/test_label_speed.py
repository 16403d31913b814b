"""Label stage speed-ups that must not change a bit: the search tables, the Kalman filter,
and a labelling pinned on a noisy synthetic walk (outputs of the pre-speed-up stage)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from gaitflow.schemas import SubjectModel
from gaitflow.stages import label
from test_label_walk import subject  # noqa: F401  (the static model fixture)

from gaitflow.evaluate_label import calibration_record, synthetic_walk
from gaitflow.markers import MARKER_INDEX


@pytest.mark.parametrize(("k", "r"), [(0, 3), (1, 4), (3, 3), (5, 4), (6, 5), (9, 4)])
def test_tuples_match_the_itertools_enumeration(k: int, r: int) -> None:
    rows = [
        t
        for t in itertools.product(range(k + 1), repeat=r)
        if len({i for i in t if i < k}) == sum(1 for i in t if i < k)
    ]
    want = np.array(rows, dtype=np.int64).reshape(-1, r)
    got = label._tuples(k, r)
    assert got.dtype == want.dtype and np.array_equal(got, want)


def test_kalman_matches_filterpy_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    dt = 1 / 30
    x = np.concatenate([rng.normal(0, 500, 3), rng.normal(0, 900, 3)])
    P = np.diag([20.0**2] * 3 + [1500.0**2] * 3)
    kf = KalmanFilter(dim_x=6, dim_z=3)
    F, Q, H, R, _ = label._kf_model(dt)
    kf.F, kf.Q, kf.H, kf.R = F.copy(), Q.copy(), H.copy(), R.copy()
    kf.x, kf.P = x.copy(), P.copy()
    for n in range(12):
        kf.predict()
        x, P = label._kf_predict(x, P, dt)
        assert np.array_equal(x, kf.x) and np.array_equal(P, kf.P)
        if n % 4 != 3:  # a miss now and then: predict only
            z = x[:3] + rng.normal(0, 15, 3)
            kf.update(z)
            x, P = label._kf_update(x, P, z, dt)
            assert np.array_equal(x, kf.x) and np.array_equal(P, kf.P)


def test_unambiguous_on_literals() -> None:
    K = 3  # blobs 0..2, 3 = missing
    T = np.array([[0, 1], [1, 0], [0, 3], [2, 1]])
    cost = np.array([1.0, 2.0, 7.0, 6.0])
    # Slot 0: the best gives blob 0, another blob (1) costs only 1 more: ambiguous.
    # Slot 1: the best gives blob 1; blob 0 (row 1) also only 1 more: ambiguous.
    assert label._unambiguous(cost, T, 0, K, 4.0) == [False, False]
    cost2 = np.array([1.0, 9.0, 2.0, 6.0])
    # Slot 0: blob 1 or 2 cost >= 5 more: kept. Slot 1: blob 0 costs 8 more: kept.
    assert label._unambiguous(cost2, T, 0, K, 4.0) == [True, True]
    # A missing slot is never kept.
    assert label._unambiguous(cost2, T, 2, K, 4.0) == [True, False]


def test_hypothesis_tables_equal_row_by_row_evaluation() -> None:
    """_Hyp scores only what the hard rules leave; the costs equal, bit for bit, evaluating
    every term on every row and setting the forbidden ones to inf."""
    rng = np.random.default_rng(7)
    K, idx = 6, [MARKER_INDEX[f"R_{s}"] for s in ("TIB", "ANK", "HEE", "TOE")]
    qm = rng.normal(0, 150, (K + 2, 3, 3))
    fr = label._Frame(
        qm=qm,
        free=np.ones(K + 2, bool),
        assign=np.full(20, -1),
        pred=rng.normal(0, 100, (20, 3)),
        sig=rng.uniform(30, 90, (20, 3)),
        near="R",
        tracked=np.zeros(20, bool),
        ambiguity=4.0,
        age=np.full(20, 10**9),
    )
    cand = np.arange(1, K + 1)
    hy = label._Hyp(fr, idx, cand)
    hy.forbid((0, 1), lambda pt, pa: pt[:, 2] > pa[:, 2] - 20.0)
    hy.forbid((2, 3), lambda ph, pt: pt[:, 0] > ph[:, 0])
    hy.add((1, 2), lambda pa, pb: label._rigid(pa, pb, 80.0))
    hy.add((1, 3), lambda pa, pb: ((pa[:, 1] - pb[:, 1]) / 80.0) ** 2)
    # Row by row, as the stage did before: every tuple, positions NaN where missing.
    T = label._tuples(K, 4)
    pres = T < K
    pts = np.full((*T.shape, 3), np.nan)
    U = np.zeros((4, K + 1))
    for k, i in enumerate(idx):
        P = np.vstack([qm[cand, label.MODE_OF[i]], np.full((1, 3), np.nan)])
        pts[:, k] = P[T[:, k]]
        U[k, :K] = label._unary(fr, i, cand)
        U[k, K] = label.MISS_COST
    cost = U[np.arange(4), T].sum(axis=1)
    both = pres[:, 1] & pres[:, 2]
    cost[both] += label._rigid(pts[both, 1], pts[both, 2], 80.0)
    both = pres[:, 1] & pres[:, 3]
    cost[both] += ((pts[both, 1, 1] - pts[both, 3, 1]) / 80.0) ** 2
    cost[pres[:, 0] & pres[:, 1] & ~(pts[:, 0, 2] > pts[:, 1, 2] - 20.0)] = np.inf
    cost[pres[:, 2] & pres[:, 3] & ~(pts[:, 3, 0] > pts[:, 2, 0])] = np.inf
    assert np.isinf(cost).any() and np.isfinite(cost).any()
    assert np.array_equal(hy.cost, cost)


# Labels of the stage before the speed-up on the walk below (blob index per marker,
# MARKER_NAMES order), for a few frames, and labels per marker over the whole walk.
PINNED = {
    5: [-1, -1, -1, -1, -1, -1, -1, -1, 10, 5, 11, -1, -1, 2, 8, 0, 14, 13, 4, 3],
    21: [-1, -1, -1, -1, -1, -1, -1, -1, 13, 2, 5, -1, -1, 8, 3, 9, 7, 6, -1, 0],
    31: [-1, -1, -1, -1, -1, -1, -1, -1, 10, 11, 12, -1, -1, 9, 0, -1, 7, -1, -1, -1],
    59: [-1, -1, -1, -1, -1, -1, -1, -1, 8, 1, 12, -1, -1, 5, 13, 10, 14, 9, 6, 2],
    75: [7, -1, -1, 5, 0, 3, 12, 6, 9, 8, -1, -1, -1, -1, -1, -1, -1, -1, 11, 10],
    111: [10, -1, -1, 6, 14, 8, 7, 3, 9, 13, -1, -1, -1, -1, -1, -1, -1, -1, 4, 12],
}
# Re-pinned after the hip rules of the pelvis search (below the far ASI and PSI too; still
# blobs out): 7 more hip labels (L_HIP 53 -> 59, R_HIP 56 -> 57, all right by the walk's
# truth, frame 111); and after the foot-track sigma and the far heel/toe track claims: wrong
# labels 3 -> 1 of ~1170 (frame 31: R_ANK on the heel's blob is now R_HEE), 8 fewer foot
# labels; and after far labels were judged over every near hypothesis (_far_unambiguous):
# one far toe label fewer, one far heel label more, the same one wrong label (frame 23);
# and after the hip was kept below the spines' expected height: one more R_HIP label
# (frame 15, right by the walk's truth); and after a near foot label was judged against
# the far heel or toe taking its blob too (_clear_of_far_foot): one R_HEE label fewer
# (frame 12, right by the walk's truth, now left out as possibly the far heel); and after a
# shoulder track restarted near the walkway's end without a move waits until it walks: the
# return pass's first frame (60, after a 10-frame gap, within restart_frames) is unlabelled,
# its 10 labels were right by the walk's truth; every later frame is as before; and after a
# near foot label whose blob another near foot marker could as well take was judged
# ambiguous: 9 foot labels fewer around the occlusions (frames 23-25, 31-32, 100-103),
# one of them wrong (frame 23: R_HEE on the ankle's blob, the heel occluded), 8 right;
# and after the hip was kept 0.4 of its drop below the spines (HIP_DROP, was 0.25): one
# more R_HIP label (frame 19) and one more L_HIP label (frame 102), both right by the
# walk's truth; and after the far tibia wand, which only absorbs its blob, was kept above
# the ankle's standing height (thirty-third session): 9 foot labels more, 8 of them the far
# foot's heel and toe (frames 10, 12, 31, 44, 88, 102, 118; frame 31 gains L_TOE) and frame
# 12's near heel, all right by the walk's truth, and none lost.
PINNED_COUNTS = [59, 0, 0, 59, 59, 59, 59, 56, 115, 115, 60, 0, 0, 59, 60, 57, 60, 53, 111, 116]


def test_labelling_pinned_on_a_noisy_walk_with_occlusions(subject: SubjectModel) -> None:  # noqa: F811
    occl = {k: ["R_HEE"] for k in range(20, 26)}
    occl |= {k: ["R_KNE", "R_ANK"] for k in range(30, 33)}
    occl |= {k: ["L_TOE"] for k in range(110, 114)}
    walk = synthetic_walk(seed=21, frames_per_pass=60, noise_mm=12.0, occlude=occl)
    st = label.SPEC.init(label.PARAMS.resolve({}))
    side = {"calibration": calibration_record(), "model": subject}
    blobs = []
    for f in walk.frames:
        st, msgs = label.SPEC.step(st, {"markers": f, **side})
        blobs.append(np.asarray(msgs[0].blob))
    for n, want in PINNED.items():
        assert np.asarray(blobs[n]).tolist() == want, f"frame {n}"
    assert (np.array(blobs) >= 0).sum(axis=0).tolist() == PINNED_COUNTS


def test_far_labels_are_judged_over_every_near_hypothesis() -> None:
    K = 3  # blobs 0..2, 3 = missing
    # far completions (HEE, TOE)
    T2 = np.array([[0, 1], [2, 1], [3, 3]])
    # near hypothesis 0 (the best) completes best with far HEE on blob 0; near hypothesis 1
    # (1 worse) completes best with far HEE on blob 2
    total = np.array([[1.0, 9.0, 12.0], [8.0, 2.0, 12.0]])
    # judged at near hypothesis 0 alone the far heel was clear (9 - 1 >= 4) ...
    assert label._unambiguous(total[0], T2, 0, K, 4.0) == [True, True]
    # ... but blob 2 as far heel costs only 1 more jointly: the heel is dropped; the toe
    # takes blob 1 in both and stays
    assert label._far_unambiguous(total, T2, 0, K, 4.0) == [False, True]
    # a far completion clearly worse under every near hypothesis keeps both
    total[1, 1] = 6.0
    assert label._far_unambiguous(total, T2, 0, K, 4.0) == [True, True]
