"""Per-pixel statistics of a view's OLAT stack, accumulated one processed frame at a time and mergeable.

`StatsAccumulator.add(rgb, saturated, lit_threshold)` streams frames (float32 sums within a chunk of lights);
`finish()` gives a `ViewStats` (count, mean, M2, ...). Two ViewStats over disjoint light sets combine exactly
with `merge` (Chan et al.'s parallel mean/variance update; counts add, maxima take the max), so chunks of a
view are processed as independent tasks and merged in a tree (`merge_tree`). Memory is a fixed number of
images per view, whatever the number of lights.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightstage.atomic import atomic_path
from lightstage.errors import LightstageError
from lightstage.npyio import load_npz
from lightstage.tonemap import LUMA, luminance

# The brightness ladder: per pixel, how many unsaturated frames are brighter than cutoff x 2^-k for each k
# (one level per stop, 1 to 16 stops below the cutoff). It is a measurement grid, not a tuned threshold: it
# gives every pixel's distribution of brightness over the lights, from which segmentation reads robust
# quantiles (a level exceeded in a quarter of the frames ignores flares and shadows in a few frames).
LADDER_STOPS = tuple(range(1, 17))


def ladder_levels(cutoff: float) -> np.ndarray:
    """(K,) float32 luminance levels of the ladder for a stage's saturation cutoff."""
    return (float(cutoff) * 2.0 ** -np.asarray(LADDER_STOPS, np.float64)).astype(np.float32)


