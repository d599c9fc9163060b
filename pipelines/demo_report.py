"""The demo's report: WORK/report.md with the PNGs a person looks at (segmentation masks, camera layout, test
predictions beside the masked ground truth with per-image PSNR, the test-PSNR curve against the ceiling, the
envmap-relit image) and the metric tables, from the records the stages wrote."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_text_atomic
from lightstage.pipelines.records import report_path
from lightstage.workdir import WorkDir

MAX_VIEWS_SHOWN = 6
MAX_PREDICTIONS_SHOWN = 4


def _viewer_lines(work: WorkDir, manifest: dict[str, Any] | None) -> list[str]:
    """The report's section on the viewer: how to open it and what it holds."""
    lines = ["", "## Interactive relighting viewer", ""]
    if not manifest:
        return lines + ["(no viewer was built)"]
    build = manifest.get("build", {})
    lines += [
        f"Open it with `lightstage view {work.root}` (serves `{work.root / 'viewer'}` on "
        "http://127.0.0.1:8023/; `--port N` for another port), or put the folder on any web server "
        f"(`python -m http.server -d {work.root / 'viewer'}`): a browser cannot load it from `file://`. Drag the "
        "light on the map, turn the environment map, change the exposure; A/B compares with the captured frame.",
        "",
        "| source | views | basis lights | components per view | basis error |",
        "|---|---|---|---|---|",
    ]
    for s in manifest.get("sets", []):
        views = s.get("views", [])
        ks = [v["components"] for v in views] or [0]
        errs = [v["relative_error"] for v in views] or [0.0]
        lines.append(
            f"| {s.get('description', s.get('source'))} | {len(views)} | {s.get('basis_lights')} | "
            f"{min(ks)}-{max(ks)} | <= {100 * max(errs):.2f} % |"
        )
    lines += [
        "",
        f"Bundle: {build.get('bytes', 0) / 1e6:.1f} MB, built in {build.get('wall_seconds', 0):.0f} s "
        f"({build.get('cpu_seconds', 0):.0f} CPU-s). Docs: docs/viewer.md.",
    ]
    return lines


# ---- the report ------------------------------------------------------------------------------------------
def _read_png(path: Path) -> np.ndarray | None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.dtype != np.uint8:
        img = (img.astype(np.float64) / np.iinfo(img.dtype).max * 255).astype(np.uint8)
    return cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)


def montage(images: list[np.ndarray], columns: int = 3, height: int = 200) -> np.ndarray:
    """Tile images (resized to one height) into a grid with a thin white gap."""
    import cv2

    tiles = [cv2.resize(im, (max(1, round(im.shape[1] * height / im.shape[0])), height)) for im in images]
    width = max(t.shape[1] for t in tiles)
    tiles = [np.pad(t, ((2, 2), (2, 2 + width - t.shape[1]), (0, 0)), constant_values=255) for t in tiles]
    rows = [np.concatenate(tiles[i : i + columns], axis=1) for i in range(0, len(tiles), columns)]
    row_w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, row_w - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows, axis=0)


