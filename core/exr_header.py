"""EXR headers read in pure Python before any decoder touches a file: file-type check first (a FIFO or device
is a clear error, never a hang), a bounded read, every header attribute, channel list and chunk table checked
against sane limits, so a hostile or truncated file is one error line naming it (lightstage.frames decodes)."""

from __future__ import annotations

import math
import os
import stat
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.errors import EnvironmentFault, LightstageError, is_environment_error

MAX_PIXELS = 16384 * 16384
# Ceiling on the bytes one decode may allocate (all channels of all parts), checked before decoding.
MAX_DECODE_BYTES = 4 << 30
# Real EXR headers are a few KB; a header that does not end within this many bytes is refused.
MAX_HEADER_BYTES = 1 << 20
MAX_CHANNELS = 1024
# Side limits handed to OpenEXR's own guard (setMaxImageSize / setMaxTileSize) as a second line of defence.
MAX_SIDE = 65536

EXR_MAGIC = b"\x76\x2f\x31\x01"
_FLAG_TILED, _FLAG_LONG_NAMES, _FLAG_DEEP, _FLAG_MULTIPART = 0x200, 0x400, 0x800, 0x1000
# OpenEXR compression enum -> (name, scanlines per chunk; None where the count is not known here)
_COMPRESSION = {
    0: ("none", 1),
    1: ("rle", 1),
    2: ("zips", 1),
    3: ("zip", 16),
    4: ("piz", 32),
    5: ("pxr24", 16),
    6: ("b44", 32),
    7: ("b44a", 32),
    8: ("dwaa", 32),
    9: ("dwab", 256),
    10: ("htj2k256", 256),
    11: ("htj2k32", 32),
    12: ("lj2k", None),
    13: ("zstd", None),
}
_PIXEL_TYPES = {0: ("uint", 4), 1: ("half", 2), 2: ("float", 4)}


@dataclass(frozen=True)
class FrameHeader:
    """What an image header says, read without decoding pixels."""

    path: Path
    width: int
    height: int
    channels: dict[str, str]  # name -> 'half' | 'float' | 'uint'
    compression: str
    attributes: dict[str, Any] = field(default_factory=dict)
    subsampled: tuple[str, ...] = ()  # channels with x/y sampling != 1
    tiled: bool = False
    parts: int = 1
    decode_bytes: int = 0  # what decoding every channel of every part allocates
    chunk_problem: str | None = None  # set when the chunk table shows truncation / an unfinished file
    part_channels: tuple[tuple[str, ...], ...] = ()  # channel names of every part, in file order

    @property
    def dtype(self) -> str:
        kinds = set(self.channels.values())
        return kinds.pop() if len(kinds) == 1 else "mixed"

    def rgb_dtype(self) -> str:
        """Sample type of the R, G, B channels ('half', 'float', 'mixed' or '' when one is missing)."""
        kinds = {self.channels.get(c, "") for c in "RGB"}
        if "" in kinds:
            return ""
        return kinds.pop() if len(kinds) == 1 else "mixed"


class _Bad(Exception):
    """Internal: a structural problem in an EXR file (turned into a LightstageError naming the file)."""


@dataclass
class _Part:
    attrs: dict[str, tuple[str, bytes]]
    channels: dict[str, tuple[str, int, int, int]]  # name -> (type, bytes, xsampling, ysampling)
    window: tuple[int, int, int, int]
    compression: int
    tiles: tuple[int, int, int, int] | None  # (xsize, ysize, level mode, rounding mode)
    kind: str


