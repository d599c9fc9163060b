"""Split protocols (paper, synthetic, custom YAML) and their resolution against a stage into a Split.

Light and camera indices are 0-based everywhere here; the paper's 1-based numbers pass through
`lightstage.lights.paper_number_to_index` only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.capture.stage import Stage
from lightstage.config import ConfigError, check_keys, read_yaml
from lightstage.errors import LightstageError
from lightstage.ids import FrameId
from lightstage.lights import paper_number_to_index
from lightstage.records.split import FrameSet, Split, StageInfo, validate_split

# The paper (§5, real data): 331 lights, 75 train lights = linspace(1, 331, 75) truncated, 10 test lights.
PAPER_NUM_LIGHTS = 331
PAPER_NUM_CAMERAS = 20
PAPER_NUM_TRAIN_LIGHTS = 75
PAPER_TEST_LIGHT_NUMBERS = (43, 73, 105, 137, 169, 203, 233, 265, 297, 329)  # 1-based, as printed
PAPER_TEST_CAMERA_FRACTION = 2 / 20  # cameras 19-20 of 20
# The paper (§5, synthetic): rows 2..8 (1-based) of a 16x32 lat-long grid, every other direction held out.
ENVMAP_ROWS, ENVMAP_COLS = 16, 32
SYNTHETIC_ROWS = tuple(range(2, 9))  # 1-based rows, upper hemisphere
SYNTHETIC_TEST_LIGHTS = 10
SYNTHETIC_TEST_VIEWS = 10

PROTOCOLS = ("paper", "synthetic")


# ---- protocols ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Protocol:
    """What a protocol asks for; `resolve` turns it into a Split of a particular stage.

    Cameras/lights: an int (a count, placed by the documented rule), a list (explicit: 0-based indices, or camera
    ids), or 'rest' (train only: everything the test set does not use). `light_rule`: 'paper' places counts
    like the paper's lights; 'hemisphere' maps the synthetic 7x32 upper-hemisphere grid onto the stage's lights.
    """

    name: str
    train_cameras: Any = "rest"
    test_cameras: Any = None  # None: the paper's share (10%, >= 1)
    train_lights: Any = None  # None: the paper's share (75/331, >= 1)
    test_lights: Any = None  # None: the paper's share (10/331, >= 1)
    train_groups: Any = "all"
    test_groups: Any = "all"
    test_views: int | None = None  # keep only this many test views (evenly spread), None: all
    light_rule: str = "paper"
    parameters: dict[str, Any] = field(default_factory=dict)


def builtin_protocol(name: str) -> Protocol:
    """The paper's real-data protocol or its synthetic (hemisphere) protocol."""
    if name == "paper":
        return Protocol("paper")
    if name == "synthetic":
        return Protocol("synthetic", light_rule="hemisphere", test_views=SYNTHETIC_TEST_VIEWS)
    raise LightstageError(f"unknown protocol {name!r} (built in: {', '.join(PROTOCOLS)}; or a YAML file)")


_YAML_KEYS = ("name", "base", "cameras", "lights", "groups", "test_views")
INLINE_PROTOCOL = "split config: protocol"  # the source (and default name) of a protocol given inline


def protocol_from_yaml(path: str | os.PathLike[str]) -> Protocol:
    """A custom protocol file: name, base (paper|synthetic), cameras/lights/groups {train, test}, test_views."""
    path = Path(path)
    return protocol_from_dict(read_yaml(path, "protocol"), str(path))


