"""Feature extraction (robotd.forward.features): the ORB parameters and the image scaled
down before detection."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robotd.forward.features import FeatureExtractor, FeatureParams


def _scene(width: int, height: int) -> np.ndarray:
    """A textured grey image: random blocks, smoothed (corners everywhere)."""
    rng = np.random.default_rng(3)
    small = rng.integers(0, 256, (height // 16, width // 16), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (width, height), interpolation=cv2.INTER_NEAREST), (5, 5), 1.0)


def test_an_image_scaled_down_gives_keypoints_in_the_full_images_pixels():
    """Detecting on the image at half size with ``image_scale`` 0.5 finds the keypoints the
    half-size image itself gives, at twice their coordinates (pixel centres kept)."""
    big = _scene(640, 480)
    half = cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA)
    orb = FeatureParams(kind="orb", max_features=300)
    ref = FeatureExtractor(orb)(half)
    got = FeatureExtractor(FeatureParams(kind="orb", max_features=300, image_scale=0.5))(big)
    assert got.image_size_px == (640, 480) and len(got) == len(ref) > 100
    np.testing.assert_allclose(got.keypoints_px, (ref.keypoints_px + 0.5) * 2.0 - 0.5, atol=1e-4)
    np.testing.assert_array_equal(got.descriptors, ref.descriptors)


def test_orb_parameters_reach_opencv():
    """The pyramid's levels reach OpenCV's detector; a high FAST threshold finds fewer
    keypoints."""
    im = _scene(640, 480)
    ex8 = FeatureExtractor(FeatureParams(kind="orb", max_features=1000))
    ex2 = FeatureExtractor(FeatureParams(kind="orb", max_features=1000, orb_levels=2))
    assert ex2._detector.getNLevels() == 2 and ex8._detector.getNLevels() == 8
    hard = FeatureExtractor(FeatureParams(kind="orb", max_features=1000, orb_fast_threshold=80))(im)
    assert len(hard) < len(ex8(im))


@pytest.mark.parametrize("field", [{"orb_levels": 0}, {"orb_scale_factor": 1.0}, {"orb_fast_threshold": 0},
                                   {"image_scale": 0.0}, {"image_scale": 1.5}])
def test_bad_orb_parameters_are_refused(field: dict) -> None:
    with pytest.raises(ValueError):
        FeatureParams(kind="orb", **field)
