"""``bench/bench_forward_band_screen.py``: the replay's counts (band searches, screened out,
accepted fallbacks lost) are the claims of its page, so they are checked on calls whose
outcome is known. The verification is replaced by a scripted one that takes the same paths
through the timers' hooks as the real one (the band's general search, then the screen)."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import pytest

import bench.bench_forward_band_screen as bench
import robotd.forward.verify as verify_module


@dataclass(frozen=True)
class _Params:
    fallback_screen: str | None = None


def _verification(accepted: bool, screened: bool) -> SimpleNamespace:
    return SimpleNamespace(
        accepted=accepted, reason="accepted" if accepted else "refused", n_matches=90, n_inliers=40 if accepted else 9,
        n_plane_inliers=0, planar=False, support_area=0.3, range_m=None, n_floor_points=0, sigma_bearing_rad=0.1,
        sigma_yaw_rad=0.02, noise_px=1.0, planarity_chi2=None, level_yaw_rad=0.0, rotation=None,
        translation_dir=None, screened=screened)


@pytest.fixture
def scripted(monkeypatch):
    """``old`` names the call's story: whether the band search runs, whether RANSAC accepts
    there, whether the screen lets it through."""
    monkeypatch.setattr(verify_module, "_general_motion", lambda *a, **k: None)
    monkeypatch.setattr(verify_module, "_screen_passes", lambda story: story["screen_passes"])

    def verify_pair(old, new, params, k):
        if not old["band"]:
            return _verification(old["accepted"], False)
        if params.fallback_screen is not None and not verify_module._screen_passes(old):
            return _verification(False, True)
        verify_module._general_motion(half_inliers=False)
        return _verification(old["accepted"], False)

    monkeypatch.setattr(verify_module, "verify_pair", verify_pair)


def _call(image, band, accepted, screen_passes=True):
    return (image, {"band": band, "accepted": accepted, "screen_passes": screen_passes}, None, _Params(), None)


def test_the_replay_counts_band_searches_screened_calls_and_lost_acceptances(scripted):
    calls = [
        _call(0, band=False, accepted=True),  # the guided search decides: no band
        _call(1, band=True, accepted=True, screen_passes=True),  # band accepted, screen passes
        _call(1, band=True, accepted=True, screen_passes=False),  # band accepted, screened: lost
        _call(2, band=True, accepted=False, screen_passes=False),  # failing band search screened out
        _call(3, band=True, accepted=False, screen_passes=True),  # failing band search, screen passes
    ]
    res = bench.replay(calls, rounds=2)
    assert res["calls"] == 5
    assert res["images_verified"] == 4
    assert res["band_searches"] == 4
    assert res["band_accepted"] == 2
    assert res["screened_out"] == 2
    assert res["accepted_lost"] == 1
    assert res["accepted_new"] == 0
    assert res["differ_where_not_screened"] == 0
    assert set(res["ratios"]) == {f"{p}_{k}" for p in ("band_ms", "call_ms", "image_ms")
                                  for k in ("median", "p99", "max", "total")}


def test_an_outcome_changed_where_nothing_was_screened_is_counted(scripted, monkeypatch):
    scripted_verify = verify_module.verify_pair

    def moody(old, new, params, k):
        v = scripted_verify(old, new, params, k)
        if params.fallback_screen is not None and not v.screened:
            v.n_inliers += 1  # the screen's run changed an answer it should not touch
        return v

    monkeypatch.setattr(verify_module, "verify_pair", moody)
    res = bench.replay([_call(0, band=True, accepted=True), _call(1, band=False, accepted=False)], rounds=1)
    assert res["differ_where_not_screened"] == 2
    assert res["screened_out"] == 0


def test_the_page_shows_each_sequences_counts(scripted):
    res = bench.replay([_call(0, band=True, accepted=True, screen_passes=False), _call(1, band=False, accepted=True)],
                       rounds=1)
    lines = bench.page({"machine": {"cpu_model": "cpu", "cpu_count": 2, "opencv": "4"}, "rounds": 1,
                        "load_avg": [0.5, 0.5, 0.5], "commit": "abc", "sequences": {"seq": res}})
    row = next(line for line in lines if line.startswith("| seq | 2 (2)"))
    assert row == "| seq | 2 (2) | 1 | 1 | 1 | 1 | 0 |"
    assert sum(line.startswith("| seq | ") for line in lines) == 4  # the counts and three time rows
