"""Where the viewer's basis images come from: the views of the ring, the captured OLAT frames of a calibrated view
(source `capture`), and a trained model's renders under a dense set of stage lights (source `model`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lightstage.cameras import PinholeCamera, rotation_axis_angle
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.workdir import WorkDir


@dataclass(frozen=True)
class RingView:
    """One view of the ring: a file-safe `name`, the label the page shows, its camera at processed
    resolution, and the calibrated view it is (None for a novel view)."""

    name: str
    label: str
    camera: PinholeCamera
    view: ViewId | None


def ring_camera(calibration, camera: str | None) -> str:
    """The camera whose turntable ring the viewer shows: `camera`, or the one at the median elevation above
    the scene centre (a side view rather than the top or bottom of the rig)."""
    cams = sorted({v.camera for v in calibration.views})
    if camera is not None:
        if camera not in cams:
            raise LightstageError(
                f"--camera {camera!r}: not a calibrated camera (e.g. {', '.join(cams[:5])})"
            )
        return camera
    centre = np.asarray(calibration.scene_centre, np.float64)
    elevation = {}
    for v, vc in calibration.views.items():
        c = vc.camera().center - centre
        elevation.setdefault(v.camera, float(np.degrees(np.arcsin(c[2] / np.linalg.norm(c)))))
    ordered = sorted(cams, key=lambda k: (elevation[k], k))
    return ordered[(len(ordered) - 1) // 2]


def ring_groups(calibration, camera: str, count: int) -> list[str]:
    """`count` groups (0: all) spread evenly over the turntable, in yaw order, that have `camera` calibrated."""
    groups = sorted(
        (g for g in calibration.yaws_deg if ViewId(g, camera) in calibration.views),
        key=lambda g: calibration.yaws_deg[g],
    )
    if not groups:
        raise LightstageError(f"camera {camera!r} has no calibrated view")
    if count <= 0 or count >= len(groups):
        return groups
    picks = np.round(np.linspace(0, len(groups), count, endpoint=False)).astype(int)
    return [groups[i] for i in picks]


def calibrated_ring(calibration, camera: str, groups: list[str]) -> list[RingView]:
    """The calibrated views (GROUP/camera) of the ring."""
    return [
        RingView(
            f"{g}_{camera}", f"{g}/{camera}", calibration.views[ViewId(g, camera)].camera(), ViewId(g, camera)
        )
        for g in groups
    ]


def novel_ring(calibration, ring: list[RingView], per_gap: int) -> list[RingView]:
    """The ring with `per_gap` novel views between consecutive calibrated ones: each calibrated camera carried
    about the calibrated turntable axis by fractions of the yaw step to the next ring view (cyclic)."""
    if per_gap <= 0 or len(ring) < 1:
        return list(ring)
    axis = np.asarray(calibration.axis.direction, np.float64)
    point = np.asarray(calibration.axis.point, np.float64)
    out: list[RingView] = []
    for i, rv in enumerate(ring):
        out.append(rv)
        nxt = ring[(i + 1) % len(ring)]
        step = (calibration.yaws_deg[nxt.view.group] - calibration.yaws_deg[rv.view.group]) % 360.0
        if len(ring) == 1:
            step = 360.0
        for j in range(1, per_gap + 1):
            angle = step * j / (per_gap + 1)
            cam = rotate_about_axis(rv.camera, axis, point, angle)
            out.append(
                RingView(
                    f"{rv.name}_p{angle:05.1f}".replace(".", "p"),
                    f"novel: {rv.label} +{angle:.1f} deg",
                    cam,
                    None,
                )
            )
    return out


def rotate_about_axis(
    camera: PinholeCamera, axis: np.ndarray, point: np.ndarray, angle_deg: float
) -> PinholeCamera:
    """The camera carried rigidly about the axis (direction, point) by `angle_deg` (right-handed): the
    turntable's rotation from one group to the next."""
    rot = rotation_axis_angle(axis, np.deg2rad(angle_deg))
    centre = point + rot @ (camera.center - point)
    R = np.asarray(camera.R) @ rot.T
    return PinholeCamera(camera.K, R, -R @ centre, camera.width, camera.height, camera.dist)


def orbit_ring(model, count: int, size: tuple[int, int]) -> list[RingView]:
    """`count` orbit cameras around the model's bounds (no calibration): elevation 20 deg, evenly in azimuth."""
    from lightstage.training.view_specs import parse_camera

    out = []
    for k in range(count):
        az = 360.0 * k / count
        spec = f"orbit:az={az:g},elev=20,size={size[0]}x{size[1]}"
        named = parse_camera(spec, None, model)
        out.append(RingView(named.name, f"orbit az {az:g} deg", named.camera, None))
    return out


def captured_lights(work: WorkDir, view: ViewId) -> list[int]:
    """The light indices of a view's processed frames on disk."""
    folder = work.frame(FrameId(view.group, view.camera, 0)).parent
    return sorted(int(p.stem) for p in folder.glob("*.exr") if p.stem.isdigit())


MAX_BASIS_BYTES = 4 << 30  # float32 basis images of one view held in memory at once


def check_basis_size(count: int, width: int, height: int, what: str) -> None:
    """One clear error, before any work, when a view's basis images would not fit in memory."""
    need = count * width * height * 3 * 4
    if need > MAX_BASIS_BYTES:
        raise LightstageError(
            f"{what}: {count} basis images of {width}x{height} need {need / 2**30:.1f} GiB per view "
            f"(limit {MAX_BASIS_BYTES / 2**30:.0f} GiB); use fewer --basis-lights or --capture-lights, or a "
            "smaller --display-size"
        )


def capture_basis(
    work: WorkDir,
    calibration,
    view: ViewId,
    max_lights: int | None = None,
    progress: Callable[[int], None] | None = None,
    display: int = 0,
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(directions (L, 3), frames (L, H, W, 3) float32 linear HDR, light indices) of one calibrated view's
    processed OLAT frames, each area-downscaled as it is read to the `display` size (longest side; 0: as
    processed); the directions are the calibrated lights of the view's group. With more frames than
    `max_lights`, that many lights spread over the group's (farthest-point sampling)."""
    from lightstage.records.processed import read_processed
    from lightstage.training.light_basis import farthest_points
    from lightstage.viewer.display import display_size, downscale

    lights = captured_lights(work, view)
    if not lights:
        raise LightstageError(
            f"{work.frame(FrameId(view.group, view.camera, 0)).parent}: no processed frames"
        )
    dirs = calibration.light_directions(view.group)
    if max(lights) >= len(dirs):
        raise LightstageError(
            f"view {view}: frame of light {max(lights)} but the calibration has {len(dirs)} lights in group {view.group}"
        )
    if max_lights is not None and len(lights) > max_lights:
        picked = farthest_points(np.asarray(dirs, np.float64)[lights], max_lights)
        lights = sorted(lights[i] for i in picked)
    cam = calibration.views[view].camera()
    w, h = display_size(cam.width, cam.height, display)
    check_basis_size(len(lights), w, h, f"view {view}")
    frames = np.empty((len(lights), h, w, 3), np.float32)
    for i, light in enumerate(lights):
        frames[i] = downscale(read_processed(work.frame(FrameId(view.group, view.camera, light)))[0], w, h)
        if progress is not None:
            progress(i + 1)
    return np.asarray(dirs, np.float64)[lights], frames, lights
