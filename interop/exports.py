"""`lightstage export WORK --format colmap|nerfstudio|olat --out DIR`: self-contained copies of a work
directory's data for other tools (images hard-linked where the file system allows)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.workdir import WorkDir

FORMATS = ("olat", "nerfstudio", "colmap")


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link `src` to `dst`, copying where links are not possible."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def export_colmap(work: WorkDir, out: Path) -> dict[str, Any]:
    """The calibrate stage's COLMAP model with its images and masks (calibration/colmap/), copied to OUT."""
    src = work.calibration_dir / "colmap"
    if not (src / "images.bin").is_file():
        raise LightstageError(f"{src}: no COLMAP model (run `lightstage calibrate` with this version)")
    files = [p for p in src.rglob("*") if p.is_file()]
    for p in files:
        _link_or_copy(p, Path(out) / p.relative_to(src))
    return {"format": "colmap", "out": str(out), "files": len(files)}


def export_nerfstudio(work: WorkDir, out: Path) -> dict[str, Any]:
    """OUT/transforms.json (calibration.export.transforms_dict: masks, applied_transform, the split's file
    lists) with the well-lit images and masks under OUT/images/<g>/<c>.png and OUT/masks/<g>/<c>.png."""
    from lightstage.calibration.export import transforms_dict
    from lightstage.records.calibration import Calibration

    out = Path(out)
    calib = Calibration.load(work.calibration)
    d = transforms_dict(calib, work, work.root)
    renamed: dict[str, str] = {}
    for f in d["frames"]:
        for key, folder in (("file_path", "images"), ("mask_path", "masks")):
            src = work.root / f[key]
            if not src.is_file():
                raise LightstageError(f"{src}: missing (run `lightstage preprocess`)")
            rel = f"{folder}/{f['group']}/{f['camera']}.png"
            _link_or_copy(src, out / rel)
            renamed[f[key]] = rel
            f[key] = rel
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        if key in d:
            d[key] = [renamed[n] for n in d[key]]
    if "ply_file_path" in d:
        _link_or_copy(work.root / d["ply_file_path"], out / "points3D.ply")
        d["ply_file_path"] = "points3D.ply"
    write_json_atomic(out / "transforms.json", d)
    return {
        "format": "nerfstudio",
        "out": str(out),
        "frames": len(d["frames"]),
        "split": "train_filenames" in d,
    }


def export_work(work: WorkDir, fmt: str, out: Path, progress: bool = False) -> dict[str, Any]:
    """Export WORK in `fmt` (one of FORMATS) to OUT."""
    if not work.root.is_dir():
        raise LightstageError(f"{work.root}: work directory not found")
    if Path(out).resolve() == work.root.resolve() or work.root.resolve() in Path(out).resolve().parents:
        raise LightstageError(f"--out {out}: must be outside the work directory")
    if fmt == "olat":
        from lightstage.interop.olat import export_olat

        return export_olat(work, Path(out), progress)
    if fmt == "nerfstudio":
        return export_nerfstudio(work, Path(out))
    if fmt == "colmap":
        return export_colmap(work, Path(out))
    raise LightstageError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