def protocol_from_dict(
    d: Any, source: str | None = "protocol", path: tuple[str, ...] = (), name: str | None = None
) -> Protocol:
    """Build a Protocol from a parsed mapping (see `protocol_from_yaml`). Unknown keys and bad values are a
    ConfigError naming `source` and the key below `path`; `name` defaults to the stem of `source`."""

    def fail(problem: str, *key: str) -> ConfigError:
        return ConfigError(problem, (*path, *key), source)

    if not isinstance(d, dict):
        raise fail(f"expected a mapping, got {d!r}")
    check_keys(d, _YAML_KEYS, path, source)
    base_name = d.get("base", "paper")
    if base_name not in PROTOCOLS:
        raise fail(f"expected one of {', '.join(PROTOCOLS)}, got {base_name!r}", "base")
    base = builtin_protocol(base_name)
    default_name = name if name is not None else Path(source or "protocol").stem
    kw: dict[str, Any] = {"name": str(d.get("name", default_name)), "light_rule": base.light_rule}
    kw["test_views"] = base.test_views
    for key in ("cameras", "lights", "groups"):
        sub = d.get(key, {}) or {}
        if not isinstance(sub, dict):
            raise fail(f"expected a mapping with 'train' and/or 'test', got {sub!r}", key)
        check_keys(sub, ("train", "test"), (*path, key), source)
        for part in ("train", "test"):
            if part in sub:
                v = sub[part]
                ok = (
                    (isinstance(v, int) and not isinstance(v, bool))
                    or isinstance(v, list)
                    or v in ("rest", "all")
                )
                if not ok:
                    raise fail(f"expected a count, a list or 'rest', got {v!r}", key, part)
                kw[f"{part}_{key}"] = v
    lights = d.get("lights") or {}
    if (
        base.light_rule == "hemisphere"
        and "test" not in lights
        and not isinstance(lights.get("train", []), list)
    ):
        raise fail("with base synthetic and no lights.test, give an explicit list", "lights", "train")
    if "test_views" in d:
        tv = d["test_views"]
        if tv is not None and (not isinstance(tv, int) or isinstance(tv, bool) or tv < 1):
            raise fail(f"expected a positive integer or null, got {tv!r}", "test_views")
        kw["test_views"] = tv
    params = {k: v for k, v in d.items() if k != "name"}
    return Protocol(parameters=params, **kw)


def paper_light_counts(num_lights: int) -> tuple[int, int]:
    """(train, test) light counts on a stage: the paper's 75 and 10 of 331, scaled by num_lights (each >= 1)."""
    n_train = max(1, round(PAPER_NUM_TRAIN_LIGHTS * num_lights / PAPER_NUM_LIGHTS))
    n_test = max(1, round(len(PAPER_TEST_LIGHT_NUMBERS) * num_lights / PAPER_NUM_LIGHTS))
    return n_train, n_test


def place_test_lights(n: int, num_lights: int) -> list[int]:
    """n test lights: the paper's test lights (a spread subset when n < 10) scaled to the stage's light count;
    beyond 10, evenly spaced. Identity on a 331-light stage with n = 10."""
    if n <= len(PAPER_TEST_LIGHT_NUMBERS):
        ranks = [int((k + 0.5) * len(PAPER_TEST_LIGHT_NUMBERS) / n) for k in range(n)]
        paper = [paper_number_to_index(PAPER_TEST_LIGHT_NUMBERS[r]) for r in ranks]
        wanted = [round(p * (num_lights - 1) / (PAPER_NUM_LIGHTS - 1)) for p in paper]
    else:
        wanted = [int((k + 0.5) * num_lights / n) for k in range(n)]
    return _place(wanted, num_lights, taken=set())


def place_train_lights(n: int, num_lights: int, test: set[int]) -> list[int]:
    """n train lights: linspace(1, L, n) truncated (1-based, as the paper), moved to the nearest free light on a
    collision with a test light. Exactly the paper's 75 on a 331-light stage."""
    numbers = np.linspace(1, num_lights, n).astype(int)
    return _place([paper_number_to_index(int(x)) for x in numbers], num_lights, taken=set(test))


def _place(wanted: list[int], num_lights: int, taken: set[int]) -> list[int]:
    if len(wanted) + len(taken) > num_lights:
        raise LightstageError(
            f"protocol asks for {len(wanted)} lights beside {len(taken)} others; the stage has {num_lights}"
        )
    out: list[int] = []
    for w in wanted:
        for d in range(num_lights):
            for cand in (w - d, w + d):
                if 0 <= cand < num_lights and cand not in taken:
                    break
            else:
                continue
            break
        taken.add(cand)
        out.append(cand)
    return sorted(out)


