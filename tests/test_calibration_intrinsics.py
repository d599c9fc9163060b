"""`calibrate-intrinsics`: ChArUco board images rendered with a known camera give back its intrinsics."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightstage.calibration.intrinsics import CharucoBoardSpec, calibrate_folder
from lightstage.cameras import look_at
from lightstage.errors import LightstageError

W, H = 800, 600
# OpenCV convention (first pixel centre at 0) for rendering with warpPerspective; lightstage adds 0.5.
K_CV = np.array([[900.0, 0.0, 401.5], [0.0, 900.0, 297.5], [0.0, 0.0, 1.0]])


def _render_views(spec: CharucoBoardSpec, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    board = spec.board()
    px_per_m = 4000.0
    bw, bh = (
        int(spec.squares_x * spec.square_length * px_per_m),
        int(spec.squares_y * spec.square_length * px_per_m),
    )
    tex = board.generateImage((bw, bh))
    # Board pixel (u, v) -> board plane point (u / px_per_m, v / px_per_m, 0) (metres).
    S = np.array([[1.0 / px_per_m, 0, 0], [0, 1.0 / px_per_m, 0], [0, 0, 1.0]])
    centre = np.array([bw / px_per_m / 2, bh / px_per_m / 2, 0.0])
    images = []
    for _ in range(n):
        direction = np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), -1.0])
        cam = centre + 0.55 * direction / np.linalg.norm(direction)
        R, t = look_at(cam, centre + rng.normal(0, 0.02, 3), up=(0.0, -1.0, 0.0))
        Hm = K_CV @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        img = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_AREA, borderValue=128)
        images.append(np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8))
    return images


def test_charuco_intrinsics_recovered(tmp_path: Path):
    spec = CharucoBoardSpec()
    rng = np.random.default_rng(0)
    cam_dir = tmp_path / "boards" / "cam00"
    cam_dir.mkdir(parents=True)
    for i, img in enumerate(_render_views(spec, 16, rng)):
        cv2.imwrite(str(cam_dir / f"{i:02d}.png"), img)
    out = tmp_path / "intrinsics.json"
    doc = calibrate_folder(tmp_path / "boards", spec, out)
    cam = json.loads(out.read_text())["cameras"]["cam00"]
    assert cam == doc["cameras"]["cam00"]
    K = np.asarray(cam["K"])
    assert cam["num_images"] >= 6 and cam["rms_px"] < 0.5
    assert K[0, 0] == pytest.approx(900.0, rel=5e-3)
    assert K[1, 1] == pytest.approx(900.0, rel=5e-3)
    # lightstage pixel-centre convention: OpenCV's cx + 0.5.
    assert K[0, 2] == pytest.approx(K_CV[0, 2] + 0.5, abs=1.5)
    assert K[1, 2] == pytest.approx(K_CV[1, 2] + 0.5, abs=1.5)
    # No lens distortion was rendered: the fitted model displaces no pixel by more than a pixel (k1 k2 k3 are
    # strongly correlated, so compare their effect, not the coefficients).
    k1, k2, p1, p2, k3 = cam["dist"]
    r = np.linspace(0.0, 0.8 * np.hypot(W / 2, H / 2) / K[0, 0], 50)  # the part of the image the board covers
    radial_px = np.abs((k1 * r**2 + k2 * r**4 + k3 * r**6) * r * K[0, 0])
    assert radial_px.max() < 1.0
    assert abs(p1) < 5e-3 and abs(p2) < 5e-3


def test_charuco_without_board_is_a_clear_error(tmp_path: Path):
    cam_dir = tmp_path / "boards" / "cam00"
    cam_dir.mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(cam_dir / f"{i}.png"), np.full((H, W), 100, np.uint8))
    with pytest.raises(LightstageError, match="ChArUco board found in 0 of 3"):
        calibrate_folder(tmp_path / "boards", CharucoBoardSpec(), tmp_path / "x.json")
