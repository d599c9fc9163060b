"""The split record (`WORK/split.json`): train and test frames as data, written by the dataset stage's
split and read by shards, evaluation and exports. Light and camera indices are 0-based.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightstage.atomic import write_text_atomic
from lightstage.config import check_keys
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId

SPLIT_FORMAT_VERSION = 1


# ---- the split record ---------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameSet:
    """Frames as per-group camera and light lists (a cross product per group), minus explicit exclusions."""

    groups: dict[str, tuple[tuple[str, ...], tuple[int, ...]]]  # group -> (camera ids, light indices)
    excluded: frozenset[FrameId] = frozenset()

    def frames(self) -> Iterator[FrameId]:
        """Every frame of the set, group -> camera -> light order, exclusions skipped."""
        for g, (cams, lights) in self.groups.items():
            for c in cams:
                for lt in lights:
                    f = FrameId(g, c, lt)
                    if f not in self.excluded:
                        yield f

    def views(self) -> list[ViewId]:
        """Every (group, camera) of the set with at least one frame listed."""
        return [ViewId(g, c) for g, (cams, lights) in self.groups.items() if lights for c in cams]

    def nominal_count(self) -> int:
        return sum(len(c) * len(lt) for c, lt in self.groups.values())

    def count(self) -> int:
        return self.nominal_count() - len(self.excluded)

    def cameras(self) -> set[str]:
        return {c for cams, _ in self.groups.values() for c in cams}

    def lights(self) -> set[int]:
        return {lt for _, lights in self.groups.values() for lt in lights}

    def to_dict(self) -> dict[str, Any]:
        return {
            "groups": {
                g: {"cameras": list(c), "lights": [int(x) for x in lt]} for g, (c, lt) in self.groups.items()
            },
            "excluded": sorted(str(f) for f in self.excluded),
        }

    @classmethod
    def from_dict(cls, d: Any, where: str) -> FrameSet:
        if not isinstance(d, dict) or not isinstance(d.get("groups"), dict):
            raise LightstageError(f"{where}: expected a mapping with 'groups'")
        check_keys(d, ("groups", "excluded"), (), where)
        groups = {}
        for g, v in d["groups"].items():
            if (
                not isinstance(v, dict)
                or not isinstance(v.get("cameras"), list)
                or not isinstance(v.get("lights"), list)
            ):
                raise LightstageError(f"{where}.groups.{g}: expected {{cameras: [...], lights: [...]}}")
            check_keys(v, ("cameras", "lights"), ("groups", str(g)), where)
            groups[str(g)] = (tuple(str(c) for c in v["cameras"]), tuple(int(x) for x in v["lights"]))
        excluded = frozenset(parse_frame_id(s, f"{where}.excluded") for s in d.get("excluded", []))
        return cls(groups, excluded)


@dataclass(frozen=True)
class StageInfo:
    """What a split needs of a stage: names and counts (so a split file validates without the stage)."""

    name: str
    camera_ids: tuple[str, ...]
    num_lights: int
    groups: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "cameras": list(self.camera_ids),
            "num_lights": self.num_lights,
            "groups": list(self.groups),
        }


@dataclass(frozen=True)
class Split:
    """A resolved train/test split of one stage."""

    protocol: str
    parameters: dict[str, Any]
    rule: str
    stage: StageInfo
    train: FrameSet
    test: FrameSet
    source: str = "split"

    def counts(self) -> dict[str, int]:
        return {
            "train": self.train.count(),
            "test": self.test.count(),
            "train_excluded": len(self.train.excluded),
            "test_excluded": len(self.test.excluded),
            "train_views": len(self.train.views()),
            "test_views": len(self.test.views()),
            "train_cameras": len(self.train.cameras()),
            "test_cameras": len(self.test.cameras()),
            "train_lights": len(self.train.lights()),
            "test_lights": len(self.test.lights()),
        }

    def to_dict(self) -> dict[str, Any]:
        return {
            "format_version": SPLIT_FORMAT_VERSION,
            "protocol": {"name": self.protocol, "parameters": self.parameters, "rule": self.rule},
            "stage": self.stage.to_dict(),
            "counts": self.counts(),
            "train": self.train.to_dict(),
            "test": self.test.to_dict(),
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Indented JSON with every list of scalars on one line (compact, still diffable)."""
        text = json.dumps(self.to_dict(), indent=2)
        text = re.sub(
            r"\[\s*([^\[\]{}]*?)\s*\]", lambda m: "[" + re.sub(r",\s+", ", ", m.group(1)) + "]", text
        )
        write_text_atomic(path, text + "\n")


