"""The out-of-distribution detector: held-out flag rates, each reason, frame checks, JSON."""

import numpy as np
import pytest

from models.inference.ood import OODDetector, Subspace, frame_statistics


def world(n_textures=30, n_windows=40, F=20, D=12, seed=0):
    """Textures on a low-dimensional manifold; the last 6 tactile columns are speed/force statistics."""
    shared = np.random.default_rng(100)  # the population: the same mixing for every draw
    mix, vmix = shared.normal(size=(3, F - 6)), shared.normal(size=(3, D))
    rng = np.random.default_rng(seed)
    tactile = []
    for _ in range(n_textures):
        z = rng.normal(size=3)
        feats = z @ mix + 0.3 * rng.normal(size=(n_windows, F - 6))
        speed = rng.uniform(20, 300, size=(n_windows, 1)) * np.array([0.5, 1.5, 1.0])
        force = rng.uniform(0.2, 4, size=(n_windows, 1)) * np.array([0.8, 1.2, 1.0])
        tactile.append(np.hstack([feats, speed, force]))
    visual = (rng.normal(size=(n_textures, 1, 3)) @ vmix) + 0.1 * rng.normal(size=(n_textures, 4, D))
    return tactile, visual, mix, vmix


@pytest.fixture(scope="module")
def fitted():
    tactile, visual, mix, vmix = world()
    frames = np.array(
        [
            frame_statistics(np.clip(0.5 + 0.15 * np.random.default_rng(i).standard_normal((64, 64)), 0, 1))
            for i in range(30)
        ]
    )
    return OODDetector.fit(tactile, visual, frames, k_tactile=3, k_visual=3), mix, vmix


def test_new_textures_from_the_population_are_rarely_flagged(fitted):
    det, _, _ = fitted
    tactile, visual, _, _ = world(n_textures=20, seed=7)  # another draw of the same population
    flagged = np.mean(np.concatenate([det.check(t, v[0]).flags for t, v in zip(tactile, visual)]))
    assert flagged < 0.06


def test_each_kind_of_fault_is_flagged_with_its_reason(fitted):
    det, _, _ = fitted
    tactile, visual, _, _ = world(n_textures=1, seed=8)
    t, v = tactile[0].copy(), visual[0, 0]
    noisy = t.copy()
    noisy[:, :-6] += 5 * np.random.default_rng(0).normal(size=noisy[:, :-6].shape)
    assert all("tactile_outlier" in r for r in det.check(noisy, v).reasons)
    fast = t.copy()
    fast[:, -6:-3] += 1000  # mm/s: far above any training stroke
    assert all("speed_out_of_range" in r for r in det.check(fast, v).reasons)
    hard = t.copy()
    hard[:, -3:] += 20  # N
    assert all("force_out_of_range" in r for r in det.check(hard, v).reasons)
    assert all("no_frame" in r for r in det.check(t, None).reasons) and det.check(t, None).flags.all()
    odd = v + 20 * np.random.default_rng(1).normal(size=v.shape)
    res = det.check(t, odd)
    assert res.visual_score > 1 and all("visual_outlier" in r for r in res.reasons)
    # distances grow off-distribution: the interval scale follows
    assert np.median(det.scale(det.check(noisy, v))) > 2 * np.median(det.scale(det.check(t, v)))


def test_frame_checks_name_what_is_wrong(fitted):
    det, _, _ = fitted
    rng = np.random.default_rng(3)
    good = np.clip(0.5 + 0.15 * rng.standard_normal((64, 64)), 0, 1).astype(np.float32)
    assert det.check_frame(good) == []
    assert "frame_underexposed" in det.check_frame(good * 0.2)
    assert "frame_overexposed" in det.check_frame(np.clip(good * 3, 0, 1))
    from scipy import ndimage

    assert "frame_blurred" in det.check_frame(ndimage.gaussian_filter(good, 3))
    dark = good.copy()
    dark[:, :32] = 0
    assert "frame_dark_region" in det.check_frame(dark)
    reasons = det.check(
        world(n_textures=1, seed=9)[0][0],
        world(n_textures=1, seed=9)[1][0, 0],
        frame_reasons=det.check_frame(good * 0.2),
    ).reasons
    assert all("frame_underexposed" in r for r in reasons)


def test_json_round_trip_gives_the_same_answers(fitted):
    det, _, _ = fitted
    again = OODDetector.from_json(det.to_json())
    tactile, visual, _, _ = world(n_textures=2, seed=11)
    for t, v in zip(tactile, visual):
        a, b = det.check(t, v[0]), again.check(t, v[0])
        assert a.reasons == b.reasons
        np.testing.assert_allclose(a.distance, b.distance, rtol=1e-4)
    with pytest.raises(ValueError, match="not an OOD"):
        OODDetector.from_dict({"format": "x"})


