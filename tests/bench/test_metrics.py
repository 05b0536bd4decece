"""Image metrics on analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from dlacli.bench.metrics import alpha_iou, masked_psnr, psnr


def test_psnr_analytic():
    gt = np.zeros((4, 8, 8, 3))
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0)
    assert psnr(gt, gt) == float("inf")
    mask = np.zeros((4, 8, 8))
    mask[:, :4] = 1
    pred = gt.copy()
    pred[:, :4] = 0.01  # error only inside the mask: masked PSNR 40 dB, whole image 3 dB better
    assert masked_psnr(pred, gt, mask) == pytest.approx(40.0)
    assert psnr(pred, gt) == pytest.approx(40.0 + 10 * np.log10(2))


def test_alpha_iou():
    a = np.zeros((10, 10))
    b = np.zeros((10, 10))
    a[:, :6] = 1
    b[:, 4:] = 1
    assert alpha_iou(a, b) == pytest.approx(20 / 100)
    assert alpha_iou(a, a) == 1.0
