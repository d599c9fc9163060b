"""Camera intrinsics (with OpenCV distortion k1 k2 p1 p2 k3) from ChArUco board images, OpenCV 5 API.

OpenCV 5 dropped the free ChArUco functions: corners come from `cv2.aruco.CharucoDetector.detectBoard` and the
fit from `cv2.calibrateCamera` on the matched object/image points (`CharucoBoard.matchImagePoints`). OpenCV's
corner coordinates put the centre of the first pixel at (0, 0); lightstage puts it at (0.5, 0.5), so cx and cy
are shifted by +0.5 on output.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: squares, square and marker side (metres), ArUco dictionary name."""

    squares_x: int = 11
    squares_y: int = 8
    square_length: float = 0.03
    marker_length: float = 0.022
    dictionary: str = "DICT_5X5_100"

    def board(self):
        import cv2

        if not hasattr(cv2.aruco, self.dictionary):
            raise LightstageError(f"unknown ArUco dictionary {self.dictionary!r}")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )


@dataclass(frozen=True)
class IntrinsicsFit:
    """Result of one camera's fit (K in lightstage's pixel-centre convention)."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float
    num_images: int
    num_corners: int


def detect_charuco(image: np.ndarray, spec: CharucoBoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """(object points (N, 3), image points (N, 2)) of the board corners seen in one image, or None."""
    import cv2

    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < 6:
        return None
    obj, img = board.matchImagePoints(corners, ids)
    if obj is None or len(obj) < 6:
        return None
    return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


def calibrate_intrinsics(
    images: list[Path], spec: CharucoBoardSpec, min_images: int = 4, fit_k3: bool = False
) -> IntrinsicsFit:
    """Fit K and distortion of one camera from its board images (k3 held at 0 unless `fit_k3`: with board
    views that do not reach the image corners k1, k2, k3 are strongly correlated and k3 overfits)."""
    import cv2

    obj_pts, img_pts, size = [], [], None
    for path in images:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise LightstageError(f"{path}: cannot read board image")
        if size is None:
            size = img.shape[::-1]
        elif img.shape[::-1] != size:
            raise LightstageError(
                f"{path}: size {img.shape[::-1]} differs from the camera's other images {size}"
            )
        found = detect_charuco(img, spec)
        if found is not None:
            obj_pts.append(found[0])
            img_pts.append(found[1])
    if len(obj_pts) < min_images:
        raise LightstageError(
            f"ChArUco board found in {len(obj_pts)} of {len(images)} images (need {min_images}); "
            "check the board description (--squares, --square-length, --marker-length, --dictionary)"
        )
    flags = 0 if fit_k3 else cv2.CALIB_FIX_K3
    rms, K, dist, _, _ = cv2.calibrateCamera(obj_pts, img_pts, size, None, None, flags=flags)
    K = np.asarray(K, dtype=np.float64)
    K[0, 2] += 0.5  # OpenCV: first pixel centre at 0; lightstage: at 0.5
    K[1, 2] += 0.5
    d = np.zeros(5)
    flat = np.asarray(dist, dtype=np.float64).ravel()
    d[: min(5, flat.size)] = flat[:5]
    return IntrinsicsFit(
        K, d, int(size[0]), int(size[1]), float(rms), len(obj_pts), int(sum(len(p) for p in obj_pts))
    )


def calibrate_folder(root: Path, spec: CharucoBoardSpec, out: Path) -> dict[str, Any]:
    """Fit every camera in `root/<camera id>/*.png|jpg|tif` and write the intrinsics JSON read by `calibrate`."""
    root = Path(root)
    if not root.is_dir():
        raise LightstageError(f"{root}: board image folder does not exist")
    cams: dict[str, Any] = {}
    for cam_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        images = sorted(
            p for p in cam_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff")
        )
        if not images:
            continue
        try:
            fit = calibrate_intrinsics(images, spec)
        except LightstageError as e:
            raise LightstageError(f"{cam_dir}: {e}") from None
        cams[cam_dir.name] = {
            "K": fit.K.tolist(),
            "dist": fit.dist.tolist(),
            "width": fit.width,
            "height": fit.height,
            "rms_px": fit.rms_px,
            "num_images": fit.num_images,
            "num_corners": fit.num_corners,
        }
    if not cams:
        raise LightstageError(f"{root}: no <camera id>/ folders with board images")
    doc = {
        "format_version": 1,
        "convention": "K at raw resolution, pixel (i, j) centred at (i + 0.5, j + 0.5); dist = k1 k2 p1 p2 k3",
        "board": spec.__dict__,
        "cameras": cams,
    }
    write_json_atomic(out, doc)
    return doc
