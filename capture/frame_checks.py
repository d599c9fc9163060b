"""Per-frame checks of capture validation: the statuses a frame can get, its manifest record, the header check
(pure Python, exr_header.read_exr_header) and the decode check a decoder process runs (capture/decoder_pool.py)."""

from __future__ import annotations

import stat
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from lightstage import exr_header, frames
from lightstage.errors import LightstageError

# Every status a frame can get; only `ok` frames are usable.
STATUSES = (
    "ok",
    "missing",  # no file where capture.yaml's template says
    "empty",  # zero bytes
    "unreadable",  # not an EXR, corrupt/unsupported header (deep data, absurd sizes)
    "truncated",  # the chunk table points past the end of the file, or chunks were never written
    "wrong_resolution",  # data window differs from the stage's raw resolution
    "wrong_channels",  # no R, G, B of one half/float type
    "corrupt",  # deep only: pixel decode failed, the decoder crashed or hung
    "non_finite",  # deep only: NaN or Inf samples
    "negative",  # deep only: negative samples
)
DEEP_STATUSES = ("corrupt", "non_finite", "negative")
LOSSY_COMPRESSIONS = ("b44", "b44a", "dwaa", "dwab", "htj2k256", "htj2k32", "lj2k")
DEFAULT_TIMEOUT_S = 300.0  # per decoded file; a full 8192x5464 frame decodes in ~0.3 s
DEFAULT_MEMORY_LIMIT_MB = 8192  # address-space ceiling of each decoder process


@dataclass
class FrameRecord:
    """One expected frame in the manifest: where it is, what its header says, and its status."""

    id: str
    path: str
    status: str = "ok"
    message: str = ""
    size: int = 0
    mtime_ns: int = 0
    dtype: str = ""
    width: int = 0
    height: int = 0
    channels: list[str] = field(default_factory=list)
    compression: str = ""
    deep: bool = False  # pixels were decoded and checked
    saturated_fraction: float | None = None  # deep only: fraction of pixels at/above the stage cutoff

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["resolution"] = [d.pop("width"), d.pop("height")]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FrameRecord:
        """A record this module wrote (`to_dict`), not user input: read as it is, keys it does not know are
        left out (the strict config loader is for configs; this runs once per frame of a 60k-frame scan)."""
        d = dict(d)
        d["width"], d["height"] = d.pop("resolution", [0, 0])
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def fail(self, status: str, message: str) -> FrameRecord:
        self.status, self.message = status, message
        return self


# --------------------------------------------------------------------------------------------------
# per-frame checks


def check_header(frame_id: str, path: Path, rel: str, expected_size: tuple[int, int] | None) -> FrameRecord:
    """Header-only checks of one file (no pixel decoding, no native code): never raises."""
    rec = FrameRecord(frame_id, rel)
    try:
        st = path.stat()
    except FileNotFoundError:
        return rec.fail("missing", f"{path}: file not found")
    except OSError as e:
        return rec.fail("unreadable", f"{path}: cannot stat ({e.strerror or e})")
    rec.size, rec.mtime_ns = st.st_size, st.st_mtime_ns
    if not stat.S_ISREG(st.st_mode):
        return rec.fail("unreadable", f"{path}: not a regular file")
    if st.st_size == 0:
        return rec.fail("empty", f"{path}: empty file")
    try:
        header = exr_header.read_exr_header(path)
    except LightstageError as e:
        return rec.fail("unreadable", str(e))
    except Exception as e:  # a bug in the parser must cost one file, not the scan
        return rec.fail("unreadable", f"{path}: cannot parse header ({type(e).__name__}: {e})")
    rec.width, rec.height = header.width, header.height
    rec.channels = list(header.channels)
    rec.compression = header.compression
    rec.dtype = header.rgb_dtype() or header.dtype
    if header.chunk_problem:
        cut = header.chunk_problem.startswith(("truncated", "incomplete"))
        return rec.fail("truncated" if cut else "unreadable", f"{path}: {header.chunk_problem}")
    if exr_header.oversized(header.width, header.height) or (
        expected_size is not None and (header.width, header.height) != tuple(expected_size)
    ):
        want = f"expected {expected_size[0]}x{expected_size[1]}" if expected_size else "over the pixel limit"
        return rec.fail("wrong_resolution", f"{path}: resolution {header.width}x{header.height}, {want}")
    try:
        exr_header.check_exr_header(header, expected_size, "RGB")
    except LightstageError as e:
        status = "unreadable" if header.decode_bytes > exr_header.MAX_DECODE_BYTES else "wrong_channels"
        return rec.fail(status, str(e))
    return rec


def decode_check(request: dict[str, Any]) -> dict[str, Any]:
    """Decode one frame and check its pixels (runs inside a decoder process); returns a small dict."""
    path = request["path"]
    expected = tuple(request["expected"]) if request.get("expected") else None
    try:
        pixels = frames.read_exr(path, expected_size=expected, channels="RGB")  # header re-checked first
    except LightstageError as e:
        return {"status": "corrupt", "message": str(e)}
    except MemoryError:
        return {"status": "corrupt", "message": f"{path}: out of memory while decoding"}
    result = frames.check_pixels(pixels, request.get("saturation"))
    message = f"{path}: {result.message}" if result.message else ""
    return {"status": result.status, "message": message, "saturated_fraction": result.saturated_fraction}
