"""Simulated mirror-ball light-probe frames (the `probe/` folder of a capture, see capture.probe).

A chrome ball (static in the world, like the object, which is removed for the probe) is photographed by every
camera under each light alone at a few turntable positions, plus one `ambient` frame per view with the room
light on. Everything uses the TRUE geometry:

- OLAT frame: the light's mirror highlight is a point at the specular point x of the sphere (its normal bisects
  the directions to the camera centre and to the light: Alhazen's problem, solved by bisection on the great
  circle in the plane of camera, centre and light), projected with the true pinhole camera and spread by a
  Gaussian PSF integrated exactly over each pixel (erf differences). The bulb itself clips where it is in view
  and the ball does not hide it. The ball's disc reflects the dark stage interior (reflectance x background).
- Ambient frame: the ball's disc (pixel coverage by supersampling around the silhouette) reflecting a uniform
  room radiance, blurred by the same PSF, over the background.
- Noise, ADC and clipping as the capture frames (render.add_noise_and_clip), seeded per frame with streams
  distinct from the capture's, so the bytes do not depend on the number of workers.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lightstage.cameras import PinholeCamera
from lightstage.capture.probe import DEFAULT_AMBIENT_TEMPLATE, DEFAULT_PROBE_TEMPLATE, ProbeInfo
from lightstage.frames import write_exr
from lightstage.simulator.render import POOL_MAX_VALUES, add_noise_and_clip
from lightstage.simulator.scene import SimScene

if TYPE_CHECKING:
    from lightstage.capture.stage import Stage
    from lightstage.simulator.geometry import TrueGeometry
from lightstage.simulator.probe_optics import (
    Highlight,
    ProbeSettings,
    ball_centre_rig,
    probe_base_images,
    probe_positions,
    render_probe_olat,
)


# ---- jobs ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProbeJob:
    """All inputs needed to render and write one view's probe frames (picklable)."""

    root: Path
    position: str
    camera: str
    group_index: int  # indices in the full stage (seed streams do not depend on selections)
    camera_index: int
    camera_model: PinholeCamera  # true camera
    light_positions: np.ndarray  # (L, 3) true world positions
    light_ids: tuple[int, ...]
    light_seed_ids: tuple[int, ...]
    scene: SimScene
    settings: ProbeSettings
    ref_light_distance: float
    saturation: float
    seed: int
    path_template: str = DEFAULT_PROBE_TEMPLATE
    ambient_template: str = DEFAULT_AMBIENT_TEMPLATE
    compression: str = "piz"  # as the capture's raw frames (render.ViewJob)
    attributes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ProbeViewRecord:
    """What a probe job reports back."""

    position: str
    camera: str
    highlights: tuple[Highlight, ...]
    bulbs: dict[int, int]  # light id -> unoccluded bulb pixels in view
    peak: float  # brightest noise-free highlight pixel
    seconds: float


def render_probe_view(job: ProbeJob) -> ProbeViewRecord:
    """Render and write one view's OLAT probe frames and its ambient frame."""
    start = time.perf_counter()
    cam = job.camera_model
    _, olat_base, ambient = probe_base_images(cam, job.scene, job.settings)
    npix = cam.width * cam.height * 3
    pool = None
    if npix <= POOL_MAX_VALUES:
        pool = np.random.default_rng([job.seed, 8, job.group_index, job.camera_index]).standard_normal(
            2 * npix, dtype=np.float32
        )

    def normals(stream: list[int]) -> np.ndarray:
        rng = np.random.default_rng([job.seed, 7, job.group_index, job.camera_index, *stream])
        if pool is not None:
            off = int(rng.integers(npix))
            return pool[off : off + npix]
        return rng.standard_normal(npix, dtype=np.float32)

    def write(path: Path, img: np.ndarray, stream: list[int]) -> None:
        raw = add_noise_and_clip(img, job.scene, job.saturation, normals(stream))
        write_exr(path, raw, half=True, compression=job.compression, attributes=job.attributes)

    highlights, bulbs, peak = [], {}, 0.0
    for lid, sid, p in zip(job.light_ids, job.light_seed_ids, job.light_positions, strict=True):
        img, hl, bulb = render_probe_olat(
            cam, p, job.scene, job.settings, job.ref_light_distance, olat_base, light_id=lid
        )
        highlights.append(hl)
        if bulb is not None:
            bulbs[lid] = int(bulb[0].size)
        if hl.visible:
            i, j = int(np.floor(hl.uv[0])), int(np.floor(hl.uv[1]))
            win = img[max(j - 2, 0) : j + 3, max(i - 2, 0) : i + 3, 1]
            peak = max(peak, float(win[win < job.scene.nuisances.bulb_radiance].max(initial=0.0)))
        path = job.root / job.path_template.format(position=job.position, camera=job.camera, light=lid)
        write(path, img, [1, sid])
    path = job.root / job.ambient_template.format(position=job.position, camera=job.camera)
    write(path, ambient, [0])
    return ProbeViewRecord(
        job.position, job.camera, tuple(highlights), bulbs, peak, time.perf_counter() - start
    )


