"""Atomic writes: no partial file on failure, normal permissions on success."""

from __future__ import annotations

import os
import stat

import pytest

from lightstage.atomic import atomic_path, write_json_atomic, write_text_atomic


def test_failed_write_leaves_nothing(tmp_path):
    target = tmp_path / "out.txt"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_permissions_follow_umask(tmp_path):
    old = os.umask(0o022)
    try:
        write_json_atomic(tmp_path / "a" / "b.json", {"x": 1})
    finally:
        os.umask(old)
    mode = stat.S_IMODE((tmp_path / "a" / "b.json").stat().st_mode)
    assert mode == 0o644
