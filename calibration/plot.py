"""layout.png: a picture of the calibrated stage (cameras, lights and turntable axis, coloured per group)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lightstage.atomic import atomic_path
from lightstage.cameras import camera_center
from lightstage.records.calibration import Calibration


def plot_layout(calib: Calibration, path: Path, title: str = "") -> Path:
    """Write a 3D view and a top view of cameras (with viewing directions), lights and the turntable axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted(calib.yaws_deg) or sorted({v.group for v in calib.views})
    cmap = plt.get_cmap("hsv")
    colours = {g: cmap(i / max(1, len(groups))) for i, g in enumerate(groups)}
    fig = plt.figure(figsize=(14, 7))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)
    for g in groups:
        views = [(v, c) for v, c in calib.views.items() if v.group == g]
        if views:
            C = np.stack([camera_center(c.R, c.t) for _, c in views])
            fwd = np.stack([c.R[2] for _, c in views])  # optical axis in world
            ax3.scatter(
                *C.T, color=colours[g], s=18, marker="s", label=f"{g} ({calib.yaws_deg.get(g, 0):.2f}°)"
            )
            ax3.quiver(*C.T, *(0.25 * fwd).T, color=colours[g], linewidth=0.6, arrow_length_ratio=0.1)
            ax2.scatter(C[:, 0], C[:, 1], color=colours[g], s=18, marker="s")
        if g in calib.light_positions:
            P = np.asarray(calib.light_positions[g])
            ax3.scatter(*P.T, color=colours[g], s=3, alpha=0.5)
            ax2.scatter(P[:, 0], P[:, 1], color=colours[g], s=3, alpha=0.4)
    d = np.asarray(calib.axis.direction, float)
    a = np.asarray(calib.axis.point, float)
    line = a[None] + np.linspace(-1.2, 1.8, 2)[:, None] * d[None]
    ax3.plot(*line.T, "k-", linewidth=2, label="turntable axis")
    ax3.scatter(*np.asarray(calib.scene_centre, float), color="k", s=30, marker="*")
    ax2.plot(line[:, 0], line[:, 1], "k-", linewidth=2)
    ax2.scatter([a[0]], [a[1]], color="k", marker="x")
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.set_box_aspect((1, 1, 1))
    ax3.legend(fontsize=7, loc="upper left", title="group (yaw)")
    ax2.set_aspect("equal")
    ax2.set_xlabel("x [m]")
    ax2.set_ylabel("y [m]")
    ax2.set_title("top view (squares: cameras, dots: lights, x: axis at its point)")
    fig.suptitle(
        title or f"calibration ({calib.method}): axis direction {np.round(d, 5)}, point {np.round(a, 4)} m"
    )
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path
