"""Which raw-frame decoder a worker process uses (config `decoder: auto`): measured on the machine, not assumed.

The two decoders of `downscale.DECODERS` give identical outputs but their cost depends on the CPU and the
kernel: OpenEXR's whole-frame decode was the floor on an AMD EPYC VM (OpenImageIO's bands 1.6-1.9x), while on
an Intel Xeon VM its per-frame path cost 2.2x the floor (fresh 268 MB arrays: page faults, huge-page zeroing)
and the bands 1.14x (docs/benchmarks.md). So with `auto` each worker process decodes its first frames with
each decoder in turn, one run of `PROBE_FRAMES + 1` consecutive frames per decoder (real frames, nothing is
decoded twice), times them in CPU seconds and uses the cheaper one from then on. The choice and the timings go
into the chunk records and the report.

Runs, not alternating frames: a worker reuses the freed frame block for the next whole-frame decode (the
workers' malloc settings), and a band decode in between breaks that reuse, so alternating frames measured
OpenEXR at up to 2x its steady cost (1.3-1.4 against 0.65-0.72 CPU-s on the AMD VM, docs/benchmarks.md).
Once the choice is made the probe's freed blocks go back to the system: under those settings a worker that kept
the bands would otherwise hold the probe's freed whole frame (~270 MB) to the end (Intel Xeon VM, 2026-12-07).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import TypeVar

from lightstage.malloc import release_free_heap
from lightstage.preprocess.downscale import DECODERS

AUTO = "auto"
CHOICES = (AUTO, *DECODERS)
PROBE_FRAMES = 2  # frames per decoder timed before a process chooses (the first of each is not counted)

T = TypeVar("T")


def choose(samples: dict[str, list[float]], probe_frames: int = PROBE_FRAMES) -> str | None:
    """The decoder with the lowest median CPU seconds per frame once every decoder has `probe_frames` samples
    beyond its first (which pays one-time costs: imports, first allocations); None while still probing.
    Ties go to the first of DECODERS."""
    counted = {d: samples.get(d, [])[1:] for d in DECODERS}
    if any(len(v) < probe_frames for v in counted.values()):
        return None
    return min(DECODERS, key=lambda d: statistics.median(counted[d]))


def next_to_probe(samples: dict[str, list[float]], probe_frames: int = PROBE_FRAMES) -> str:
    """While probing, the first decoder (in DECODERS order) that has not finished its run of `probe_frames + 1`
    consecutive frames: each decoder is timed in its own steady state, not interleaved with the other."""
    for d in DECODERS:
        if len(samples.get(d, [])) < probe_frames + 1:
            return d
    return DECODERS[-1]


class DecoderChooser:
    """Per-process state of `decoder: auto`: the samples taken so far and the decoder chosen from them."""

    def __init__(
        self,
        probe_frames: int = PROBE_FRAMES,
        clock: Callable[[], float] = time.process_time,
        on_chosen: Callable[[], object] = release_free_heap,
    ) -> None:
        self.probe_frames, self.clock, self.on_chosen = probe_frames, clock, on_chosen
        self.samples: dict[str, list[float]] = {d: [] for d in DECODERS}
        self.chosen: str | None = None
        self.counts: dict[str, int] = {d: 0 for d in DECODERS}  # frames decoded by this process, per decoder

    def run(self, configured: str, decode: Callable[[str], T]) -> tuple[T, str]:
        """Decode one frame with `decode(decoder)`: the configured decoder, or under `auto` the chosen one (or
        the next to probe, timed). Returns the result and the decoder that ran."""
        if configured != AUTO or self.chosen is not None:
            decoder = configured if configured != AUTO else self.chosen
            result = decode(decoder)
        else:
            decoder = next_to_probe(self.samples, self.probe_frames)
            cpu0 = self.clock()
            result = decode(decoder)
            self.samples[decoder].append(self.clock() - cpu0)
            self.chosen = choose(self.samples, self.probe_frames)
            if self.chosen is not None:
                self.on_chosen()  # once: the probe's freed blocks are not kept for the process's life
        self.counts[decoder] += 1
        return result, decoder

    def probe_medians(self) -> dict[str, float]:
        """Median probe CPU seconds per decoder (first samples left out), for the chunk records."""
        return {d: round(statistics.median(v[1:]), 4) for d, v in self.samples.items() if len(v) > 1}


_PROCESS_CHOOSER = DecoderChooser()


def process_chooser() -> DecoderChooser:
    """The chooser of this worker process (dask worker or pool process: one chunk task at a time)."""
    return _PROCESS_CHOOSER