def read_exr_header(path: str | os.PathLike[str]) -> FrameHeader:
    """Parse an EXR header only (fast, pure Python, bounded reads: safe on hostile files).

    Raises a LightstageError naming the file for anything that is not a well-formed flat (non-deep) EXR
    header; truncation found in the chunk table is reported in `chunk_problem` (read_exr refuses it).
    """
    path = Path(path)
    try:
        _check_regular(path)  # before any open: opening a FIFO blocks until a writer appears
        # O_NONBLOCK: should the path be swapped for a FIFO after the check, the open does not wait either
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as f:
            st = os.fstat(f.fileno())
            size = st.st_size
            if not stat.S_ISREG(st.st_mode):
                raise _Bad(_file_kind(st.st_mode))
            if size == 0:
                raise _Bad("empty file")
            head = f.read(min(size, 4096))  # a typical header is well under 1 KB
            if len(head) < 8 or head[:4] != EXR_MAGIC:
                raise _Bad("not an EXR file (bad magic number)")
            try:
                parts, table_at, flags = _parse_headers(head, size)
            except _NeedMore:
                head = head + f.read(min(size, MAX_HEADER_BYTES) - len(head))
                try:
                    parts, table_at, flags = _parse_headers(head, size)
                except _NeedMore:
                    raise _Bad(f"header does not end within {min(size, MAX_HEADER_BYTES)} bytes") from None
            chunk_problem = _check_chunk_tables(f, parts, table_at, size, bool(flags & _FLAG_MULTIPART))
    except _Bad as e:
        raise LightstageError(f"{path}: {e}") from None
    except FileNotFoundError:
        raise LightstageError(f"{path}: file not found") from None
    except OSError as e:
        raise _os_error(path, e) from None
    first = parts[0]
    x0, y0, x1, y1 = first.window
    channels = {n: t for n, (t, _, _, _) in first.channels.items()}
    subsampled = tuple(n for n, (_, _, xs, ys) in first.channels.items() if (xs, ys) != (1, 1))
    decode_bytes = sum(
        (p.window[2] - p.window[0] + 1)
        * (p.window[3] - p.window[1] + 1)
        * sum(c[1] for c in p.channels.values())
        for p in parts
    )
    return FrameHeader(
        path=path,
        width=x1 - x0 + 1,
        height=y1 - y0 + 1,
        channels=channels,
        compression=_COMPRESSION[first.compression][0],
        attributes=_plain_attributes(first.attrs),
        subsampled=subsampled,
        tiled=first.tiles is not None,
        parts=len(parts),
        decode_bytes=decode_bytes,
        chunk_problem=chunk_problem,
        part_channels=tuple(tuple(p.channels) for p in parts),
    )


class _NeedMore(Exception):
    """Internal: the header runs past the bytes read so far."""


