"""A trained model for inference, the interface relighting, novel views, meshes and notebooks use:
`load_trained(work)` -> `TrainedModel` (the `RelightableModel` protocol), and `render_image` of a camera."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from lightstage.cameras import PinholeCamera, camera_rays
from lightstage.training.checkpoint import CHECKPOINT_NAME, load_checkpoint
from lightstage.training.config import TrainConfig, without_retired
from lightstage.training.model import RelightModel
from lightstage.workdir import WorkDir


@runtime_checkable
class RelightableModel(Protocol):
    """What relighting, rendering and meshing need of a trained model (lightstage.training.model)."""

    centre: Any  # scene-bounds centre (3,) or scalar: x_norm = (x - centre) / scale in [-1, 1]^3
    scale: Any  # scene-bounds half-extent, scalar or (3,)

    def render_rays(self, origins, directions, light_directions, chunk: int = ...) -> Any:
        """(N, 3) world rays and per-ray unit light directions -> (N, 3) linear HDR."""
        ...

    def density(self, points_world) -> Any:
        """(N, 3) world points -> (N,) volume density."""
        ...

    def image_from_camera(self, camera, light_direction) -> np.ndarray:
        """(H, W, 3) linear HDR image of a PinholeCamera under a white OLAT light from `light_direction`."""
        ...


@torch.no_grad()
def render_image(
    model: RelightModel, camera: PinholeCamera, light_direction: np.ndarray, chunk: int = 8192
) -> np.ndarray:
    """(H, W, 3) float32 HDR image rendered in chunks of rays (deterministic samples)."""
    device = model.centre.device
    o, d = camera_rays(camera)
    o_t = torch.from_numpy(o.astype(np.float32)).to(device)
    d_t = torch.from_numpy(d.astype(np.float32)).to(device)
    light = torch.as_tensor(np.asarray(light_direction, np.float32), device=device).reshape(1, 3)
    out = []
    for i in range(0, len(o_t), chunk):
        n = len(o_t[i : i + chunk])
        out.append(
            model(o_t[i : i + chunk], d_t[i : i + chunk], light.expand(n, 3), randomized=False)["rgb"].float()
        )
    return torch.cat(out).cpu().numpy().reshape(camera.height, camera.width, 3)


class TrainedModel:
    """A trained RelightModel in eval mode on one device, with world-coordinate queries that never build graphs."""

    def __init__(
        self,
        model: RelightModel,
        config: TrainConfig,
        exposure: float = 1.0,
        baseline_rgb: list[float] | None = None,
        step: int = 0,
    ):
        self.model = model.eval()
        self.config = config
        self.exposure = exposure
        self.baseline_rgb = baseline_rgb or [0.0, 0.0, 0.0]
        self.step = step

    @property
    def device(self) -> torch.device:
        return self.model.centre.device

    @property
    def centre(self) -> np.ndarray:
        """Bounds centre (world metres)."""
        return self.model.centre.cpu().numpy().astype(np.float64)

    @property
    def scale(self) -> float:
        """Bounds scale: x_norm = (x - centre) / scale."""
        return float(self.model.scale)

    @torch.no_grad()
    def render_rays(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        light_directions: torch.Tensor,
        chunk: int = 8192,
    ) -> torch.Tensor:
        """(N, 3) linear HDR pixels for world rays under unit light directions (rendered in chunks)."""
        out = []
        for i in range(0, origins.shape[0], chunk):
            sl = slice(i, i + chunk)
            res = self.model(
                origins[sl].to(self.device),
                directions[sl].to(self.device),
                light_directions[sl].to(self.device),
                randomized=False,
            )
            out.append(res["rgb"].float())
        return torch.cat(out) if out else torch.zeros(0, 3, device=self.device)

    @torch.no_grad()
    def density(self, points_world: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """(N,) fine-network density at world points (0 outside the scene bounds)."""
        parts = [
            self.model.density(points_world[i : i + chunk].to(self.device))
            for i in range(0, len(points_world), chunk)
        ]
        return torch.cat(parts) if parts else torch.zeros(0, device=self.device)

    def image_from_camera(
        self, camera: PinholeCamera, light_direction: np.ndarray, chunk: int = 8192
    ) -> np.ndarray:
        """(H, W, 3) float32 linear HDR image seen by `camera` under the unit `light_direction`."""
        return render_image(self.model, camera, light_direction, chunk)


def load_trained(
    work: WorkDir | str | os.PathLike[str],
    checkpoint: str | os.PathLike[str] | None = None,
    device: str | torch.device = "cpu",
) -> TrainedModel:
    """Load WORK/train/checkpoint.pt (or `checkpoint`) onto `device`; `work` a WorkDir or a plain path."""
    work = work if isinstance(work, WorkDir) else WorkDir.at(work)
    path = Path(checkpoint) if checkpoint is not None else work.train_dir / CHECKPOINT_NAME
    ck = load_checkpoint(path, map_location=device)
    config = TrainConfig.from_dict(without_retired(ck["config"]))
    state = ck["model"]
    model = RelightModel(config.model, state["centre"].cpu(), float(state["scale"]))
    state.setdefault("box", model.box.clone())  # checkpoints from before the scene box sampled the unit cube
    model.load_state_dict(state)
    stats = ck.get("stats", {})
    return TrainedModel(
        model.to(device),
        config,
        float(stats.get("exposure", 1.0)),
        stats.get("baseline_rgb"),
        int(ck.get("step", 0)),
    )