@dataclass
class ViewStats:
    """Statistics over the frames (lights) of one view; arrays are (h, w[, 3]).

    mean/m2: per-channel mean and sum of squared deviations over all `count` frames (variance = m2/count).
    peak: max luminance; saturated: frames flagged saturated; lit: unsaturated frames whose luminance
    exceeded that frame's lit threshold; lum_sum: luminance summed over unsaturated frames; ladder: (K, h, w)
    unsaturated frames brighter than each level of `ladder_levels` (empty (0, h, w) when not accumulated).
    The counts (saturated, lit, ladder) are uint16; only `StatsAccumulator.finish(reuse=True)` leaves them
    uint8, and `load` and `merge` widen them.
    """

    count: int
    lights: tuple[int, ...]
    mean: np.ndarray
    m2: np.ndarray
    peak: np.ndarray
    saturated: np.ndarray
    lit: np.ndarray
    lum_sum: np.ndarray
    ladder: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.ladder is None:
            self.ladder = np.zeros((0, *self.peak.shape), np.uint16)

    @property
    def variance(self) -> np.ndarray:
        return self.m2 / max(self.count, 1)

    @property
    def unsaturated(self) -> np.ndarray:
        """(h, w) number of unsaturated frames."""
        return self.count - self.saturated.astype(np.int64)

    def unsaturated_mean_luminance(self) -> np.ndarray:
        return (self.lum_sum / np.maximum(self.unsaturated, 1)).astype(np.float32)

    def lit_fraction(self) -> np.ndarray:
        return (self.lit / np.maximum(self.unsaturated, 1)).astype(np.float32)

    def mean_luminance(self) -> np.ndarray:
        """(h, w) float32 luminance of the mean over every frame, saturated ones included: a processed pixel is
        the area mean of clipped raw values, so it stays linear in the object's coverage where the object clips
        (a silhouette pixel of an overexposed object is flagged saturated in every frame)."""
        return luminance(self.mean).astype(np.float32)

    def brightness_quantile(self, q: float) -> np.ndarray:
        """(h, w) float32: per pixel, the brightness (stops relative to the cutoff, <= 0; higher is brighter)
        that a fraction `q` of its frames exceed, read from the ladder and interpolated linearly between its
        levels; -(K + 1) where fewer than `q` of the frames reach the lowest level. A saturated frame is at or
        above the cutoff, so it exceeds every level: a pixel that clips in most frames (an overexposed object)
        is at the top, not left without a level (the ladder counts unsaturated frames only).

        One ladder level at a time (the fractions rise with the level index, so a pixel's level is the first
        that reaches `q`): the same float32 arithmetic as on the whole (K, h, w) stack, without its 0.2 GB of
        temporaries at 2048 x 1366 (0.3-0.4 s per call there against 0.5 s, idle Intel VM)."""
        k = len(self.ladder)
        if k == 0:
            raise LightstageError("statistics without the brightness ladder (rerun preprocess)")
        n = np.float32(max(self.count, 1))
        sat = self.saturated.astype(np.float32)
        qf = np.float32(q)
        stops = np.asarray(LADDER_STOPS, np.float32)
        out = np.full(sat.shape, -(stops[-1] + 1.0), np.float32)
        open_ = np.ones(sat.shape, bool)  # pixels whose level is not found yet
        prev = None
        for j in range(k):
            frac = (self.ladder[j].astype(np.float32) + sat) / n
            hit = open_ & (frac >= qf)
            if j == 0:
                out[hit] = -stops[0]
            elif hit.any():
                lo, hi = prev[hit], frac[hit]
                t = (qf - lo) / np.maximum(hi - lo, np.float32(1e-6))
                out[hit] = -(stops[j - 1] + t * (stops[j] - stops[j - 1]))
            open_ &= ~hit
            if not open_.any():
                break
            prev = frac
        return out

    def chroma_variation(self) -> np.ndarray:
        """(h, w) RMS over channels of the per-channel standard deviation relative to the mean luminance."""
        std = np.sqrt(np.maximum(self.variance, 0)).mean(axis=-1)
        return (std / np.maximum(self.mean @ np.array(LUMA, np.float32), 1e-12)).astype(np.float32)

    # ---- merge ---------------------------------------------------------------------------------------
    def merge(self, other: ViewStats, in_place: bool = False) -> ViewStats:
        """Statistics of the union of two disjoint light sets (Chan et al. pairwise update). `in_place`: the
        result is written over this object's arrays (the same values, in the same order of operations), so
        merging holds no third set of images: for `merge_tree` over parts nobody else holds."""
        if self.mean.shape != other.mean.shape:
            raise LightstageError(
                f"cannot merge statistics of shapes {self.mean.shape} and {other.mean.shape}"
            )
        overlap = set(self.lights) & set(other.lights)
        if overlap:
            raise LightstageError(f"statistics overlap in lights {sorted(overlap)[:5]}")
        if other.count == 0:
            return self
        if self.count == 0:
            return other
        na, nb = self.count, other.count
        n = na + nb
        if not in_place:
            delta = other.mean - self.mean
            mean = self.mean + delta * np.float32(nb / n)
            m2 = self.m2 + other.m2 + delta * delta * np.float32(na * nb / n)
            mean, m2 = mean.astype(np.float32), m2.astype(np.float32)
        else:
            delta = np.subtract(other.mean, self.mean)
            m2 = np.add(self.m2, other.m2, out=self.m2)
            square = np.multiply(delta, delta)
            m2 += np.multiply(square, np.float32(na * nb / n), out=square)
            del square
            mean = np.add(self.mean, np.multiply(delta, np.float32(nb / n), out=delta), out=self.mean)

        def add_counts(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            out = a if in_place and a.dtype == np.uint16 else None
            return np.add(a, b, out=out, dtype=np.uint16)

        return ViewStats(
            count=n,
            lights=tuple(sorted(self.lights + other.lights)),
            mean=mean,
            m2=m2,
            peak=np.maximum(self.peak, other.peak, out=self.peak if in_place else None),
            saturated=add_counts(self.saturated, other.saturated),
            lit=add_counts(self.lit, other.lit),
            lum_sum=np.add(self.lum_sum, other.lum_sum, out=self.lum_sum if in_place else None),
            ladder=add_counts(self.ladder, other.ladder)
            if len(self.ladder) == len(other.ladder)
            else _no_ladder(self),
        )

    # ---- files ---------------------------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "count": np.array(self.count),
            "lights": np.array(self.lights, dtype=np.int32),
            "mean": self.mean,
            "m2": self.m2,
            "peak": self.peak,
            "saturated": self.saturated,
            "lit": self.lit,
            "lum_sum": self.lum_sum,
            "ladder": self.ladder,
        }

    def save(self, path: str | os.PathLike[str], extras: dict[str, np.ndarray] | None = None) -> None:
        """Write as an uncompressed .npz, atomically (extra arrays ride along)."""
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **self.arrays(), **(extras or {}))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ViewStats:
        """Read a file written by `save` (its extra arrays land in `extras`)."""
        path = Path(path)
        try:
            data = load_npz(path)
        except (OSError, ValueError) as e:
            raise LightstageError(f"{path}: unreadable statistics ({e})") from None
        try:
            stats = cls(
                count=int(data.pop("count")),
                lights=tuple(int(x) for x in data.pop("lights")),
                mean=data.pop("mean"),
                m2=data.pop("m2"),
                peak=data.pop("peak"),
                saturated=_widen(data.pop("saturated")),
                lit=_widen(data.pop("lit")),
                lum_sum=data.pop("lum_sum"),
                ladder=_widen(data.pop("ladder", None)),
            )
        except KeyError as e:
            raise LightstageError(f"{path}: statistics lack {e}") from None
        stats.extras = data
        return stats


