"""Bulb detection: sub-pixel centre of a clipped disc in a 4x area-downscaled frame; partly hidden bulbs rejected."""

from __future__ import annotations

import cv2
import numpy as np

from lightstage.calibration.bulbs import detect_bulb

CLIP = 4.4


def _frame(centre_raw, radius_raw, size=(96, 64), background=0.01):
    """Processed (4x area mean) RGB + saturation flags of a raw frame showing a clipped disc (raw pixel centres
    inside the disc are clipped), on a dim background."""
    w, h = size
    rows, cols = np.mgrid[0 : 4 * h, 0 : 4 * w]
    disc = (cols + 0.5 - centre_raw[0]) ** 2 + (rows + 0.5 - centre_raw[1]) ** 2 <= radius_raw**2
    raw = np.where(disc, CLIP, background).astype(np.float32)
    rgb = cv2.resize(np.repeat(raw[..., None], 3, axis=-1), (w, h), interpolation=cv2.INTER_AREA)
    sat = disc.reshape(h, 4, w, 4).any(axis=(1, 3))
    return rgb, sat


def test_detect_bulb_centre_is_subpixel():
    mask = np.zeros((64, 96), bool)
    mask[20:50, 10:30] = True  # the object, away from the bulb
    for cx, cy in [(250.3, 100.7), (261.0, 141.25), (300.8, 90.1)]:
        rgb, sat = _frame((cx, cy), 15.0)
        u, v, area = detect_bulb(rgb, sat, mask, CLIP)
        # Processed coordinates are raw / 4 under the pixel-centre convention.
        assert abs(u - cx / 4) < 0.05 and abs(v - cy / 4) < 0.05
        assert abs(area - np.pi * (15.0 / 4) ** 2) < 2.0


def test_detect_bulb_rejects_hidden_and_cut_bulbs():
    rgb, sat = _frame((250.3, 100.7), 15.0)
    mask = np.zeros((64, 96), bool)
    mask[:, 66:] = True  # the object's silhouette touches the bulb: it may be partly hidden
    assert detect_bulb(rgb, sat, mask, CLIP) is None
    rgb, sat = _frame((4.0, 100.0), 15.0)  # cut by the image border
    assert detect_bulb(rgb, sat, np.zeros((64, 96), bool), CLIP) is None
    rgb, sat = _frame((250.0, 100.0), 0.0)  # nothing clipped
    assert detect_bulb(rgb, sat, np.zeros((64, 96), bool), CLIP) is None