def test_bad_inputs_are_named(fitted):
    det, _, _ = fitted
    with pytest.raises(ValueError, match="tactile must be"):
        det.check(np.zeros((3, 5)), None)
    with pytest.raises(ValueError, match="NaN"):
        det.check(np.full((1, 20), np.nan), None)
    with pytest.raises(ValueError, match="visual must be"):
        det.check(np.zeros((1, 20)), np.zeros(3))
    with pytest.raises(ValueError, match="3 textures"):
        Subspace.fit(np.zeros((4, 3)), np.array([0, 0, 1, 1]), k=1, quantile=0.9)
    with pytest.raises(ValueError, match="≥ 3 training textures"):
        OODDetector.fit([np.zeros((3, 20))] * 2)


def test_a_frame_checked_once_gives_the_same_answer_per_window(fitted):
    det, _, _ = fitted
    tactile, visual, _, _ = world(n_textures=1, seed=12)
    frame = det.check_visual(visual[0, 0], ["frame_blurred"])
    a = det.check(tactile[0], visual[0, 0], frame_reasons=["frame_blurred"])
    b = det.check(tactile[0], frame=frame)
    assert a.reasons == b.reasons and all("frame_blurred" in r for r in b.reasons)
    np.testing.assert_allclose(a.distance, b.distance)
    assert det.check_visual(None).reasons == ("no_frame",)


def test_statistics_before_extra_groups_are_found_by_position_and_kept_in_json():
    """With extra feature groups the 6 speed/force statistics sit before the groups' columns (the base block
    ends with them): the range checks read those columns, not the groups' (tap features vary per surface)."""
    tactile, _, _, _ = world(n_textures=12, seed=3)
    rng = np.random.default_rng(4)
    groups = [rng.normal(size=(1, 5)) * np.ones((len(t), 1)) for t in tactile]  # one value per surface, like taps
    with_groups = [np.hstack([t, g]) for t, g in zip(tactile, groups)]
    start = tactile[0].shape[1] - 6
    det = OODDetector.fit(with_groups, k_tactile=3, stat_start=start)
    probe = with_groups[0].copy()
    probe[:, -5:] += 50  # a new surface's group features far from the training ones: not a speed or force fault
    reasons = det.check(probe).reasons
    assert not any("speed_out_of_range" in r or "force_out_of_range" in r for r in reasons)
    fast = with_groups[0].copy()
    fast[:, start : start + 3] += 1000  # mm/s
    assert all("speed_out_of_range" in r for r in det.check(fast).reasons)
    again = OODDetector.from_json(det.to_json())
    assert again.stat_start == start and all("speed_out_of_range" in r for r in again.check(fast).reasons)
    # the columns counted from the end (a detector without stat_start) read the groups instead: the fault
    naive = OODDetector.fit(with_groups, k_tactile=3)
    assert any("speed_out_of_range" in r for r in naive.check(probe).reasons)
    with pytest.raises(ValueError, match="start at column"):
        OODDetector.fit(with_groups, k_tactile=3, stat_start=with_groups[0].shape[1] - 2)


def test_taps_outside_their_training_range_are_flagged_and_the_range_kept_in_json():
    """The taps group's columns (3, from taps_start) get the training range (+ margin): a surface whose tap features
    lie outside it is flagged taps_out_of_range, one inside is not; the range survives JSON, and a detector written
    without it (older files) reads as no taps check."""
    tactile, _, _, _ = world(n_textures=12, seed=3)
    rng = np.random.default_rng(5)
    taps = [rng.uniform(1.0, 2.0, size=(1, 3)) * np.ones((len(t), 1)) for t in tactile]  # one value per surface
    with_taps = [np.hstack([t, g]) for t, g in zip(tactile, taps)]
    start = tactile[0].shape[1]
    det = OODDetector.fit(with_taps, k_tactile=3, stat_start=start - 6, taps_start=start)
    inside = with_taps[0].copy()
    assert not any("taps_out_of_range" in r for r in det.check(inside).reasons)
    hard = inside.copy()
    hard[:, start] = 2.0 + 0.2  # past the training maximum by more than the 10 % margin (of a 1-wide range)
    result = det.check(hard)
    assert result.flags.all() and all("taps_out_of_range" in r for r in result.reasons)
    again = OODDetector.from_json(det.to_json())
    assert again.taps_start == start and all("taps_out_of_range" in r for r in again.check(hard).reasons)
    older = det.to_dict()
    for key in ("taps_start", "taps_lo", "taps_hi"):
        del older[key]
    assert not any("taps_out_of_range" in r for r in OODDetector.from_dict(older).check(hard).reasons)
    with pytest.raises(ValueError, match="tap features start at column"):
        OODDetector.fit(with_taps, k_tactile=3, taps_start=start + 1)