def _check_regular(path: Path) -> None:
    """Raise _Bad for a path that is not a regular file (FIFO, device, socket, directory), from stat alone."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise _Bad(_file_kind(st.st_mode))


def _file_kind(mode: int) -> str:
    """What a non-regular file is, for the message (a FIFO or a device would hang or stream forever)."""
    for test, what in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a directory"),
    ):
        if test(mode):
            return f"not a regular file ({what})"
    return "not a regular file"


def _os_error(path: Path, e: OSError) -> LightstageError:
    """An OSError met reading `path`: an EnvironmentFault (retried, never a bad frame) when its errno says the
    machine failed (permission, I/O error, ...), else a LightstageError about the file."""
    cls = EnvironmentFault if is_environment_error(e) else LightstageError
    return cls(f"{path}: cannot read ({e.strerror or e})")


def prefetch_file(path: str | os.PathLike[str], timeout_s: float) -> None:
    """Read the whole file once in a helper thread (it lands in the page cache the decoder then reads), so that
    stalled storage fails within `timeout_s` naming the file instead of hanging the task: an EnvironmentFault
    for the timeout and for OSErrors of the machine, a LightstageError for a FIFO, device or missing file.
    Costs ~0.01 CPU-s per 200 MB from the page cache. A stalled thread is left behind (it cannot be stopped)."""
    import threading

    path = Path(path)
    outcome: list[BaseException | None] = []
    done = threading.Event()

    def run() -> None:
        try:
            _read_all(path)
            outcome.append(None)
        except BaseException as e:  # noqa: BLE001 - handed to the waiting thread
            outcome.append(e)
        done.set()

    threading.Thread(target=run, name=f"prefetch {path.name}", daemon=True).start()
    if not done.wait(timeout_s):
        raise EnvironmentFault(f"{path}: read stalled: the file was not read within {timeout_s:g} s")
    e = outcome[0]
    if e is None:
        return
    if isinstance(e, _Bad):
        raise LightstageError(f"{path}: {e}")
    if isinstance(e, FileNotFoundError):
        raise LightstageError(f"{path}: file not found")
    if isinstance(e, OSError):
        raise _os_error(path, e)
    raise e


_READ_BUFFERS: list[memoryview] = []  # free 8 MB read buffers (a stalled read keeps its own)


def _read_all(path: Path) -> None:
    """Read `path` to its end into a reused buffer (the type is checked before the open)."""
    try:
        buf = _READ_BUFFERS.pop()
    except IndexError:
        buf = memoryview(bytearray(8 << 20))
    try:
        _check_regular(path)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        try:
            while os.readv(fd, [buf]):
                pass
        finally:
            os.close(fd)
    finally:
        _READ_BUFFERS.append(buf)


def _parse_headers(buf: bytes, file_size: int) -> tuple[list[_Part], int, int]:
    """Parse the version field and every part header in `buf`; return (parts, offset of the chunk table, flags)."""
    (version,) = struct.unpack_from("<i", buf, 4)
    flags = version & ~0xFF
    if version & 0xFF != 2:
        raise _Bad(f"unsupported EXR version {version & 0xFF}")
    if flags & ~(_FLAG_TILED | _FLAG_LONG_NAMES | _FLAG_DEEP | _FLAG_MULTIPART):
        raise _Bad(f"unknown EXR version flags 0x{flags:x}")
    if flags & _FLAG_DEEP and not flags & _FLAG_MULTIPART:
        raise _Bad("deep EXR data is not supported (frames must be flat images)")
    max_name = 255 if flags & _FLAG_LONG_NAMES else 31
    pos, parts = 8, []
    while True:
        attrs, pos = _parse_attributes(buf, pos, max_name, file_size)
        parts.append(_make_part(attrs, flags, len(parts)))
        if not flags & _FLAG_MULTIPART:
            break
        if pos >= len(buf):
            raise _NeedMore
        if buf[pos] == 0:  # an empty header ends the list of parts
            pos += 1
            break
        if len(parts) >= 1024:
            raise _Bad("more than 1024 parts")
    return parts, pos, flags


def _cstring(buf: bytes, pos: int, limit: int, what: str) -> tuple[str, int]:
    end = buf.find(b"\0", pos, pos + limit + 1)
    if end < 0:
        if len(buf) - pos <= limit:
            raise _NeedMore
        raise _Bad(f"{what} longer than {limit} characters at byte {pos}")
    try:
        return buf[pos:end].decode("utf-8"), end + 1
    except UnicodeDecodeError:
        raise _Bad(f"{what} is not valid UTF-8 at byte {pos}") from None


def _parse_attributes(
    buf: bytes, pos: int, max_name: int, file_size: int
) -> tuple[dict[str, tuple[str, bytes]], int]:
    attrs: dict[str, tuple[str, bytes]] = {}
    while True:
        if pos >= len(buf):
            raise _NeedMore
        if buf[pos] == 0:
            return attrs, pos + 1
        name, pos = _cstring(buf, pos, max_name, "attribute name")
        kind, pos = _cstring(buf, pos, max_name, f"type of attribute {name!r}")
        if pos + 4 > len(buf):
            raise _NeedMore
        (n,) = struct.unpack_from("<i", buf, pos)
        pos += 4
        if n < 0 or pos + n > min(file_size, MAX_HEADER_BYTES):
            raise _Bad(f"attribute {name!r} has an invalid size {n}")
        if pos + n > len(buf):
            raise _NeedMore
        attrs[name] = (kind, buf[pos : pos + n])
        pos += n
        if len(attrs) > 10000:
            raise _Bad("more than 10000 header attributes")


def _make_part(attrs: dict[str, tuple[str, bytes]], flags: int, index: int) -> _Part:
    where = f"part {index}: " if flags & _FLAG_MULTIPART else ""

    def need(name: str, kind: str, size: int | None) -> bytes:
        if name not in attrs:
            raise _Bad(f"{where}missing required header attribute {name!r}")
        k, v = attrs[name]
        if k != kind or (size is not None and len(v) != size):
            raise _Bad(f"{where}header attribute {name!r} has type {k!r} ({len(v)} bytes), expected {kind!r}")
        return v

    kind = "tiledimage" if flags & _FLAG_TILED else "scanlineimage"
    if "type" in attrs:
        kind = attrs["type"][1].split(b"\0")[0].decode("ascii", "replace")
    if kind.startswith("deep"):
        raise _Bad(f"{where}deep EXR data is not supported (frames must be flat images)")
    if kind not in ("scanlineimage", "tiledimage"):
        raise _Bad(f"{where}unknown part type {kind!r}")
    window = struct.unpack("<4i", need("dataWindow", "box2i", 16))
    x0, y0, x1, y1 = window
    if x1 < x0 or y1 < y0:
        raise _Bad(f"{where}invalid data window ({x0}, {y0})-({x1}, {y1})")
    (compression,) = need("compression", "compression", 1)
    if compression not in _COMPRESSION:
        raise _Bad(f"{where}unknown compression type {compression}")
    channels = _parse_channels(need("channels", "chlist", None), where)
    tiles = None
    if kind == "tiledimage":
        xs, ys, mode = struct.unpack("<IIB", need("tiles", "tiledesc", 9))
        if not (1 <= xs <= MAX_SIDE and 1 <= ys <= MAX_SIDE) or mode & 0xF > 2 or mode >> 4 > 1:
            raise _Bad(f"{where}invalid tile description {xs}x{ys} mode {mode}")
        tiles = (xs, ys, mode & 0xF, mode >> 4)
    return _Part(attrs, channels, window, compression, tiles, kind)


def _parse_channels(data: bytes, where: str) -> dict[str, tuple[str, int, int, int]]:
    channels: dict[str, tuple[str, int, int, int]] = {}
    pos = 0
    while True:
        if pos >= len(data):
            raise _Bad(f"{where}channel list is not terminated")
        if data[pos] == 0:
            break
        try:
            name, pos = _cstring(data, pos, 255, "channel name")
        except _NeedMore:
            raise _Bad(f"{where}channel list is not terminated") from None
        if pos + 16 > len(data):
            raise _Bad(f"{where}channel {name!r}: truncated channel description")
        ptype, _linear, xs, ys = struct.unpack_from("<iB3xii", data, pos)
        pos += 16
        if ptype not in _PIXEL_TYPES:
            raise _Bad(f"{where}channel {name!r}: unknown pixel type {ptype}")
        if xs < 1 or ys < 1:
            raise _Bad(f"{where}channel {name!r}: invalid sampling {xs}x{ys}")
        if name in channels:
            raise _Bad(f"{where}duplicate channel {name!r}")
        channels[name] = (*_PIXEL_TYPES[ptype], xs, ys)
        if len(channels) > MAX_CHANNELS:
            raise _Bad(f"{where}more than {MAX_CHANNELS} channels")
    if not channels:
        raise _Bad(f"{where}no channels")
    return channels


def _chunk_count(part: _Part) -> int | None:
    """Number of chunks the part's offset table holds (None when unknown for its compression)."""
    if "chunkCount" in part.attrs:
        kind, value = part.attrs["chunkCount"]
        if kind == "int" and len(value) == 4:
            return struct.unpack("<i", value)[0]
    x0, y0, x1, y1 = part.window
    w, h = x1 - x0 + 1, y1 - y0 + 1
    if part.tiles is None:
        lines = _COMPRESSION[part.compression][1]
        return None if lines is None else -(-h // lines)
    tx, ty, mode, rounding = part.tiles

    def levels(n: int) -> int:
        return (math.ceil(math.log2(n)) if rounding else int(math.log2(n))) + 1

    def size(n: int, level: int) -> int:
        return max(1, -(-n // (1 << level)) if rounding else n >> level)

    def tiles(lx: int, ly: int) -> int:
        return -(-size(w, lx) // tx) * -(-size(h, ly) // ty)

    if mode == 0:
        return tiles(0, 0)
    if mode == 1:
        return sum(tiles(lv, lv) for lv in range(levels(max(w, h))))
    return sum(tiles(lx, ly) for lx in range(levels(w)) for ly in range(levels(h)))


def _check_chunk_tables(f: Any, parts: list[_Part], table_at: int, size: int, multipart: bool) -> str | None:
    """Read the chunk offset tables and check they point inside the file; None when the layout is sound."""
    counts = [_chunk_count(p) for p in parts]
    if any(c is None for c in counts):
        return None  # compression with an unknown chunk height: leave it to the decoder
    total = sum(counts)  # type: ignore[arg-type]
    if total > 1 << 24:
        x0, y0, x1, y1 = parts[0].window
        raise _Bad(f"implausible chunk count {total} (data window {x1 - x0 + 1}x{y1 - y0 + 1})")
    if any(c < 1 for c in counts):  # type: ignore[operator]
        raise _Bad(f"invalid chunk count {min(counts)}")  # type: ignore[type-var]
    table_end = table_at + 8 * total
    if table_end > size:
        return f"truncated: file ends at byte {size}, inside the chunk table (needs {table_end} bytes)"
    f.seek(table_at)
    offsets = np.frombuffer(f.read(8 * total), dtype="<u8")
    unwritten = int(np.count_nonzero(offsets == 0))
    if unwritten:  # OpenEXR itself refuses a table with unwritten entries
        return f"incomplete: {unwritten} of {total} chunks were never written"
    if (offsets < table_end).any():
        return "corrupt chunk table: offsets point into the header"
    if (offsets >= size).any():
        bad = int((offsets >= size).sum())
        return f"truncated: {bad} of {total} chunks start past the end of the file ({size} bytes)"
    last = int(offsets.max())
    f.seek(last)
    head = f.read(4 + 16 + 4)  # [part number] + tile coordinates or scanline y + data size
    part = parts[0]
    if multipart:
        if len(head) < 4:
            return f"truncated: last chunk at byte {last} has no complete header ({size} bytes)"
        (index,) = struct.unpack_from("<i", head, 0)
        if not 0 <= index < len(parts):
            return f"corrupt chunk table: the chunk at byte {last} names part {index}"
        part = parts[index]
    prefix = (4 if multipart else 0) + (16 if part.tiles is not None else 4)
    if len(head) < prefix + 4:
        return f"truncated: last chunk at byte {last} has no complete header ({size} bytes)"
    (data_size,) = struct.unpack_from("<i", head, prefix)
    if data_size <= 0:
        return f"corrupt chunk table: the chunk at byte {last} declares {data_size} bytes"
    if last + prefix + 4 + data_size > size:
        return f"truncated: last chunk at byte {last} needs {data_size} bytes, file ends at {size}"
    return None


def _plain_attributes(attrs: dict[str, tuple[str, bytes]]) -> dict[str, Any]:
    """Header attributes of simple types (string, int, float, double) as Python values."""
    out: dict[str, Any] = {}
    for name, (kind, value) in attrs.items():
        if kind == "string":
            out[name] = value.decode("utf-8", "replace")
        elif kind == "int" and len(value) == 4:
            out[name] = struct.unpack("<i", value)[0]
        elif kind == "float" and len(value) == 4:
            out[name] = struct.unpack("<f", value)[0]
        elif kind == "double" and len(value) == 8:
            out[name] = struct.unpack("<d", value)[0]
    return out


def check_exr_header(
    header: FrameHeader, expected_size: tuple[int, int] | None = None, channels: str = "RGB"
) -> None:
    """Refuse, before decoding, what read_exr cannot return safely: truncation, a data window that is not
    the expected size or too large, missing / subsampled / integer channels, or too many bytes to decode."""
    if header.chunk_problem:
        raise LightstageError(f"{header.path}: {header.chunk_problem}")
    _check_size(header, expected_size)
    if header.decode_bytes > MAX_DECODE_BYTES:
        raise LightstageError(
            f"{header.path}: decoding would need {header.decode_bytes / 2**30:.1f} GiB "
            f"(limit {MAX_DECODE_BYTES / 2**30:.0f} GiB)"
        )
    missing = [c for c in channels if c not in header.channels]
    if missing:
        raise LightstageError(
            f"{header.path}: missing channel(s) {', '.join(missing)} (has {', '.join(sorted(header.channels))})"
        )
    sub = [c for c in channels if c in header.subsampled]
    if sub:
        raise LightstageError(f"{header.path}: subsampled channel(s) {', '.join(sub)} are not supported")
    kinds = {header.channels[c] for c in channels}
    if len(kinds) != 1 or not kinds <= {"half", "float"}:
        raise LightstageError(
            f"{header.path}: channels {', '.join(channels)} must all be half or all float, "
            f"got {', '.join(header.channels[c] for c in channels)}"
        )


def oversized(width: int, height: int) -> bool:
    """True for a data window no supported frame has (over MAX_PIXELS, or a side over MAX_SIDE)."""
    return width * height > MAX_PIXELS or max(width, height) > MAX_SIDE


def _check_size(header: FrameHeader, expected: tuple[int, int] | None) -> None:
    if oversized(header.width, header.height):
        raise LightstageError(
            f"{header.path}: data window {header.width}x{header.height} exceeds the size limit ({MAX_SIDE} per side, {MAX_PIXELS} pixels)"
        )
    if expected is not None and (header.width, header.height) != tuple(expected):
        raise LightstageError(
            f"{header.path}: resolution {header.width}x{header.height}, expected {expected[0]}x{expected[1]}"
        )


def reason(e: BaseException) -> str:
    return first_line(str(e)) or type(e).__name__


def first_line(text: str) -> str:
    lines = (text or "").strip().splitlines()
    return lines[0][:200] if lines else ""