def _widen(counts: np.ndarray | None) -> np.ndarray | None:
    """Counts as uint16 (a chunk's partial keeps counts of fewer than 256 frames in uint8)."""
    return counts.astype(np.uint16) if counts is not None and counts.dtype == np.uint8 else counts


def _no_ladder(s: ViewStats) -> np.ndarray:
    return np.zeros((0, *s.peak.shape), np.uint16)


def empty_stats(height: int, width: int) -> ViewStats:
    """Statistics of no frames (the identity of `merge`)."""
    return ViewStats(
        count=0,
        lights=(),
        mean=np.zeros((height, width, 3), np.float32),
        m2=np.zeros((height, width, 3), np.float32),
        peak=np.zeros((height, width), np.float32),
        saturated=np.zeros((height, width), np.uint16),
        lit=np.zeros((height, width), np.uint16),
        lum_sum=np.zeros((height, width), np.float32),
        ladder=np.zeros((len(LADDER_STOPS), height, width), np.uint16),
    )


def merge_tree(parts: Iterable[ViewStats], consume: bool = False) -> ViewStats | None:
    """Merge statistics pairwise in a balanced tree, streaming: at most log2(k) + 1 partials are held.
    `consume`: the parts are nobody else's (e.g. loaded from files), so merges write over them (`merge`'s
    `in_place`): the same result with ~190 MB less at 2048x1366 (the view task's peak at 331 lights)."""
    stack: list[tuple[int, ViewStats]] = []  # (level, stats) like a binary counter
    for part in parts:
        level, cur = 0, part
        while stack and stack[-1][0] == level:
            _, prev = stack.pop()
            cur = prev.merge(cur, in_place=consume)
            level += 1
        stack.append((level, cur))
    if not stack:
        return None
    _, out = stack.pop()
    while stack:
        _, prev = stack.pop()
        out = prev.merge(out, in_place=consume)
    return out