def hemisphere_grid() -> tuple[np.ndarray, np.ndarray]:
    """(224, 3) unit directions of rows 2..8 (1-based) x 32 columns of a 16x32 lat-long grid (cell centres, +z up),
    and a bool mask of the held-out half (checkerboard: (row + col) odd)."""
    dirs, held = [], []
    for r in SYNTHETIC_ROWS:
        theta = np.deg2rad((r - 0.5) * 180.0 / ENVMAP_ROWS)
        for c in range(ENVMAP_COLS):
            phi = np.deg2rad((c + 0.5) * 360.0 / ENVMAP_COLS)
            dirs.append([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
            held.append((r + c) % 2 == 1)
    return np.asarray(dirs), np.asarray(held)


def hemisphere_lights(light_dirs: np.ndarray) -> tuple[list[int], list[int]]:
    """Map the synthetic protocol onto a stage's lights (rig-frame unit directions, (L, 3)).

    Every upper-hemisphere light (z > 0) takes the label of its nearest grid direction: train or held out.
    Test lights: for 10 held-out grid directions evenly spread in raster order, the nearest held-out-labelled
    stage light (each used once). On a stage whose lights are the grid directions this gives exactly 112 / 10.
    """
    grid, held = hemisphere_grid()
    upper = np.flatnonzero(light_dirs[:, 2] > 1e-9)
    if upper.size == 0:
        raise LightstageError("synthetic protocol: the stage has no lights on the upper hemisphere")
    cos = light_dirs[upper] @ grid.T  # (U, 224)
    nearest = np.argmax(cos, axis=1)
    train = sorted(int(i) for i in upper[~held[nearest]])
    candidates = upper[held[nearest]]
    held_dirs = grid[held]
    picks = np.linspace(0, len(held_dirs) - 1, SYNTHETIC_TEST_LIGHTS).round().astype(int)
    test: list[int] = []
    for p in picks:
        if len(test) == len(candidates):
            break
        order = np.argsort(-(light_dirs[candidates] @ held_dirs[p]))
        for k in order:
            if int(candidates[k]) not in test:
                test.append(int(candidates[k]))
                break
    return train, sorted(test)


def _cameras(spec: Any, ids: tuple[str, ...], what: str, src: str) -> list[str]:
    if isinstance(spec, list):
        out = []
        for c in spec:
            if isinstance(c, int) and not isinstance(c, bool):
                if not 0 <= c < len(ids):
                    raise LightstageError(
                        f"{src}: {what}: camera index {c} not on the stage (0..{len(ids) - 1})"
                    )
                out.append(ids[c])
            elif str(c) in ids:
                out.append(str(c))
            else:
                raise LightstageError(f"{src}: {what}: camera {c!r} not on the stage ({ids[0]}..{ids[-1]})")
        return out
    raise AssertionError(spec)


def _lights(spec: list, num_lights: int, what: str, src: str) -> list[int]:
    out = []
    for x in spec:
        if not isinstance(x, int) or isinstance(x, bool) or not 0 <= x < num_lights:
            raise LightstageError(
                f"{src}: {what}: light {x!r} not on the stage (0-based 0..{num_lights - 1})"
            )
        out.append(x)
    return out


def resolve(
    protocol: Protocol, stage: Stage, excluded: set[FrameId] | None = None, source: str = "protocol"
) -> Split:
    """Apply a protocol to a stage: pick cameras, lights and groups, subtract rejected frames, validate."""
    ids = tuple(stage.camera_ids)
    C, L = len(ids), len(stage.lights)
    src = f"{source} (stage {stage.name!r}: {C} cameras, {L} lights)"
    rules = []
    # cameras: the last 10% (>= 1) test, the rest train
    tc = protocol.test_cameras
    if tc is None:
        tc = max(1, round(PAPER_TEST_CAMERA_FRACTION * C))
        rules.append(f"test cameras = the last {tc} of {C} (the paper's 2 of 20, >= 1)")
    if isinstance(tc, int):
        if tc >= C or tc < 1:
            raise LightstageError(
                f"{src}: asks for {tc} test cameras; the stage has {C} (at least one must train)"
            )
        test_cams = list(ids[C - tc :])
    else:
        test_cams = _cameras(tc, ids, "cameras.test", src)
    trc = protocol.train_cameras
    if trc in ("rest", "all", None):
        train_cams = [c for c in ids if c not in test_cams]
    elif isinstance(trc, int):
        if trc > C - len(test_cams):
            raise LightstageError(
                f"{src}: asks for {trc} training cameras; only {C - len(test_cams)} are not test cameras"
            )
        train_cams = [c for c in ids if c not in test_cams][:trc]
    else:
        train_cams = _cameras(trc, ids, "cameras.train", src)
    # lights
    if protocol.light_rule == "hemisphere" and not isinstance(protocol.test_lights, list | int):
        train_l, test_l = hemisphere_lights(_unit(stage.light_positions_rig()))
        rules.append(
            "lights: each upper-hemisphere stage light takes the train/held-out label of its nearest direction on "
            "the 7x32 grid (rows 2-8 of 16x32, checkerboard held out); test = nearest held-out lights to 10 "
            "evenly spread held-out directions"
        )
        if isinstance(protocol.train_lights, list):
            train_l = _lights(protocol.train_lights, L, "lights.train", src)
        if not test_l:
            raise LightstageError(
                f"{src}: synthetic protocol: no held-out upper-hemisphere light for testing"
            )
    else:
        n_train, n_test = paper_light_counts(L)
        tl = protocol.test_lights
        if tl is None:
            tl = n_test
            rules.append(
                f"test lights = {n_test} of {L} (the paper's 10 of 331, scaled, >= 1), at the paper's test lights scaled to {L} lights"
            )
        if isinstance(tl, int):
            if not 1 <= tl < L:
                raise LightstageError(
                    f"{src}: asks for {tl} test lights; the stage has {L} (at least one must train)"
                )
            test_l = place_test_lights(tl, L)
        else:
            test_l = _lights(tl, L, "lights.test", src)
        trl = protocol.train_lights
        if trl is None:
            trl = n_train
            rules.append(
                f"train lights = {n_train} of {L} (the paper's 75 of 331, scaled, >= 1): trunc(linspace(1, {L}, {n_train})) 1-based, moved off test lights"
            )
        if trl in ("rest", "all"):
            train_l = [i for i in range(L) if i not in set(test_l)]
        elif isinstance(trl, int):
            if trl < 1 or trl + len(test_l) > L:
                raise LightstageError(
                    f"{src}: asks for {trl} train + {len(test_l)} test lights; the stage has {L}"
                )
            train_l = place_train_lights(trl, L, set(test_l))
        else:
            train_l = _lights(trl, L, "lights.train", src)

    # groups
    def groups(spec: Any, what: str) -> list[str]:
        if spec in ("all", "rest", None):
            return list(stage.group_names)
        if isinstance(spec, int):
            raise LightstageError(f"{src}: groups.{what}: give a list of group names or 'all'")
        out = []
        for g in spec:
            g = f"{g:03d}" if isinstance(g, int) else str(g)
            if g not in stage.group_names:
                raise LightstageError(
                    f"{src}: groups.{what}: group {g!r} not on the stage ({', '.join(stage.group_names)})"
                )
            out.append(g)
        return out

    train_groups, test_groups = groups(protocol.train_groups, "train"), groups(protocol.test_groups, "test")
    train_fs = {g: (tuple(train_cams), tuple(train_l)) for g in train_groups}
    test_views = [(g, c) for g in test_groups for c in test_cams]
    if protocol.test_views is not None and protocol.test_views < len(test_views):
        keep = {int(k) for k in np.linspace(0, len(test_views) - 1, protocol.test_views).round()}
        test_views = [v for k, v in enumerate(test_views) if k in keep]
        rules.append(f"test views = {len(test_views)} of the held-out (group, camera) views, evenly spread")
    test_fs: dict[str, tuple[tuple[str, ...], tuple[int, ...]]] = {}
    for g in test_groups:
        cams = tuple(c for gg, c in test_views if gg == g)
        if cams:
            test_fs[g] = (cams, tuple(test_l))
    excluded = excluded or set()
    train = FrameSet(train_fs, frozenset(f for f in excluded if _member(train_fs, f)))
    test = FrameSet(test_fs, frozenset(f for f in excluded if _member(test_fs, f)))
    params = {
        "train_cameras": train_cams,
        "test_cameras": test_cams,
        "train_lights": train_l,
        "test_lights": test_l,
        "train_groups": train_groups,
        "test_groups": test_groups,
        "test_views": protocol.test_views,
        "light_rule": protocol.light_rule,
        "requested": protocol.parameters,
    }
    split = Split(
        protocol.name,
        params,
        "; ".join(rules),
        StageInfo(stage.name, tuple(stage.camera_ids), len(stage.lights), tuple(stage.group_names)),
        train,
        test,
        src,
    )
    validate_split(split)
    return split


def _member(groups: dict[str, tuple[tuple[str, ...], tuple[int, ...]]], f: FrameId) -> bool:
    cams, lights = groups.get(f.group, ((), ()))
    return f.camera in cams and f.light in lights


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
