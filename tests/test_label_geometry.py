"""Label geometry: wand-marker constraints and the plausibility check of the static model."""

from __future__ import annotations

import numpy as np
from gaitflow.schemas import SubjectModel
from gaitflow.stages import label
from gaitflow.stages.model import TEMPLATE_SHO_HEIGHT

from gaitflow.markers import MARKER_INDEX


def _pt(f: float, h: float) -> np.ndarray:
    return np.array([[f, 0.0, h]])


def test_interval_cost_zero_inside_and_grows_outside() -> None:
    a = _pt(0.0, 0.0)
    inside = label._interval(a, _pt(0.0, 100.0), 50.0, 300.0)[0]
    below = label._interval(a, _pt(0.0, 20.0), 50.0, 300.0)[0]
    above = label._interval(a, _pt(0.0, 345.0), 50.0, 300.0)[0]
    assert inside == 0.0
    assert np.isclose(below, (30.0 / 15.0) ** 2)
    assert np.isclose(above, (45.0 / 15.0) ** 2)


def test_on_segment_cost_for_a_wand_on_and_off_the_shank() -> None:
    kne, ank = _pt(0.0, 450.0), _pt(40.0, 80.0)
    on = label._on_segment(kne, _pt(20.0, 265.0), ank)[0]  # halfway along the shank
    off = label._on_segment(kne, _pt(120.0, 265.0), ank)[0]  # 100 mm in front of it
    past = label._on_segment(kne, _pt(50.0, -10.0), ank)[0]  # below the ankle
    assert on < 0.1
    assert off > 10.0 and past > 10.0


def _geometry_with_foot(
    offs: dict[str, list[float]], measured: dict[str, bool] | None = None
) -> label.Geometry:
    hdr = SubjectModel.make_header("cam0", "static", 0, 0, True)
    extra = {"sho_height_mm": TEMPLATE_SHO_HEIGHT, "offsets_from_shoulder": offs}
    if measured is not None:
        extra["measured"] = measured
    m = SubjectModel(
        header=hdr,
        reference=np.full((20, 3), np.nan),
        distances=np.full((20, 20), np.nan),
        near_side="R",
        extra=extra,
    )
    return label.Geometry.from_model(m)


def test_implausible_static_segment_falls_back_to_the_template() -> None:
    tpl = label.Geometry.from_model(None)
    # A static pose whose toe was taken for a blob 35 mm ahead of the ankle.
    offs = {
        "near_ANK": [100.0, 0.0, 85.0],
        "near_HEE": [40.0, 0.0, 40.0],
        "near_TOE": [135.0, 0.0, 80.0],
    }
    geo = _geometry_with_foot(offs)
    assert np.isclose(geo.d("ANK", "TOE"), tpl.d("ANK", "TOE"))
    # A plausible measured segment is kept.
    assert np.isclose(geo.d("ANK", "HEE"), np.hypot(60.0, 45.0))


def test_a_measured_foot_within_foot_scale_is_kept() -> None:
    # The template's foot (ANK, HEE, TOE offsets from the shoulder) scaled by 1.5 about
    # the ankle (opensim_rajagopal_walk: a toe marker on the toe's tip, a heel marker low on
    # the shoe), and then only the toe moved to the toe's tip: foot lengths beyond
    # PLAUSIBLE but inside FOOT_SCALE are the subject's, not a labelling error.
    tpl = label.Geometry.from_model(None)
    ank = tpl.rel_sho("near", "ANK")

    def scaled(site: str, k: float) -> list[float]:
        return (ank + k * (tpl.rel_sho("near", site) - ank)).tolist()

    offs = {f"near_{s}": scaled(s, 1.5) for s in ("ANK", "HEE", "TOE")}
    geo = _geometry_with_foot(offs)
    for a, b in label.FOOT:
        assert np.isclose(geo.d(a, b), 1.5 * tpl.d(a, b)), (a, b)
    offs = {"near_ANK": scaled("ANK", 1.0), "near_HEE": scaled("HEE", 1.0)}
    offs["near_TOE"] = scaled("TOE", 1.6)
    geo = _geometry_with_foot(offs)
    assert np.isclose(geo.d("ANK", "TOE"), 1.6 * tpl.d("ANK", "TOE"))
    assert geo.d("HEE", "TOE") > (1.0 + label.PLAUSIBLE) * tpl.d("HEE", "TOE")
    # Beyond FOOT_SCALE (a toe 2.2 times as far ahead): the template's.
    offs["near_TOE"] = scaled("TOE", 2.2)
    geo = _geometry_with_foot(offs)
    assert np.isclose(geo.d("ANK", "TOE"), tpl.d("ANK", "TOE"))