class StatsAccumulator:
    """Streams frames of one chunk of lights into float32 sums and integer counts; `finish` converts to
    ViewStats.

    The per-pixel counts (ladder levels, lit, saturated) run in uint8 and are added into uint16 totals every
    `COUNT_STRETCH` frames: half the memory traffic of uint16 counters. The ladder takes one pass to find, per
    pixel, how many levels the luminance does not exceed (`_levels_below`), then one uint8 compare per level,
    instead of a float compare per level (3x cheaper at 2048x1366, the same counts)."""

    def __init__(self, height: int, width: int, cutoff: float | None = None):
        """`cutoff`: the stage's saturation cutoff, for the brightness ladder (None: no ladder)."""
        self.height, self.width = height, width
        self.levels = ladder_levels(cutoff) if cutoff is not None else np.zeros(0, np.float32)
        self._top = _ladder_top_bits(self.levels)
        k = len(self.levels)
        self._lit, self._sat = k, k + 1  # rows of the count arrays after the ladder's
        self._counts8 = np.zeros((k + 2, height, width), np.uint8)
        self._counts16: np.ndarray | None = None  # totals of earlier stretches, made at the first flush
        self._stretch = 0
        self._spent = False
        self._bits = np.empty((height, width), np.int32)
        self._below = np.empty((height, width), np.uint8)
        self._cmp = np.empty((height, width), np.uint8)
        self.count = 0
        self.lights: list[int] = []
        self.s1 = np.zeros((height, width, 3), np.float32)
        self.s2 = np.zeros((height, width, 3), np.float32)
        self.peak = np.zeros((height, width), np.float32)
        self.lum_sum = np.zeros((height, width), np.float32)

    def add(
        self,
        light: int,
        rgb: np.ndarray,
        saturated: np.ndarray,
        lit_threshold: float,
        lum: np.ndarray | None = None,
    ) -> None:
        """Accumulate one frame: (h, w, 3) float32 rgb, (h, w) bool saturated, its lit threshold."""
        import cv2

        if self._spent:
            raise LightstageError("statistics accumulator already finished with reuse")
        if rgb.shape != (self.height, self.width, 3):
            raise LightstageError(f"frame of shape {rgb.shape}, statistics are {self.height}x{self.width}")
        if lum is None:
            lum = luminance(rgb)
        counts, cmp = self._counts8, self._cmp
        sat = np.ascontiguousarray(saturated, bool).view(np.uint8)
        unsat = np.bitwise_xor(sat, 1)
        cv2.accumulate(rgb, self.s1)
        cv2.accumulateSquare(rgb, self.s2)
        np.maximum(self.peak, lum, out=self.peak)
        np.add(counts[self._sat], sat, out=counts[self._sat])
        cv2.accumulate(lum, self.lum_sum, mask=unsat)
        cv2.compare(lum, float(lit_threshold), cv2.CMP_GT, dst=cmp)  # 255 where lit
        np.bitwise_and(cmp, unsat, out=cmp)  # 1 where lit and unsaturated
        np.add(counts[self._lit], cmp, out=counts[self._lit])
        if len(self.levels):
            below = self._levels_below(lum, sat)
            for k in range(len(self.levels)):
                cv2.compare(below, k, cv2.CMP_LE, dst=cmp)  # 255 where lum > levels[k]
                np.subtract(counts[k], cmp, out=counts[k])  # 255 is -1 in uint8: adds one
        self.count += 1
        self.lights.append(int(light))
        self._stretch += 1
        if self._stretch == COUNT_STRETCH:
            self._flush()

    def _levels_below(self, lum: np.ndarray, sat: np.ndarray) -> np.ndarray:
        """(h, w) uint8: per pixel, how many ladder levels (from the top) the luminance does not exceed; all
        of them for saturated pixels. The levels are the cutoff's float32 bits minus one exponent step per
        stop, and non-negative floats order like their int32 bits, so the count is (top bits - lum bits) >> 23,
        clipped: exactly the strict `lum > level` comparisons of `direct_stats`."""
        bits, below = self._bits, self._below
        np.maximum(lum.view(np.int32), 0, out=bits)  # negative values (and -0.0) lie below every level
        np.subtract(self._top, bits, out=bits)
        np.right_shift(bits, 23, out=bits)
        np.clip(bits, 0, len(self.levels), out=bits)
        np.copyto(below, bits, casting="unsafe")
        np.copyto(below, len(self.levels), where=sat.view(bool))
        return below

    def _flush(self) -> None:
        """Add the uint8 counts of this stretch of frames into the uint16 totals and restart them."""
        if self._counts16 is None:
            self._counts16 = self._counts8.astype(np.uint16)
        else:
            np.add(self._counts16, self._counts8, out=self._counts16)
        self._counts8.fill(0)
        self._stretch = 0

    def _totals(self) -> np.ndarray:
        """(K + 2, h, w) uint16 counts of all frames added so far (a new array)."""
        if self._counts16 is None:
            return self._counts8.astype(np.uint16)
        return np.add(self._counts16, self._counts8, dtype=np.uint16)

    def finish(self, reuse: bool = False) -> ViewStats:
        """Statistics of the frames added so far (float64 arithmetic for the sums-to-moments step).

        `reuse`: the statistics take over the accumulator's arrays instead of copies (the mean and m2 are
        computed in place of the sums, and counts of fewer than 256 frames stay uint8, which `ViewStats.load`
        widens): a chunk task saves its partial without ~200 MB of fresh arrays at 2048x1366. The accumulator
        is spent then."""
        if self._spent:
            raise LightstageError("statistics accumulator already finished with reuse")
        n = self.count
        if reuse and self._counts16 is None:
            counts = self._counts8
        elif reuse:
            counts = np.add(self._counts16, self._counts8, out=self._counts16)
        else:
            counts = self._totals()
        ladder, lit, saturated = counts[: self._lit], counts[self._lit], counts[self._sat]
        if n == 0:
            s = empty_stats(self.height, self.width)
            s.ladder = ladder.astype(np.uint16)
            return s
        mean, m2 = (self.s1, self.s2) if reuse else (np.empty_like(self.s1), np.empty_like(self.s2))
        for r in range(0, self.height, 256):  # row bands keep the float64 temporaries small
            s1 = self.s1[r : r + 256].astype(np.float64)
            m2[r : r + 256] = np.maximum(self.s2[r : r + 256] - s1 * s1 / n, 0.0)
            mean[r : r + 256] = s1 / n
        self._spent = reuse
        return ViewStats(
            count=n,
            lights=tuple(self.lights),
            mean=mean,
            m2=m2,
            peak=self.peak if reuse else self.peak.copy(),
            saturated=saturated,
            lit=lit,
            lum_sum=self.lum_sum if reuse else self.lum_sum.copy(),
            ladder=ladder,
        )


