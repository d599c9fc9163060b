"""The split stage: a protocol (dataset/protocols.py) resolved against the capture's stage into
`WORK/split.json` (lightstage.records.split), with overlap validation and preprocess rejections excluded and counted:
frames preprocess could not process, broken frames (a light misfired, a wrong exposure: preprocess/broken.py) and,
under flare_policy drop only, frames rejected for a flare. Frames with a bulb or flare in view stay in the split
under the default flare_policy mask; their flare and bulb pixels are flagged instead (docs/preprocess.md).

Light and camera indices are 0-based everywhere here; the paper's 1-based numbers pass through
`lightstage.lights.paper_number_to_index` only.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.capture.stage import Stage
from lightstage.config import load
from lightstage.dataset.protocols import (
    INLINE_PROTOCOL,
    PROTOCOLS,
    Protocol,
    builtin_protocol,
    protocol_from_dict,
    protocol_from_yaml,
    resolve,
)
from lightstage.errors import LightstageError
from lightstage.executor import Executor
from lightstage.ids import FrameId
from lightstage.records.split import parse_frame_id
from lightstage.workdir import WorkDir


# ---- the stage -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SplitConfig:
    """`lightstage split`: protocol name, YAML path or an inline protocol mapping (the YAML keys); optional stage
    preset (split without a capture)."""

    protocol: str | dict[str, Any] = "paper"
    stage_preset: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.protocol, dict):  # an inline protocol is checked here, naming its key
            protocol_from_dict(self.protocol, None, ("protocol",))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SplitConfig:
        """The strict loader (`lightstage.config`); an inline protocol's keys are checked too."""
        return load(cls, d)


def load_protocol(spec: str | dict[str, Any]) -> Protocol:
    """A built-in protocol name, a YAML file path, or an inline mapping with the YAML keys."""
    if isinstance(spec, dict):
        return protocol_from_dict(spec, INLINE_PROTOCOL)
    if spec in PROTOCOLS:
        return builtin_protocol(spec)
    if Path(spec).is_file():
        return protocol_from_yaml(spec)
    raise LightstageError(f"protocol {spec!r}: neither a built-in ({', '.join(PROTOCOLS)}) nor a YAML file")


def work_stage(work: WorkDir, preset: str | None = None) -> Stage:
    """The stage of a work directory: a named preset, or the capture's stage.yaml via WORK/capture.txt."""
    if preset:
        from lightstage.capture.presets import stage_preset

        return stage_preset(preset)
    from lightstage.capture.layout import open_capture

    return open_capture(work.capture_path()).stage


def rejected_frames(work: WorkDir) -> set[FrameId]:
    """Frames preprocess rejected (`rejected_frames`: broken frames, and flare frames under flare_policy drop) or
    could not process (`problems`), from WORK/reports/preprocess.json; empty when the report is absent."""
    path = work.report("preprocess")
    if not path.is_file():
        return set()
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise LightstageError(f"{path}: unreadable preprocess report ({e})") from None
    items: list[Any] = []
    if isinstance(d, dict):
        for key in ("rejected_frames", "rejected", "problems"):
            v = d.get(key)
            if isinstance(v, list):
                items += v
            elif isinstance(v, dict):  # {frame_id: reason}
                items += list(v)
    out = set()
    for it in items:
        text = it.get("frame") if isinstance(it, dict) else it
        out.add(parse_frame_id(text, f"{path}: rejected frames"))
    return out


def run_split(
    work: WorkDir, config: SplitConfig, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any]:
    """Resolve the protocol against the work directory's stage, write WORK/split.json and reports/split.json."""
    t0 = time.perf_counter()
    stage = work_stage(work, config.stage_preset)
    protocol = load_protocol(config.protocol)
    excluded = set() if config.stage_preset else rejected_frames(work)
    source = config.protocol if isinstance(config.protocol, str) else "split config: protocol"
    split = resolve(protocol, stage, excluded, source=source)
    split.save(work.split)
    counts = split.counts()
    summary = {
        "stage": "split",
        "protocol": split.protocol,
        "stage_name": stage.name,
        "stage_preset": config.stage_preset,
        "counts": counts,
        "rejected_in_report": len(excluded),
        "output": str(work.split),
        "seconds": round(time.perf_counter() - t0, 3),
        "warnings": [],
        "errors": [],
    }
    write_json_atomic(work.report("split"), summary)
    return summary
