"""The preprocess stage's configuration: one dataclass with defaults, read by the strict loader (`from_dict`)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from typing import Any

from lightstage.config import ConfigError, load
from lightstage.frames import COMPRESSIONS
from lightstage.preprocess.decoder_choice import CHOICES


@dataclass(frozen=True)
class PreprocessConfig:
    """Parameters of downscaling, per-view statistics, segmentation and flare scoring. Segmentation's
    thresholds are measured per view (background level and spread, object level); the parameters below say
    how far above the measured background a pixel must be, never an absolute level (docs/preprocess.md)."""

    # ---- downscale / output frames
    # compression of the processed frames' colour part: none | rle | piz | zip (lossless only; the saturation
    # flags are always RLE). Noisy HDR colour barely compresses, so "none" is the default: 16.9 MB per 2048x1366
    # frame for the cheapest write; "piz" makes frames ~1/3 smaller for more CPU (docs/benchmarks.md).
    compression: str = "none"
    band_rows: int = 32  # raw rows decoded and downscaled per band (multiple of 4): stays in cache
    # raw frame decoder, same results: auto (each worker times both on its first frames and keeps the cheaper:
    # which one wins depends on the machine, preprocess/decoder_choice.py) | openexr (whole frame, then banded
    # downscale; +270 MB per worker) | bands (OpenImageIO scanline bands: never the whole frame in memory)
    decoder: str = "auto"
    # ---- reliability
    read_timeout_s: float = (
        120.0  # a raw frame not read within this fails the task naming it (stalled storage)
    )
    max_bad_fraction: float = 0.05  # the stage fails when more than this fraction of frames is missing or bad
    # ---- scheduling
    chunk_lights: int = 32  # lights per task: a chunk's partial statistics merge with the others in a tree
    window: int = 0  # tasks in flight with a dask client (0: 4 per worker thread)
    # ---- segmentation (on the processed resolution)
    segmentation: str = "adaptive"  # adaptive | lit_fraction (the old fixed-fraction rule)
    # adaptive: a pixel's lit levels are the brightnesses these fractions of its frames exceed ...
    # (and `mean`: the mean luminance over the stack, where a dark part lit well in one or two frames stands out)
    brightness_quantiles: str = "0.1,0.25"
    min_quantile_frames: float = 2.0  # ... and at least this many frames (a flare is in one, rarely two)
    border_width: float = (
        0.03  # ... the background is first measured in a border ring this wide (x short side)
    )
    background_sigmas: float = 3.0  # foreground: above the local background by this many local spreads ...
    contrast_fraction: float = 0.3  # ... and by this fraction of the way (in stops) to the object level ...
    min_contrast_stops: float = 1.0  # ... and by at least this many stops
    background_blur: float = 0.1  # smoothing of the local background map (x the frame diagonal)
    colour_band: int = 3  # pixels outside the silhouette that colour may add (0: no colour refinement)
    # lit_fraction (and the per-frame `lit` statistic): a pixel is lit in a frame when brighter than
    # lit_ratio x the frame's dark level + lit_floor x the stage's saturation cutoff, foreground when lit in
    # at least min_lit_fraction of its unsaturated frames (fixed numbers: tuned on the old clean simulator)
    lit_ratio: float = 4.0
    lit_floor: float = 2.0**-13
    min_lit_fraction: float = 0.12
    # foreground pixels are saturated in at most this fraction of frames (1: no bound; an overexposed object
    # clips in most frames, a bulb in view in its own light's frame only)
    max_saturated_fraction: float = 1.0
    open_radius: int = 1  # morphological opening radius (pixels)
    close_radius: int = 2  # morphological closing radius (pixels)
    min_component_fraction: float = 0.05  # keep components with at least this fraction of the largest one ...
    centre_weight: float = 0.5  # ... scored by area, discounted by distance from the image centre
    fill_holes: bool = True
    band_width: int = 6  # zone map: pixels on each side of the silhouette that form the band
    # ---- cross-group consistency (consistency.py): once every view of a camera has its mask, masked pixels
    # whose mean image agrees with most of the camera's other groups (within background_sigmas of the noise
    # measured on that camera's background) are stage structure fixed to the camera, not the turning object
    consistency: bool = True
    consistency_max_removed: float = (
        0.5  # ... unless that would remove more than this fraction of a view's mask
    )
    # ---- sanity flags of a view's mask (view.json "flags", the report, the console, overlay.png)
    flag_border_fraction: float = 0.5  # the mask covers more than this fraction of the frame's perimeter
    flag_min_fraction: float = 0.002  # foreground fraction below this ...
    flag_max_fraction: float = 0.6  # ... or above this
    flag_group_ratio: float = 2.5  # foreground fraction this many times off the median of its group's views
    # a flagged view is an error of the stage unless the capture supplies its mask (masks/<g>/<c>.png) or it is
    # listed here ("group/camera", e.g. "000/cam03"): its mask is then accepted as it is
    accept_masks: tuple[str, ...] = ()
    # ---- flare / outlier frames
    flare_dilate: int = 8  # mask dilation (pixels) before measuring energy outside it
    flare_thumb: int = 8  # per-frame thumbnails for flare scoring are this many times smaller
    # what a frame with a bulb or flare in view becomes (docs/preprocess.md): mask (the frame stays in the split;
    # its flare and bulb pixels are flagged in preprocess/views/<g>/<c>/flare/<lll>.png, carry a flag bit in the
    # shards and no loss) | drop (the frame is rejected when its flare score exceeds flare_threshold)
    flare_policy: str = "mask"
    flare_threshold: float = 0.15  # `drop`: reject a frame when its flare score exceeds this
    flare_margin: float = (
        0.1  # a light is in view within this fraction of the frame diagonal outside the frame
    )
    flare_veil: float = 0.05  # the veil disc reaches where the flare adds this fraction of the object's level
    # the frame-level drop (preprocess/broken.py): a frame this many robust spreads, and at least min_stops, from
    # the same camera and light in the other groups is broken (a light misfired, a wrong exposure)
    broken_sigmas: float = 6.0
    broken_min_stops: float = 1.0
    max_lost_fraction: float = 0.1  # flag views that lose more than this fraction of frames (bad + rejected)
    # ---- SfM images (calibration's input, preprocess/sfm_image.py)
    sfm_max_side: int = (
        2048  # at raw / f, the largest with long side <= this (f <= 4; 0: processed resolution)
    )
    # frames (evenly spread lights, the same for every view) averaged per view. Many: the lights turn with the
    # rig, so the object's shading changes between groups and moves its SIFT keypoints; averaging 32 lights
    # (nearly uniform light) instead of 8 took calibration's worst camera from 0.15-0.19 to 0.04-0.05 deg.
    sfm_lights: int = 32
    sfm_trim: bool = True  # leave each pixel's brightest of those frames out (specular highlights)
    # ---- previews
    exposure: float = 0.0  # tonemap exposure for wellit/overlay PNGs; 0 = automatic, once per capture
    exposure_percentile: float = 99.0  # automatic exposure maps this foreground luminance percentile to 1

    @classmethod
    def from_dict(cls, data: Any, source: str | None = None) -> PreprocessConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and out-of-range values are a
        ConfigError naming `source` (the file, when there is one) and the key."""
        return load(cls, data, source)

    def __post_init__(self) -> None:
        """Out-of-range values are a ConfigError naming the key."""

        def bad(key: str, what: str) -> ConfigError:
            return ConfigError(f"{what}, got {getattr(self, key)!r}", key)

        try:
            qs = self.quantiles()
        except ValueError:
            qs = ()
        if not qs or not all(0 < q < 1 for q in qs):
            raise bad(
                "brightness_quantiles", "expected comma-separated fractions in (0, 1), and optionally mean"
            )
        if self.flare_policy not in ("mask", "drop"):
            raise bad("flare_policy", "expected mask or drop")
        if self.segmentation not in ("adaptive", "lit_fraction"):
            raise bad("segmentation", "expected adaptive or lit_fraction")
        if self.compression not in COMPRESSIONS:
            raise bad("compression", f"expected one of {', '.join(COMPRESSIONS)}")
        if self.decoder not in CHOICES:
            raise bad("decoder", f"expected one of {', '.join(CHOICES)}")
        if not self.read_timeout_s > 0:
            raise bad("read_timeout_s", "expected a number of seconds > 0")
        if self.band_rows < 4 or self.band_rows % 4:
            raise bad("band_rows", "expected a positive multiple of 4")
        for key in ("chunk_lights", "flare_thumb"):
            if getattr(self, key) < 1:
                raise bad(key, "expected an integer >= 1")
        if self.sfm_lights < 1:
            raise bad("sfm_lights", "expected an integer >= 1")
        for key in (
            "window",
            "sfm_max_side",
            "open_radius",
            "close_radius",
            "band_width",
            "flare_dilate",
            "colour_band",
        ):
            if getattr(self, key) < 0:
                raise bad(key, "expected an integer >= 0")
        for key in (
            "lit_ratio",
            "lit_floor",
            "centre_weight",
            "flare_threshold",
            "flare_margin",
            "broken_sigmas",
            "broken_min_stops",
            "exposure",
            "background_sigmas",
            "min_contrast_stops",
            "background_blur",
            "flag_group_ratio",
            "min_quantile_frames",
        ):
            if not getattr(self, key) >= 0:
                raise bad(key, "expected a number >= 0")
        for key in (
            "min_lit_fraction",
            "max_saturated_fraction",
            "min_component_fraction",
            "max_lost_fraction",
            "max_bad_fraction",
            "border_width",
            "contrast_fraction",
            "flag_border_fraction",
            "flag_min_fraction",
            "flag_max_fraction",
            "consistency_max_removed",
            "flare_veil",
        ):
            if not 0 <= getattr(self, key) <= 1:
                raise bad(key, "expected a fraction in [0, 1]")
        for name in self.accept_masks:
            g, _, c = str(name).partition("/")
            if not g or not c or "/" in c:
                raise ConfigError(
                    f"expected views as group/camera (e.g. 000/cam03), got {name!r}", "accept_masks"
                )
        if not 0 < self.exposure_percentile <= 100:
            raise bad("exposure_percentile", "expected a percentile in (0, 100]")

    def quantiles(self) -> tuple[float, ...]:
        """brightness_quantiles as numbers (without `mean`)."""
        return tuple(float(x) for x in self.brightness_quantiles.split(",") if x.strip() not in ("", "mean"))

    def mean_layer(self) -> bool:
        """brightness_quantiles lists `mean`: the mean luminance over the stack is a lit level too."""
        return "mean" in (x.strip() for x in self.brightness_quantiles.split(","))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def stats_key(self) -> str:
        """Hash of what the per-view statistics depend on (a rerun with another value recomputes them)."""
        keys = ("chunk_lights", "lit_ratio", "lit_floor", "flare_thumb")
        return _hash({**{k: getattr(self, k) for k in keys}, "format": STATS_FORMAT})

    def view_key(self) -> str:
        """Hash of everything the per-view outputs depend on."""
        keep = {k: v for k, v in self.to_dict().items() if k not in _NOT_IN_VIEW_KEY}
        return _hash({**keep, "format": STATS_FORMAT, "segment": SEGMENT_FORMAT})


# Settings that change how, not what, a view is computed (the decoders give identical frames).
# The consistency settings act after the views (the camera step has its own key: camera_task.camera_key).
_NOT_IN_VIEW_KEY = (
    "window",
    "band_rows",
    "compression",
    "decoder",
    "read_timeout_s",
    "max_bad_fraction",
    "consistency",
    "consistency_max_removed",
    "accept_masks",
    "broken_sigmas",  # the broken-frame test runs on every view's levels, in the report
    "broken_min_stops",
)

# Bumped when the statistics or segmentation change meaning, so stale view outputs are recomputed.
STATS_FORMAT = 3  # 2: frame thumbnails cover whole blocks only; 3: brightness ladder, frames / LED intensity, flare vs the upper quartile

# Bumped when a view's segmentation changes its result: 2: wide background blurs on a downsampled copy; 3: colour
# grows the mask until it adds nothing, the inclusive mask (stats.npz mask_inclusive) for the camera step.
# 4: saturated frames count as brighter than every level; no bound on a foreground pixel's saturated frames.
SEGMENT_FORMAT = 4


def _hash(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]