def load_split(path: str | os.PathLike[str]) -> Split:
    """Read and validate a split.json."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except OSError as e:
        raise LightstageError(f"{path}: cannot read split ({e.strerror}); run `lightstage split`") from None
    except json.JSONDecodeError as e:
        raise LightstageError(f"{path}: invalid JSON ({e})") from None
    if not isinstance(d, dict) or d.get("format_version") != SPLIT_FORMAT_VERSION:
        raise LightstageError(
            f"{path}: unsupported split format {d.get('format_version') if isinstance(d, dict) else d!r}"
        )
    try:
        st = d["stage"]
        stage = StageInfo(str(st["name"]), tuple(st["cameras"]), int(st["num_lights"]), tuple(st["groups"]))
        p = d["protocol"]
        split = Split(
            str(p["name"]),
            dict(p.get("parameters", {})),
            str(p.get("rule", "")),
            stage,
            FrameSet.from_dict(d["train"], f"{path}: train"),
            FrameSet.from_dict(d["test"], f"{path}: test"),
            str(path),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise LightstageError(f"{path}: malformed split ({type(e).__name__}: {e})") from None
    validate_split(split)
    return split


def parse_frame_id(text: Any, where: str) -> FrameId:
    """'g/c/lll' -> FrameId."""
    parts = str(text).split("/")
    if len(parts) != 3 or not parts[2].isdigit():
        raise LightstageError(f"{where}: {text!r} is not a frame id 'group/camera/light'")
    return FrameId(parts[0], parts[1], int(parts[2]))


def validate_split(split: Split) -> None:
    """Raise LightstageError if test lights or cameras appear in training, or anything is not on the stage."""
    where = split.source
    st = split.stage
    for name, fs in (("train", split.train), ("test", split.test)):
        for g, (cams, lights) in fs.groups.items():
            if g not in st.groups:
                raise LightstageError(
                    f"{where}: {name}: group {g!r} is not on stage {st.name!r} ({len(st.groups)} groups)"
                )
            bad_c = [c for c in cams if c not in st.camera_ids]
            if bad_c:
                raise LightstageError(
                    f"{where}: {name}: camera(s) {', '.join(bad_c)} not on stage {st.name!r} "
                    f"({len(st.camera_ids)} cameras: {st.camera_ids[0]}..{st.camera_ids[-1]})"
                )
            bad_l = [lt for lt in lights if not 0 <= lt < st.num_lights]
            if bad_l:
                raise LightstageError(
                    f"{where}: {name}: light(s) {bad_l[:5]} not on stage {st.name!r} "
                    f"(0-based indices 0..{st.num_lights - 1})"
                )
            if len(set(cams)) != len(cams) or len(set(lights)) != len(lights):
                raise LightstageError(f"{where}: {name}: group {g}: duplicate cameras or lights")
        if fs.count() <= 0:
            raise LightstageError(f"{where}: the {name} set is empty")
    overlap_l = split.train.lights() & split.test.lights()
    if overlap_l:
        raise LightstageError(
            f"{where}: test light(s) {sorted(overlap_l)[:10]} (0-based) also appear in training; "
            "test lights must be unseen"
        )
    overlap_c = split.train.cameras() & split.test.cameras()
    if overlap_c:
        raise LightstageError(
            f"{where}: test camera(s) {', '.join(sorted(overlap_c))} also appear in training; test views must be unseen"
        )
