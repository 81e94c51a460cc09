"""Image metrics against values worked out by hand on tiny images."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evcal.metrics import image_metrics, psnr, psnr_paper, rmse, ssim, ssim_paper

# a 2x2 pair: differences -2, 2, 0, -4 -> squares 4, 4, 0, 16 -> MSE = 24 / 4 = 6
A = np.array([[10.0, 20.0], [30.0, 40.0]])
B = np.array([[12.0, 18.0], [30.0, 44.0]])
MSE_AB = 6.0


def test_rmse_by_hand() -> None:
    assert rmse(A, B) == pytest.approx(math.sqrt(MSE_AB), rel=1e-15)
    assert rmse(np.zeros((3, 3)), np.full((3, 3), 3.0)) == 3.0


def test_psnr_by_hand() -> None:
    assert psnr(A, B) == pytest.approx(10 * math.log10(255.0**2 / MSE_AB), rel=1e-14)
    # MSE = 2.55^2 = 255^2 / 1e4 -> 40 dB; another range scales R^2
    assert psnr(np.zeros((2, 2)), np.full((2, 2), 2.55)) == pytest.approx(40.0, abs=1e-12)
    assert psnr(np.zeros((2, 2)), np.full((2, 2), 0.01), data_range=1.0) == pytest.approx(40.0)


def test_psnr_paper_is_exactly_twice_psnr() -> None:
    assert psnr_paper(A, B) == 2 * psnr(A, B)
    assert psnr_paper(A, B) == pytest.approx(20 * math.log10(255.0**2 / MSE_AB), rel=1e-14)
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.uniform(0, 255, (2, 8, 8))
        assert psnr_paper(a, b) == 2 * psnr(a, b)
        assert image_metrics(a, b)["psnr_paper"] == 2 * image_metrics(a, b)["psnr"]


def test_ssim_paper_by_hand() -> None:
    # means 25 and 26; deviations (-15, -5, 5, 15) and (-14, -8, 4, 18); N - 1 = 3
    mu_a, mu_b = 25.0, 26.0
    s_aa = (225 + 25 + 25 + 225) / 3
    s_bb = (196 + 64 + 16 + 324) / 3
    s_ab = (210 + 40 + 20 + 270) / 3
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    expected = ((2 * mu_a * mu_b + c1) * (2 * s_ab + c2)) / (
        (mu_a**2 + mu_b**2 + c1) * (s_aa + s_bb + c2)
    )
    assert ssim_paper(A, B) == pytest.approx(expected, rel=1e-14)
    assert ssim_paper(A, B) == pytest.approx(0.983568, abs=1e-6)  # the number, for the record


def test_identical_images() -> None:
    img = np.random.default_rng(0).uniform(0, 255, (12, 10))
    assert rmse(img, img) == 0.0
    assert psnr(img, img) == float("inf")
    assert psnr_paper(img, img) == float("inf")
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    assert ssim_paper(img, img) == pytest.approx(1.0, abs=1e-12)
    m = image_metrics(img, img.copy())
    assert set(m) == {"rmse", "psnr", "ssim", "psnr_paper", "ssim_paper"}
    assert m["rmse"] == 0.0
    assert m["psnr"] == math.inf
    assert m["ssim"] == pytest.approx(1.0)


def test_ssim_is_skimage_uniform_7x7_window() -> None:
    # on a 7x7 image scikit-image keeps only the central window, which is the whole image:
    # with a uniform window and sample covariances it equals the global SSIM
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 255, (7, 7))
    b = np.clip(a + rng.normal(0, 20, (7, 7)), 0, 255)
    assert ssim(a, b) == pytest.approx(ssim_paper(a, b), rel=1e-9)
    # a smooth ramp with noise in its top half: each local window sees the noise against
    # little local structure, the global window against the whole ramp
    a = np.add.outer(np.linspace(20, 230, 20), np.zeros(24))
    b = a.copy()
    b[:10] += rng.normal(0, 20, (10, 24))
    assert 0 < ssim(a, b) < ssim_paper(a, b) - 0.05


def test_metrics_order_sensible() -> None:
    rng = np.random.default_rng(2)
    ref = rng.uniform(20, 230, (16, 16))
    good = ref + rng.normal(0, 2, ref.shape)
    bad = ref + rng.normal(0, 20, ref.shape)
    mg, mb = image_metrics(good, ref), image_metrics(bad, ref)
    assert mg["rmse"] < mb["rmse"]
    for key in ("psnr", "ssim", "psnr_paper", "ssim_paper"):
        assert mg[key] > mb[key]


def test_input_errors() -> None:
    with pytest.raises(ValueError, match=r"shapes \(2, 2\) and \(2, 3\)"):
        rmse(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="second image has 1 NaN or infinite"):
        psnr(np.zeros((2, 2)), np.array([[0, 0], [0, np.nan]]))
    with pytest.raises(ValueError, match="first image has 2 NaN or infinite"):
        ssim_paper(np.array([[np.inf, 0], [0, -np.inf]]), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="data_range"):
        psnr(A, B, data_range=0)
    with pytest.raises(ValueError, match="at least 7x7"):
        ssim(A, B)
    with pytest.raises(ValueError, match="empty"):
        rmse(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="1 pixel"):
        ssim_paper(np.zeros((1, 1)), np.zeros((1, 1)))
    with pytest.raises(ValueError, match="image_metrics: images have shapes"):
        image_metrics(np.zeros((8, 8)), np.zeros((8, 9)))