def test_foot_lengths_learned_from_walking_frames_and_outliers_ignored() -> None:
    geo = label.Geometry.from_model(None)
    st = label.init(label.PARAMS.resolve({}))
    ia, ih, it = (MARKER_INDEX[f"R_{s}"] for s in ("ANK", "HEE", "TOE"))
    assign = np.full(20, -1)
    assign[[ia, ih, it]] = [0, 1, 2]
    # A foot 20 % longer than the template's: ANK (0, 80), HEE (-45, 45), TOE heel + 1.2 L.
    ht = 1.2 * geo.d("HEE", "TOE")
    pts = np.array([[0.0, 0.0, 80.0], [-45.0, 0.0, 45.0], [ht - 45.0, 0.0, 45.0]])
    fm = np.repeat(pts[:, None, :], 3, axis=1)
    for _ in range(60):
        st = label._learn_foot(st, fm, assign, label._learned(geo, st), "R")
    learned = label._learned(geo, st)
    assert abs(learned.d("HEE", "TOE") - ht) < 0.05 * ht
    assert st.foot_n == 60
    # A frame whose "toe" is twice as far (a wrong label) teaches nothing.
    far = fm.copy()
    far[2, :, 0] = 2.5 * ht
    st2 = label._learn_foot(st, far, assign, learned, "R")
    assert st2.foot_n == st.foot_n and np.allclose(st2.foot, st.foot)


def _template_foot_offsets(k: float = 1.0) -> dict[str, list[float]]:
    """The template's near ankle, heel and toe offsets, the foot scaled by k about the ankle."""
    tpl = label.Geometry.from_model(None)
    ank = tpl.rel_sho("near", "ANK")
    return {f"near_{s}": (ank + k * (tpl.rel_sho("near", s) - ank)).tolist() for s in label.SITES}


def test_the_static_foot_side_is_the_near_side_of_a_measured_plausible_foot() -> None:
    foot = {"ANK": True, "HEE": True, "TOE": True}
    assert _geometry_with_foot(_template_foot_offsets(), foot).foot_side == "R"
    assert _geometry_with_foot(_template_foot_offsets(), {**foot, "HEE": False}).foot_side == ""
    assert _geometry_with_foot(_template_foot_offsets()).foot_side == ""  # no flags
    # a foot beyond FOOT_SCALE is a static labelling error, not the subject's foot
    assert _geometry_with_foot(_template_foot_offsets(2.5), foot).foot_side == ""


def _foot_frame(geo: label.Geometry, hee_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Floor positions (3 blobs, 3 modes, 3) of a near foot whose heel lies ``hee_gap`` mm
    behind the ankle (the template's toe), and the assignment naming them R_ANK, R_HEE,
    R_TOE."""
    ank = geo.rel_sho("near", "ANK")
    toe = geo.rel_sho("near", "TOE")
    hee = ank - np.array([hee_gap, 0.0, 0.0])
    fm = np.repeat(np.stack([ank, hee, toe])[:, None, :], 3, axis=1)
    assign = np.full(20, -1)
    for b, s in enumerate(("ANK", "HEE", "TOE")):
        assign[MARKER_INDEX[f"R_{s}"]] = b
    return fm, assign


def test_the_walk_teaches_the_foot_only_near_the_static_foot() -> None:
    # `shoes`: a shoe's reflector under the ankle, taken for the heel, taught a foot whose
    # heel crept from 58 to 36 mm behind the ankle, step by step within 40 % of the last.
    geo = label.Geometry.from_model(None)
    static = np.array([geo.d(a, b) for a, b in label.FOOT])
    st = label.init(label.PARAMS.resolve({}))
    d0 = geo.d("ANK", "HEE")
    short, fm_a = _foot_frame(geo, 0.7 * d0)  # 30 % short: within 40 % of the last length
    assert label._learn_foot(st, short, fm_a, geo, "R").foot_n == 1
    assert label._learn_foot(st, short, fm_a, geo, "R", static).foot_n == 0
    near, fm_b = _foot_frame(geo, 0.9 * d0)  # 10 % short: the foot's own variation
    learned = label._learn_foot(st, near, fm_b, geo, "R", static)
    assert learned.foot_n == 1 and learned.foot is not None
    assert learned.foot[0] < d0
