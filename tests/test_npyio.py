"""NumPy files are read through lightstage.npyio, whose lock keeps numpy's header parsing (ast.literal_eval) to
one thread at a time: CPython up to 3.12 can fail concurrent AST construction with `SystemError: AST constructor
recursion depth mismatch`, which the suite hit in a two-thread dask worker loading statistics."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from lightstage import npyio

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "capture", "simulator", "preprocess", "calibration", "dataset", "interop", "training")
PACKAGES += ("viewer", "pipelines")
HOME = "core/npyio.py"


def raw_numpy_loads(planted: dict[str, str] | None = None) -> list[str]:
    """`file:line` of every `np.load(...)` / `numpy.load(...)` call in the package folders outside npyio."""
    planted = planted or {}
    out = []
    for folder in PACKAGES:
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = str(path.relative_to(REPO))
            if rel == HOME:
                continue
            tree = ast.parse(path.read_text() + planted.get(rel, ""), rel)
            for node in ast.walk(tree):
                f = node.func if isinstance(node, ast.Call) else None
                if (
                    isinstance(f, ast.Attribute)
                    and f.attr == "load"
                    and isinstance(f.value, ast.Name)
                    and f.value.id in ("np", "numpy")
                ):
                    out.append(f"{rel}:{node.lineno}")
    return out


def test_every_numpy_load_goes_through_npyio():
    found = raw_numpy_loads()
    assert not found, "np.load outside lightstage.npyio (use load_npz / load_npy):\n" + "\n".join(found)
    planted = raw_numpy_loads({"preprocess/stats.py": "\ndef f(p):\n    return np.load(p)\n"})
    assert len(planted) == 1 and planted[0].startswith("preprocess/stats.py:")


def test_headers_are_parsed_under_the_lock(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    np.savez(tmp_path / "a.npz", x=np.arange(3), y=np.eye(2, dtype=np.float32))
    np.save(tmp_path / "b.npy", np.arange(4, dtype=np.int16))
    held: list[bool] = []
    parse = ast.literal_eval

    def watched(source):  # numpy parses each array header with ast.literal_eval
        held.append(npyio._HEADER_LOCK.locked())
        return parse(source)

    monkeypatch.setattr(ast, "literal_eval", watched)
    z = npyio.load_npz(tmp_path / "a.npz")
    assert set(z) == {"x", "y"} and z["y"].dtype == np.float32
    assert list(npyio.load_npz(tmp_path / "a.npz", ["x"])) == ["x"]
    assert npyio.load_npy(tmp_path / "b.npy").tolist() == [0, 1, 2, 3]
    mapped = npyio.load_npy(tmp_path / "b.npy", mmap_mode="r")
    assert isinstance(mapped, np.memmap) and mapped[3] == 3
    assert len(held) == 5 and all(held)
    assert not npyio._HEADER_LOCK.locked()


def test_pickles_are_refused(tmp_path: Path):
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="pickle"):
        npyio.load_npy(tmp_path / "o.npy")
    assert not npyio._HEADER_LOCK.locked()  # released on errors too


def test_a_damaged_npz_is_a_value_error_that_callers_name(tmp_path: Path):
    """A truncated archive raised zipfile.BadZipFile, which the loaders' (OSError, ValueError) handlers let
    through as a traceback; now ValueError, and e.g. the statistics loader names the file."""
    from lightstage.errors import LightstageError
    from lightstage.preprocess.stats import ViewStats

    np.savez(tmp_path / "full.npz", a=np.zeros(1000))
    data = (tmp_path / "full.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="not a readable .npz archive"):
        npyio.load_npz(tmp_path / "cut.npz")
    assert not npyio._HEADER_LOCK.locked()
    with pytest.raises(LightstageError, match=r"cut\.npz: unreadable statistics"):
        ViewStats.load(tmp_path / "cut.npz")