def _views_with(work: WorkDir, names: tuple[str, ...]) -> list[Path]:
    root = work.preprocess_dir / "views"
    found: list[Path] = []
    for view in sorted(p for p in root.glob("*/*") if p.is_dir()):
        for name in names:
            if (view / name).is_file():
                found.append(view / name)
                break
    step = max(1, len(found) // MAX_VIEWS_SHOWN)
    return found[::step][:MAX_VIEWS_SHOWN]


def _load_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _metrics_table(ev: dict[str, Any]) -> list[str]:
    lines = ["| metric | value |", "|---|---|"]
    found = False
    for section in ("mean", "metrics", "summary"):
        block = ev.get(section)
        if isinstance(block, dict):
            for k, v in block.items():
                if isinstance(v, int | float | str) and not isinstance(v, bool):
                    lines.append(
                        f"| {section}.{k} | {v:.4g} |" if isinstance(v, float) else f"| {section}.{k} | {v} |"
                    )
                    found = True
    for k, v in ev.items():
        if (
            isinstance(v, float | int)
            and not isinstance(v, bool)
            and ("psnr" in k or "ssim" in k or "lpips" in k)
        ):
            lines.append(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |")
            found = True
        if isinstance(v, dict) and ("baseline" in k or "lpips" in k):
            for kk, vv in v.items():
                if isinstance(vv, int | float | str) and not isinstance(vv, bool):
                    lines.append(
                        f"| {k}.{kk} | {vv:.4g} |" if isinstance(vv, float) else f"| {k}.{kk} | {vv} |"
                    )
                    found = True
    return lines if found else ["(no metrics found in reports/eval.json)"]


# The rows of the metrics table: key suffix -> how the figures are scored (training/metrics.py CONVENTIONS).
SCORINGS = (
    ("", "masked, our tonemap"),
    ("_full", "full frame, our tonemap"),
    ("_paper", "masked, paper code's sRGB(log(1 + hdr))"),
)


def _fmt(v: Any, digits: int) -> str:
    return f"{v:.{digits}f}" if isinstance(v, int | float) and not isinstance(v, bool) else "n/a"


def _flare_rows(ev: dict[str, Any]) -> list[str]:
    """Table rows beside the scorings: the masked figures without the frames' flare and bulb pixels, and over the
    back-lit test images alone (training/flagged.py); none when eval.json predates them."""
    mean, back = ev.get("mean", {}), ev.get("backlit")
    model = [("psnr", 2), ("ssim", 4), ("lpips", 4), ("lpips_alex", 4)]
    rows = []
    if "psnr_unflagged" in mean:
        cells = [_fmt(mean.get("psnr_unflagged"), 2), _fmt(mean.get("ssim_unflagged"), 4)] + ["n/a"] * 7
        rows.append("| masked, without flare and bulb pixels | " + " | ".join(cells) + " |")
    if isinstance(back, dict) and back.get("count"):
        b = back.get("mean", {})
        cells = [_fmt(b.get(k), d) for k, d in model] + [_fmt(b.get(f"ceiling_{k}"), d) for k, d in model]
        cells.append(_fmt(b.get("baseline_psnr"), 2))
        rows.append(f"| masked, back-lit test images only ({back['count']}) | " + " | ".join(cells) + " |")
    return rows


def _eval_table(ev: dict[str, Any]) -> list[str]:
    """Model, ceiling and baseline per scoring convention (eval.json with `conventions`), with the notes."""
    mean = ev.get("mean", {})
    lines = [
        "| scoring | PSNR (dB) | SSIM | LPIPS VGG | LPIPS Alex | ceiling PSNR | ceiling SSIM | ceiling LPIPS VGG "
        "| ceiling LPIPS Alex | baseline PSNR |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for suffix, what in SCORINGS:
        model = [("psnr", 2), ("ssim", 4), ("lpips", 4), ("lpips_alex", 4)]
        cells = [_fmt(mean.get(k + suffix), d) for k, d in model]
        cells += [_fmt(mean.get(f"ceiling_{k}{suffix}"), d) for k, d in model]
        cells.append(_fmt(mean.get("baseline_psnr" + suffix), 2))
        lines.append(f"| {what} | " + " | ".join(cells) + " |")
    lines += _flare_rows(ev)
    lines += [
        "",
        f"Means over {ev.get('count', '?')} test images ({ev.get('masked_count', '?')} with a foreground mask; "
        "outside it the target is 0, as in training and the paper's code). The ceiling is what a perfect "
        f"prediction scores on the same images ({ev.get('ceiling_count', 0)} of them): {ev.get('ceiling', 'n/a')}. "
        f"LPIPS: {ev.get('lpips_note', 'n/a')}. SSIM: {ev.get('ssim', 'n/a')}. The baseline "
        "predicts the mean training colour everywhere. Definitions: docs/model.md (Evaluation).",
    ]
    return lines


def _paper_protocol_table(ev: dict[str, Any]) -> list[str]:
    """eval.json's `paper_protocol`: the paper's Table 1/2 rows (its code's convention), ceiling beside."""
    pp = ev.get("paper_protocol")
    if not isinstance(pp, dict) or not pp.get("rows"):
        return ["(no paper-protocol table in reports/eval.json)"]
    lines = ["| metric | this capture | ceiling |", "|---|---|---|"]
    for row in pp["rows"]:
        digits = 3 if "LPIPS" in row["metric"] else 1
        lines.append(f"| {row['metric']} | {_fmt(row['ours'], digits)} | {_fmt(row['ceiling'], digits)} |")
    lines += [
        "",
        f"Means over the {pp.get('images', '?')} images of the {pp.get('split', 'test')} split, scored as the "
        f"paper's code does: {pp.get('convention', 'n/a')}. Rows and precision as the paper's Tables 1 and 2 "
        "(SSIM x 100; LPIPS VGG is what its code reports). The ceiling is a perfect prediction's score.",
    ]
    return lines


PANEL_HEIGHT = 160
COLUMNS = ("prediction", "ground truth (masked)", "error (|difference| x 4)")


def _text_strip(width: int, texts: list[tuple[int, str]], height: int = 22) -> np.ndarray:
    """A white (height, width, 3) strip with black text at the given x offsets (cv2.putText)."""
    import cv2

    strip = np.full((height, width, 3), 255, np.uint8)
    for x, text in texts:
        cv2.putText(
            strip, text, (x + 4, height - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA
        )
    return strip


def prediction_grid(rows: list[tuple[np.ndarray, str]]) -> np.ndarray:
    """Labelled grid of evaluation PNGs (each prediction | masked target | error side by side): a header with
    the column names, then per row a caption line (name, masked PSNR) above the panels."""
    import cv2

    tiles = []
    for img, caption in rows:
        h, w = img.shape[:2]
        scale = PANEL_HEIGHT / h
        interp = cv2.INTER_NEAREST if scale > 1 else cv2.INTER_AREA  # enlarged pixels stay pixels
        tiles.append(
            (cv2.resize(img, (max(1, round(w * scale)), PANEL_HEIGHT), interpolation=interp), caption)
        )
    width = max(t.shape[1] for t, _ in tiles)
    out = [_text_strip(width, [(k * tiles[0][0].shape[1] // 3, c) for k, c in enumerate(COLUMNS)], 26)]
    for tile, caption in tiles:
        tile = np.pad(tile, ((0, 0), (0, width - tile.shape[1]), (0, 0)), constant_values=255)
        out += [_text_strip(width, [(0, caption)]), tile, np.full((4, width, 3), 255, np.uint8)]
    return np.concatenate(out, axis=0)


def _prediction_rows(work: WorkDir, ev: dict[str, Any]) -> list[tuple[Path, str]]:
    """(eval PNG, caption) of the first test images, with their masked and ceiling PSNR from eval.json."""
    rows = []
    for r in ev.get("images", [])[:MAX_PREDICTIONS_SHOWN]:
        png = work.eval_dir / f"{r.get('name')}.png"
        if png.is_file():
            cap = f"{r['name']}: masked PSNR {_fmt(r.get('psnr'), 2)} dB"
            if isinstance(r.get("ceiling_psnr"), int | float):
                cap += f" (ceiling {r['ceiling_psnr']:.2f})"
            rows.append((png, cap + f", full frame {_fmt(r.get('psnr_full'), 2)} dB"))
    if not rows:  # an eval.json without per-image rows: the PNGs alone
        rows = [(p, p.stem) for p in sorted(work.eval_dir.rglob("*.png"))[:MAX_PREDICTIONS_SHOWN]]
    return rows


def psnr_curve(work: WorkDir, ev: dict[str, Any], path: Path) -> bool:
    """report/psnr_curve.png: the periodic masked test PSNR logged during training (train/log.json) against
    the step, the ceiling on the same images as a horizontal line, the final evaluation as a point."""
    evals = _load_json(work.train_dir / "log.json").get("eval", [])
    evals = [e for e in evals if isinstance(e, dict) and isinstance(e.get("psnr"), int | float)]
    if not evals:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lightstage.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    steps = [int(e["step"]) for e in evals]
    n = len(evals[-1].get("images", [])) or None
    ax.plot(
        steps, [e["psnr"] for e in evals], "o-", label=f"masked test PSNR ({n or '?'} image(s), periodic)"
    )
    if all(isinstance(e.get("psnr_full"), int | float) for e in evals):
        ax.plot(steps, [e["psnr_full"] for e in evals], "--", color="grey", label="same, full frame")
    rows = {r.get("name"): r for r in ev.get("images", [])}
    names = evals[-1].get("images") or list(rows)  # logs from before the names were kept: every test image
    ceil = [rows[k].get("ceiling_psnr") for k in names if k in rows]
    if ceil and all(isinstance(c, int | float) for c in ceil) and len(ceil) == len(names):
        same = "same images" if evals[-1].get("images") else "all test images"
        ax.axhline(float(np.mean(ceil)), color="tab:red", label=f"ceiling: perfect prediction, {same}")
    else:
        ax.text(0.02, 0.95, f"ceiling: {ev.get('ceiling', 'unavailable')}"[:90], transform=ax.transAxes,
                fontsize=7, va="top")  # fmt: skip
    final = ev.get("mean", {}).get("psnr")
    if isinstance(final, int | float) and ev.get("checkpoint_step") is not None:
        ax.plot([ev["checkpoint_step"]], [final], "s", color="black",
                label=f"final evaluation, all {ev.get('count', '?')} test images")  # fmt: skip
    ax.set_xlabel("training step")
    ax.set_ylabel("masked test PSNR (dB), our tonemap")
    ax.set_title("Test PSNR over training")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return True


def _calibration_table(cal: dict[str, Any]) -> list[str]:
    """Calibration errors against the simulator's ground truth, and what observed the lights."""
    gt, sfm = cal.get("ground_truth"), cal.get("sfm", {})
    if not isinstance(gt, dict) or "raw" not in gt:
        return []
    raw = gt["raw"]
    rows = [
        ("camera rotation (deg)", raw.get("rotation_error_deg", {})),
        ("camera centre (mm)", raw.get("camera_centre_error_mm", {})),
        ("light position (mm)", raw.get("light_position_error_mm", {})),
        ("group yaw (deg)", {k: abs(v) for k, v in gt.get("yaw_error_deg", {}).items() if k != "per_group"}),
        # what the pose errors do to the model's pixels (per-view mean over the true object box, aligned)
        (
            "object reprojection shift (processed px)",
            gt.get("aligned", {}).get("object_reprojection_shift_px", {}),
        ),
    ]
    lines = [
        "",
        "Calibration against the simulator's ground truth:",
        "",
        "| error | mean | max |",
        "|---|---|---|",
    ]
    for name, block in rows:
        if isinstance(block, dict) and "mean" in block and "max" in block:
            lines.append(f"| {name} | {block['mean']:.3g} | {block['max']:.3g} |")
    lights = sfm.get("lights", {})
    if lights:
        lines += [
            "",
            f"Lights observed: {lights.get('num_observed', 0)} of {lights.get('num_lights', '?')} "
            f"({lights.get('num_seen_as_bulbs', 0)} as bulbs in view, {lights.get('num_seen_in_probe', 0)} in the "
            "mirror-ball probe)"
            + (
                "; the others keep their nominal rig positions."
                if lights.get("num_observed", 0) < lights.get("num_lights", 0)
                else "."
            ),
        ]
    return lines


def write_report(
    work: WorkDir,
    timings: dict[str, float],
    relit: dict[str, Any],
    seconds: float,
    preset: str,
    viewer: dict[str, Any] | None = None,
) -> Path:
    """WORK/report.md plus PNGs in WORK/report/: masks, camera layout, predictions vs truth, relit image."""
    from lightstage.frames import write_image

    pics = work.root / "report"
    pics.mkdir(parents=True, exist_ok=True)
    lines = [
        "# lightstage demo report",
        "",
        f"Simulated capture `{preset}` in `{work.root / 'capture'}`, processed in `{work.root}`. "
        f"This run of the demo took {seconds / 60:.1f} minutes (stages that were up to date were skipped; "
        "the record column has the time each stage took when it ran). Per-stage records: `reports/<stage>.json`.",
        "",
        "## Stages",
        "",
        "| stage | seconds this run | record |",
        "|---|---|---|",
    ]
    for stage in ("validate", "preprocess", "calibrate", "split", "shard", "train", "eval"):
        rec = _load_json(report_path(work, stage)).get("pipeline", {})
        took = timings.get(stage, 0.0)
        status = rec.get("status", "?")
        errs = rec.get("errors", 0)
        lines.append(f"| {stage} | {took:.1f} | {status}, {rec.get('seconds', 0):.1f} s, {errs} error(s) |")

    masks = [_read_png(p) for p in _views_with(work, ("overlay.png", "mask.png"))]
    masks = [m for m in masks if m is not None]
    lines += ["", "## Segmentation masks", ""]
    if masks:
        write_image(pics / "masks.png", montage(masks))
        lines.append("![masks](report/masks.png)")
    else:
        lines.append("(no per-view mask images found under preprocess/views)")

    layout = work.calibration_dir / "layout.png"
    lines += ["", "## Camera layout", ""]
    if layout.is_file():
        shutil.copyfile(layout, pics / "layout.png")
        lines.append("![camera layout](report/layout.png)")
    else:
        lines.append("(calibration wrote no layout.png)")
    lines += _calibration_table(_load_json(work.report("calibration")))

    ev = _load_json(work.report("eval"))
    preds = [(p, cap, _read_png(p)) for p, cap in _prediction_rows(work, ev)]
    preds = [(p, cap, t) for p, cap, t in preds if t is not None]
    lines += ["", "## Test predictions (prediction | ground truth (masked) | error)", ""]
    if preds:
        write_image(pics / "predictions.png", prediction_grid([(t, cap) for _, cap, t in preds]))
        lines.append("![predictions](report/predictions.png)")
        lines += [f"- `{p.relative_to(work.root)}`: {cap}" for p, cap, _ in preds]
    else:
        lines.append("(eval wrote no PNGs)")

    lines += ["", "## Test PSNR over training", ""]
    if psnr_curve(work, ev, pics / "psnr_curve.png"):
        lines.append("![test PSNR over training](report/psnr_curve.png)")
    else:
        lines.append("(training logged no periodic evaluation: train/log.json has no `eval` entries)")

    lines += ["", "## Metrics (test split)", ""]
    lines += _eval_table(ev) if "conventions" in ev else _metrics_table(ev)
    lines += ["", "## Paper protocol (test split, the paper code's convention)", ""]
    lines += _paper_protocol_table(ev)

    lines += ["", "## Environment-map relighting", ""]
    relit_pngs = sorted((work.root / "relight").glob("*.png"))
    if relit_pngs:
        for p in relit_pngs[:3]:
            shutil.copyfile(p, pics / f"relit_{p.name}")
            lines.append(f"![{p.stem}](report/relit_{p.name})")
        lines.append("")
        lines.append(
            f"Envmap: `{relit.get('envmap')}`, {_relit_lights(relit)} median-cut lights; "
            f"tonemap: {relit.get('tonemap', '')}."
        )
    else:
        lines.append("(no relit image)")
    lines += _viewer_lines(work, viewer)
    path = work.root / "report.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def _relit_lights(relit: dict[str, Any]) -> str:
    """The median-cut light counts the relight summary holds (e.g. "16"), or "?" when it names none."""
    counts = {int(k) for view in relit.get("views", {}).values() for k in view.get("results", {})}
    return ", ".join(str(c) for c in sorted(counts)) or "?"