def probe_jobs(
    root: Path,
    stage: Stage,
    truth: TrueGeometry,
    scene: SimScene,
    seed: int,
    group_indices: dict[str, int],
    camera_indices: dict[str, int],
    light_seed_ids: tuple[int, ...],
    settings: ProbeSettings | None = None,
    attributes: dict | None = None,
) -> tuple[ProbeInfo, list[ProbeJob]]:
    """probe.yaml's ProbeInfo and one job per (position, camera) of a simulated capture. `group_indices` and
    `camera_indices` map names to indices in the full preset stage (seed streams)."""
    settings = settings if settings is not None else ProbeSettings()
    positions = probe_positions(stage, settings)
    info = ProbeInfo(
        radius_m=settings.radius_m,
        positions=tuple(positions),
        notes={
            "simulator": "lightstage.simulator.probe",
            "ball": f"chrome ball, radius {settings.radius_m} m, reflectance {settings.reflectance}",
            "position_groups": {p: p for p in positions},
            "exposure": "set so the lights' mirror highlights do not clip (brightest pixel about "
            f"{settings.highlight_peak}, cutoff {stage.saturation}); bulbs in view still clip",
            "ambient": "room light on, stage lights off: the ball's silhouette",
            "lights": "indices as in stage.yaml",
        },
    )
    jobs = [
        ProbeJob(
            root=Path(root),
            position=g,
            camera=c.id,
            group_index=group_indices[g],
            camera_index=camera_indices[c.id],
            camera_model=truth.view_camera(stage, g, c.id),
            light_positions=truth.light_positions(g),
            light_ids=tuple(lt.index for lt in stage.lights),
            light_seed_ids=tuple(light_seed_ids),
            scene=scene,
            settings=settings,
            ref_light_distance=stage.sphere_radius,
            saturation=stage.saturation,
            seed=seed,
            path_template=info.path_template,
            ambient_template=info.ambient_template,
            attributes=dict(attributes or {}),
        )
        for g in positions
        for c in stage.cameras
    ]
    return info, jobs


def probe_ground_truth(
    truth: TrueGeometry, settings: ProbeSettings, positions: list[str], records: list[ProbeViewRecord]
) -> dict[str, Any]:
    """ground_truth/probe.json: the ball (world and per-position rig frame), settings, the true highlights."""
    c = np.asarray(settings.centre_world, np.float64)
    return {
        "radius_m": settings.radius_m,
        "ball_centre_world": c.tolist(),
        "positions": {
            g: {
                "group": g,
                "yaw_deg": truth.yaws_deg[g],
                "ball_centre_rig": ball_centre_rig(c, truth.yaws_deg[g], truth.axis).tolist(),
            }
            for g in positions
        },
        "settings": asdict(settings),
        "highlights": [
            {
                "position": r.position,
                "camera": r.camera,
                "light": h.light,
                "uv": [float(h.uv[0]), float(h.uv[1])],
                "point_world": h.point_world.tolist(),
                "visible": h.visible,
                "energy": h.energy,
            }
            for r in records
            for h in r.highlights
        ],
        "bulbs_in_view": [
            {"position": r.position, "camera": r.camera, "light": lt, "pixels": n}
            for r in records
            for lt, n in r.bulbs.items()
        ],
        "peak_highlight_pixel": max((r.peak for r in records), default=0.0),
        "content": "ball centre static in the world; rig frame = the group's rig frame (x_w = R_g x_r + t_g, "
        "true axis and yaw); highlights: projection of the mirror-reflection point of each light's centre "
        "(pixel (i, j) spans [i, i+1) x [j, j+1)), visible = faces camera and light and inside the image",
    }


__all__ = [
    "ProbeSettings",
    "ProbeJob",
    "ProbeViewRecord",
    "render_probe_view",
    "probe_jobs",
    "probe_ground_truth",
]
