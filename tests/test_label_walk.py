"""Labelling (Alg. 5) on synthetic walks: direction change, occlusion, strays, scoring."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gaitflow.schemas import GroundTruth, LabelledMarkers, SubjectModel
from gaitflow.stages import label, model

from gaitflow.evaluate_label import Walk, calibration_record, synthetic_walk
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES

HIP_GONE = range(40, 45)  # five frames with the right hip marker under the arm


@pytest.fixture(scope="module")
def subject() -> SubjectModel:
    walk = synthetic_walk(seed=11, frames_per_pass=10, static=True, trial="static")
    st = model.SPEC.init(model.PARAMS.resolve({}))
    out = []
    for f in walk.frames:
        st, msgs = model.SPEC.step(st, {"markers": f, "calibration": calibration_record()})
        out.extend(msgs)
    return out[0]


def _run(walk: Walk, subject: SubjectModel | None, **params: object) -> list[LabelledMarkers]:
    st = label.SPEC.init(label.PARAMS.resolve(params))
    out = []
    side = {"calibration": calibration_record()}
    if subject is not None:
        side["model"] = subject
    for f in walk.frames:
        st, msgs = label.SPEC.step(st, {"markers": f, **side})
        assert len(msgs) == 1
        out.append(msgs[0])
    return out


@pytest.fixture(scope="module")
def occluded(subject: SubjectModel) -> tuple[Walk, list[LabelledMarkers]]:
    walk = synthetic_walk(seed=12, occlude={k: ["R_HIP"] for k in HIP_GONE})
    return walk, _run(walk, subject)


def _wrong(walk: Walk, labs: list[LabelledMarkers]) -> list[str]:
    bad = []
    for lab, ids in zip(labs, walk.truth, strict=True):
        for i in np.flatnonzero(lab.blob >= 0):
            if ids[lab.blob[i]] != i:
                bad.append(f"frame {lab.header.frame}: {MARKER_NAMES[i]}")
    return bad


def test_no_wrong_label_through_both_directions(occluded: tuple) -> None:
    walk, labs = occluded
    assert _wrong(walk, labs) == []  # strays (truth -1) included: they stay unlabelled
    n = len(walk.frames) // 2
    out, back = labs[:n], labs[n:]
    # Out: walking toward +u shows the right side; back: the left side (the L/R swap).
    assert {m.near_side for m in out} == {"R"} and {m.direction for m in out} == {1}
    assert {m.near_side for m in back} == {"L"} and {m.direction for m in back} == {-1}


@pytest.mark.parametrize("near", ["R", "L"])
def test_near_leg_labelled_in_almost_every_frame(occluded: tuple, near: str) -> None:
    walk, labs = occluded
    n = len(walk.frames) // 2
    part = labs[:n] if near == "R" else labs[n:]
    for site in ("SHO", "HIP", "THI", "KNE", "TIB", "ANK", "HEE", "TOE"):
        i = MARKER_INDEX[f"{near}_{site}"]
        frames = [m for m in part if m.header.frame not in HIP_GONE]
        got = np.mean([m.blob[i] >= 0 for m in frames])
        assert got >= 0.9, f"{near}_{site} labelled in {got:.0%} of frames"
    far = "L" if near == "R" else "R"
    for site in ("HEE", "TOE"):
        got = np.mean([m.blob[MARKER_INDEX[f"{far}_{site}"]] >= 0 for m in part])
        assert got >= 0.8, f"{far}_{site} labelled in {got:.0%} of frames"


def test_hip_occlusion_gives_a_gap_not_a_wrong_label(occluded: tuple) -> None:
    walk, labs = occluded
    i = MARKER_INDEX["R_HIP"]
    by_frame = {m.header.frame: m for m in labs}
    for k in HIP_GONE:
        m = by_frame[k]
        assert m.blob[i] == -1 and np.isnan(m.position[i]).all() and np.isnan(m.pixel[i]).all()
    # Recovered right after the arm has passed.
    assert by_frame[HIP_GONE[-1] + 1].blob[i] >= 0
    assert by_frame[HIP_GONE[-1] + 2].blob[i] >= 0
    assert _wrong(walk, labs) == []


def test_positions_follow_each_markers_cluster_mode(occluded: tuple) -> None:
    walk, labs = occluded
    f, m = walk.frames[30], labs[30]
    for i in np.flatnonzero(m.blob >= 0):
        mode = ("normal", "top", "bottom").index(label.cluster_mode(MARKER_NAMES[i]))
        np.testing.assert_array_equal(m.position[i], f.position[m.blob[i], mode])
        np.testing.assert_array_equal(m.pixel[i], f.centroid[m.blob[i]])


def test_without_model_the_template_still_labels_safely() -> None:
    walk = synthetic_walk(seed=13, frames_per_pass=40)
    labs = _run(walk, None)
    assert _wrong(walk, labs) == []
    assert np.mean([(m.blob >= 0).sum() for m in labs]) > 5


def test_score_labelling_counts_wrong_and_missing() -> None:
    names = {n: i for i, n in enumerate(MARKER_NAMES)}
    tp = np.full((20, 2), np.nan)
    tp[names["R_KNE"]] = (100.0, 200.0)
    tp[names["R_ANK"]] = (110.0, 300.0)
    vis = np.zeros(20, bool)
    vis[[names["R_KNE"], names["R_ANK"]]] = True
    truth = []
    labs = []
    for k, kne_px in enumerate([(100.5, 200.0), (110.0, 300.0)]):  # frame 1: KNE on the ANK
        hdr = GroundTruth.make_header("c", "walk-01", k, 0)
        truth.append(
            GroundTruth(
                header=hdr,
                position=np.zeros((20, 3)),
                pixel=tp,
                visible=vis,
                occluded=np.zeros(20, bool),
                knee_flexion=np.zeros(2),
            )
        )
        px = np.full((20, 2), np.nan)
        px[names["R_KNE"]] = kne_px
        labs.append(
            LabelledMarkers.follow(
                hdr,
                position=np.zeros((20, 3)),
                pixel=px,
                blob=np.full(20, -1, np.int32),
                direction=1,
                near_side="R",
            )
        )
    s = label.score_labelling(labs, truth)
    assert s["frames"] == 2 and s["accuracy"] == 0.5
    assert s["labels"] == 2 and s["wrong"] == 1 and s["precision"] == 0.5
    assert s["recall"] == pytest.approx(1 / 4)  # 4 visible marker-frames, 1 found


def test_empty_and_all_nan_frames_give_empty_labels() -> None:
    from gaitflow.schemas import Markers3D

    st = label.SPEC.init(label.PARAMS.resolve({}))
    for k, n in enumerate([0, 3]):
        hdr = Markers3D.make_header("cam0", "walk-01", k, k)
        mk = Markers3D(
            header=hdr,
            centroid=np.full((n, 2), np.nan),
            marker_radius=np.zeros(n),
            region_radius=np.zeros(n),
            depth=np.full((n, 3), np.nan),
            position=np.full((n, 3, 3), np.nan),
        )
        st, out = label.SPEC.step(st, {"markers": mk})
        assert len(out) == 1 and (out[0].blob == -1).all() and out[0].near_side == ""


def test_a_subject_standing_after_walking_gets_no_labels(subject: SubjectModel) -> None:
    # Walking, then standing still (stopping to turn in view): the shoulder track slows
    # below turn_speed, the subject is "turning", and no label is published, the shoulder
    # included (while turning the track may move to the other shoulder as it comes nearer).
    walk = synthetic_walk(seed=3, frames_per_pass=30)
    last = walk.frames[24]
    still = [
        dataclasses.replace(last, header=dataclasses.replace(last.header, frame=25 + k))
        for k in range(20)
    ]
    frames = walk.frames[:25] + still
    labs = _run(Walk(frames, walk.truth[:25] + [walk.truth[24]] * 20, walk.near[:45]), subject)
    assert np.isfinite(labs[20].position).all(axis=1).sum() >= 8  # walking: labelled
    for lab in labs[-5:]:
        assert not np.isfinite(lab.position).any(), MARKER_NAMES[
            int(np.flatnonzero(np.isfinite(lab.position).all(axis=1))[0])
        ]


def test_the_blobs_left_unnamed_go_out_as_spares_with_their_heel_position(
    subject: SubjectModel,
) -> None:
    walk = synthetic_walk(seed=12)
    # locate's offset of a marker centre towards the camera, which heels do not get
    frames = [dataclasses.replace(f, surface_offset_mm=14.0) for f in walk.frames]
    walk = dataclasses.replace(walk, frames=frames)
    labs = _run(walk, subject)
    heel_mode = label.OWN_MODE[MARKER_INDEX["R_HEE"]]
    n_spare = 0
    for f, lab in zip(walk.frames, labs, strict=True):
        cen = np.asarray(f.centroid, dtype=float).reshape(-1, 2)
        rest = np.setdiff1d(np.arange(len(cen)), lab.blob[lab.blob >= 0])
        np.testing.assert_array_equal(lab.spare_pixel, cen[rest])
        pos = label.fill_modes(np.asarray(f.position).reshape(-1, 3, 3))[rest, heel_mode]
        # heels are published at the surface point (heel_side_on): so are the spares
        want = label.surface_point(pos, f.surface_offset_mm)
        np.testing.assert_allclose(lab.spare_heel, want)
        n_spare += len(rest)
    # the walk's stray reflectors (truth -1) are never named: they are spares
    assert n_spare >= sum(int(np.sum(np.asarray(ids) < 0)) for ids in walk.truth) > 0