# uint8 counters of StatsAccumulator are added into the uint16 totals after this many frames (before 256)
COUNT_STRETCH = 255


def _ladder_top_bits(levels: np.ndarray) -> int:
    """The int32 bits of the level one stop above the first (the cutoff in float32), checking that the levels
    are normal positive floats one exponent step apart, as `StatsAccumulator._levels_below` needs."""
    if len(levels) == 0:
        return 0
    bits = levels.view(np.int32).astype(np.int64)
    top = int(bits[0]) + (LADDER_STOPS[0] << 23)
    expected = top - (np.asarray(LADDER_STOPS, np.int64) << 23)
    if not (
        np.isfinite(levels).all() and levels[-1] >= np.finfo(np.float32).tiny and (bits == expected).all()
    ):
        raise LightstageError(
            f"saturation cutoff {levels[0] * 2.0:g}: its brightness ladder is not representable"
        )
    return top


def direct_stats(
    frames: list[np.ndarray],
    saturated: list[np.ndarray],
    lit_thresholds: list[float],
    lights: list[int],
    cutoff: float | None = None,
) -> ViewStats:
    """Reference statistics from the whole stack in memory (float64; tests)."""
    x = np.stack(frames).astype(np.float64)
    s = np.stack(saturated)
    lum = x @ np.array(LUMA)
    unsat = ~s
    lit = (lum > np.asarray(lit_thresholds, np.float64)[:, None, None]) & unsat
    return ViewStats(
        count=len(frames),
        lights=tuple(lights),
        mean=x.mean(axis=0).astype(np.float32),
        m2=((x - x.mean(axis=0)) ** 2).sum(axis=0).astype(np.float32),
        peak=lum.max(axis=0).astype(np.float32),
        saturated=s.sum(axis=0).astype(np.uint16),
        lit=lit.sum(axis=0).astype(np.uint16),
        lum_sum=(lum * unsat).sum(axis=0).astype(np.float32),
        ladder=np.stack([((lum > lv) & unsat).sum(axis=0) for lv in ladder_levels(cutoff)]).astype(np.uint16)
        if cutoff is not None
        else None,
    )
