"""The Python side of the page: the image the viewer shows for given settings, from the bundle's compressed
basis (what the page draws) or from uncompressed basis images, with the weights of
lightstage.training.light_basis (the same definition the bundle's tables were made with)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.errors import LightstageError
from lightstage.training.light_basis import LightBasis, envmap_weights
from lightstage.viewer.compress import CompressedBasis
from lightstage.viewer.sets import DEFAULT_AZIMUTH_DEG, DEFAULT_ELEVATION_DEG, _compressed, azel_direction

MODES = ("point", "envmap", "both")


@dataclass(frozen=True)
class Settings:
    """The page's controls: set and view indices, light mode, point light (azimuth / elevation in degrees,
    intensity in capture lights), envmap (name, rotation in whole degrees, intensity), exposure (absolute, or
    None for the page's default for the mode times 2^exposure_stops)."""

    set: int = 0
    view: int = 0
    mode: str = "point"
    azimuth_deg: float = DEFAULT_AZIMUTH_DEG
    elevation_deg: float = DEFAULT_ELEVATION_DEG
    intensity: float = 1.0
    envmap: str = "sky"
    rotate_deg: int = 0
    envmap_intensity: float = 1.0
    exposure: float | None = None
    exposure_stops: float = 0.0


class Bundle:
    """A built viewer folder: its manifest and, on demand, each view's compressed basis and light basis."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        try:
            self.manifest: dict[str, Any] = json.loads((self.root / "manifest.json").read_text())
        except (OSError, ValueError) as e:
            raise LightstageError(f"{self.root / 'manifest.json'}: not a viewer bundle ({e})") from None

    def view(self, s: int, v: int) -> dict[str, Any]:
        return self.manifest["sets"][s]["views"][v]

    def compressed(self, s: int, v: int) -> CompressedBasis:
        return _compressed(self.root, self.view(s, v))

    def basis(self, s: int, v: int) -> LightBasis:
        """The view's light basis, triangulated again from its directions (as the build did)."""
        entry = self.manifest["sets"][s]["bases"][self.view(s, v)["basis"]]
        return LightBasis.of(np.asarray(entry["directions"], np.float64))

    @cached_property
    def envmaps(self) -> dict[str, Any]:
        return {e["name"]: e for e in self.manifest["envmaps"]}

    def radiance(self, name: str) -> np.ndarray:
        e = self.envmaps[name]
        return np.fromfile(self.root / e["radiance"], dtype="<f4").reshape(e["height"], e["width"], 3)


def settings_weights(bundle: Bundle, s: Settings) -> np.ndarray:
    """(L, 3) basis-light weights for the settings (point light and/or envmap)."""
    from lightstage.training.envmap import EnvMap

    if s.mode not in MODES:
        raise LightstageError(f"mode must be one of {', '.join(MODES)}, got {s.mode!r}")
    basis = bundle.basis(s.set, s.view)
    w = np.zeros((len(basis), 3))
    if s.mode in ("point", "both"):
        w += basis.point_weights(azel_direction(s.azimuth_deg, s.elevation_deg), s.intensity)
    if s.mode in ("envmap", "both"):
        env = EnvMap(bundle.radiance(s.envmap).astype(np.float64), float(s.rotate_deg))
        w += s.envmap_intensity * envmap_weights(env, basis, bundle.manifest["olat_factor"])
    return w


def settings_exposure(bundle: Bundle, s: Settings) -> float:
    """The exposure the page uses: the absolute one, or the mode's default times 2^stops."""
    if s.exposure is not None:
        return float(s.exposure)
    base = bundle.manifest["sets"][s.set]["exposure"]
    if s.mode != "point":
        base = bundle.envmaps[s.envmap]["exposure"][bundle.manifest["sets"][s.set]["name"]]
    return float(base * 2.0**s.exposure_stops)


def reference_image(
    bundle: Bundle, s: Settings, basis_images: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """(linear HDR image (H, W, 3) float32, exposure) for the settings: from `basis_images` (L, H, W, 3) when
    given (e.g. the captured frames themselves), else from the bundle's compressed basis."""
    from lightstage.training.light_basis import relight_basis

    w = settings_weights(bundle, s)
    if basis_images is not None:
        img = relight_basis(basis_images, w)
    else:
        img = bundle.compressed(s.set, s.view).reconstruct(w)
    return img, settings_exposure(bundle, s)
