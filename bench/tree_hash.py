"""Hash a work directory's outputs so two runs can be compared byte for byte (issue 20's acceptance).

Every visible file below WORK counts by its relative path and bytes, except the per-stage reports
(`reports/`: timings, hosts, the pipeline's records), `capture.txt` (an absolute path) and logs (`*.log`,
timestamped). JSON outputs are hashed without the keys that differ between two runs of the same code
(timings such as `seconds`, `created`; the cache keys `inputs_key`/`inputs_hash` over mtimes; the counts of
frames a task processed or reused, which a killed and resumed task splits differently, and which decoder
decoded them, which `decoder: auto` measures in each run), with the work
and capture paths replaced by placeholders, so runs in different folders compare equal. Calibration's SfM
is deterministic only with one pycolmap thread: compare runs made with `calibrate: {num_threads: 1}`.

    python bench/tree_hash.py WORK [--capture CAPTURE] [--list]

prints one sha256 (and, with --list, one line per file: its own sha256 and path).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

EXCLUDED_TOP = ("reports", "capture.txt")
# JSON keys that hold wall/CPU times, dates, cache keys over file mtimes and reports, or how much work this
# particular run did rather than read back (a resumed or rescheduled task reuses frames), not results.
TIMING_KEYS = frozenset(
    {"seconds", "cpu_seconds", "created", "started", "finished", "timings", "inputs_key", "inputs_hash"}
    | {"processed", "reused", "resumed"}
    | {"decoded", "decoder_probe"}  # which decoder ran how many frames (decoder: auto measures per run)
)


def output_files(work: Path) -> list[Path]:
    """The compared files: visible (no hidden atomic-write temporaries), outside the reports."""
    out = []
    for p in sorted(work.rglob("*")):
        rel = p.relative_to(work)
        if not p.is_file() or rel.parts[0] in EXCLUDED_TOP or p.suffix == ".log":
            continue
        if any(part.startswith(".") for part in rel.parts):
            continue
        out.append(p)
    return out


def _drop_timings(obj: Any) -> Any:
    """`obj` without TIMING_KEYS at any depth."""
    if isinstance(obj, dict):
        return {k: _drop_timings(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [_drop_timings(v) for v in obj]
    return obj


def file_bytes(path: Path, replacements: list[tuple[bytes, bytes]]) -> bytes:
    """The file's bytes; text outputs with absolute run paths replaced, JSON also without timing keys."""
    data = path.read_bytes()
    if path.suffix in (".json", ".yaml", ".txt", ".csv", ".log"):
        for old, new in replacements:
            data = data.replace(old, new)
    if path.suffix == ".json":
        try:
            data = json.dumps(_drop_timings(json.loads(data)), sort_keys=True).encode()
        except ValueError:
            pass
    return data


def tree_hash(work: str | Path, capture: str | Path | None = None, listing: list[str] | None = None) -> str:
    """sha256 over (relative path, bytes) of every output file of `work` (see the module docstring)."""
    work = Path(work).resolve()
    if capture is None and (work / "capture.txt").is_file():
        capture = (work / "capture.txt").read_text().strip()
    replacements = [(str(work).encode(), b"<WORK>")]
    if capture is not None:
        replacements.insert(0, (str(Path(capture).resolve()).encode(), b"<CAPTURE>"))
    h = hashlib.sha256()
    for p in output_files(work):
        rel = str(p.relative_to(work))
        data = file_bytes(p, replacements)
        h.update(rel.encode() + b"\0" + len(data).to_bytes(8, "little") + data)
        if listing is not None:
            listing.append(f"{hashlib.sha256(data).hexdigest()}  {rel}")
    return h.hexdigest()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path, help="work directory")
    ap.add_argument("--capture", type=Path, help="capture path to mask (default: WORK/capture.txt)")
    ap.add_argument("--list", action="store_true", help="also print each file's sha256 and path")
    args = ap.parse_args(argv)
    if not args.work.is_dir():
        print(f"tree_hash: error: {args.work}: not a directory", file=sys.stderr)
        return 2
    listing: list[str] | None = [] if args.list else None
    digest = tree_hash(args.work, args.capture, listing)
    for line in listing or []:
        print(line)
    print(digest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
