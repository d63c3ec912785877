"""The scan stream in front of SLAM: a source's messages in, clean scans in stamp order out.

On the way it picks the clock (header stamp or record time, ``slam.io.stamps``), puts
messages recorded a few places out of order back in order (the reorder buffer), follows a
clock that stepped back, counts and skips what cannot be used (damaged messages, stamps
not after the last kept one) and fills what the driver left out: the ring from the beam
table inferred on the first scans, and, when asked, the per-point time of clouds stored
beam by beam. It yields every kept :class:`Scan` (strictly increasing stamps) and every
:class:`SkippedMessage` (already counted in :class:`StreamStats`).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from itertools import islice
from typing import Any

import numpy as np

from slam.errors import InputError
from slam.io.stamps import Reorder
from slam.types import Scan, SkippedMessage

log = logging.getLogger(__name__)

# this many scans in a row whose stamps are not after the last kept one stop the run (bad
# input): the rest of the input would be dropped, a useless trajectory without an error
STAMP_RUN_LIMIT = 10

Item = Scan | SkippedMessage


@dataclass
class StreamStats:
    """What the stream dropped or repaired (metrics.json): skipped messages by reason,
    (message index, s added to its and every later stamp) where the clock stepped back,
    and the beam model as inferred or read (``BeamModel.describe``)."""

    skipped: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    clock_steps: list[tuple[int, float]] = field(default_factory=list)
    sensor: str | None = None


class ScanStream:
    """Clean scans from ``scans`` (a ScanSource or any iterable of Scan / SkippedMessage).

    ``config``: the ``source`` section (clock, reorder window, beam window, layout time).
    ``start``: the index of the first message used (those before are read and ignored).
    ``max_frames``: stop after this many scans. ``strict``: the first skipped message or
    bad stamp raises InputError instead of being counted. STAMP_RUN_LIMIT stamps in a row
    not after the last kept one raise InputError unless they show a clock step (followed).
    """

    def __init__(
        self,
        scans: Iterable[Item],
        config: Any,
        *,
        start: int = 0,
        max_frames: int | None = None,
        strict: bool = False,
        stats: StreamStats | None = None,
    ) -> None:
        self.config, self.max_frames, self.strict = config, max_frames, strict
        self.stats = stats if stats is not None else StreamStats()
        self.beams: Any = None  # slam.sensor.beam_model.BeamModel once estimated; False: none
        notes = getattr(scans, "notes", None)
        self._notes = notes if isinstance(notes, list) else None  # a clock step is noted
        use_stamps = getattr(scans, "use_stamps", None)  # bags: header or record time
        self._has_record = callable(use_stamps)  # the source has a second clock
        self._clock = config.stamps  # "auto" | "header" | "record"
        if callable(use_stamps):
            use_stamps(config.stamps, config.reorder_window)
        elif config.stamps == "record":
            raise InputError(
                "source.stamps=record: only bags have a record time; this input's stamps "
                "are its own (use source.stamps auto or header)"
            )
        self._reorder = Reorder(islice(scans, start, None), config.reorder_window)
        self._buffer: list[Scan] = []  # the first scans, held until the beam model exists
        self._period = 0.1  # sweep period (s): median stamp step of the first scans
        # per-point time from the layout for beam-by-beam clouds without one: as the time
        # field ("always") or for the front end to try ("auto": KITTI-style clouds, in
        # folders or bags, are published motion-compensated, an Ouster driver's are not)
        self._layout_time = config.layout_time != "never"
        self._layout_trusted = config.layout_time == "always"
        # scans not after the last kept one, in a row, with that last stamp: skipped when a
        # scan in order comes, or the clock stepped back (STAMP_RUN_LIMIT of them)
        self._held_back: list[tuple[Scan, float]] = []
        self._offset = 0.0  # s added to every stamp since the clock stepped back
        self._last: float | None = None  # the stamp of the last scan kept
        self._kept = 0  # scans kept so far (yielded or held for the beam model)

    def items(
        self,
        stop: Callable[[], bool] = lambda: False,
        on_message: Callable[[int], None] | None = None,
    ) -> Iterator[Item]:
        """Kept scans and skipped messages until the input ends, ``max_frames`` scans or
        ``stop()`` (checked after every message; then the scans held are not released).
        ``on_message(n)``: called with the number of input messages consumed so far."""
        for n, item in enumerate(self._reorder, 1):
            if self.max_frames is not None and self._kept >= self.max_frames:
                break
            yield from self._consume(item)
            if on_message is not None:
                on_message(n)
            if stop():
                return
        yield from self._settle_held_back()  # out-of-order scans at the very end
        yield from self._flush()  # a source shorter than the beam-model window

    __iter__ = items

    def drain(self) -> Iterator[Item]:
        """The scans still held (reorder buffer, beam window) after the input stopped with
        an error (a truncated bag, stamps gone wrong): read frames are not lost."""
        for scan in self._reorder.drain():
            scan.stamp = float(scan.stamp) + self._offset
            if self._last is None or scan.stamp > self._last:
                yield from self._feed(scan)
        yield from self._settle_held_back()
        yield from self._flush()

    # ------------------------------------------------------------------ beams
    def _estimate_beams(self, scans: list[Scan]) -> None:
        """The beam table from the first scans: the ring field when the driver gives one,
        else the point layout / elevation histogram (slam.sensor). Logged once."""
        from slam.sensor.beam_table import beams_from_rings, estimate_beams

        scans = [s for s in scans if len(s) >= 100]  # empty / nearly empty scans tell nothing
        try:
            if not scans:
                raise InputError("no scan with points among the first ones")
            if all(s.ring is not None for s in scans):
                self.beams = beams_from_rings([s.xyz for s in scans], [s.ring for s in scans])
            else:
                self.beams = estimate_beams([s.xyz for s in scans])
        except (InputError, ValueError, IndexError) as exc:  # e.g. a 2D laser: no beams
            log.info("no beam model: %s", exc)
            self.beams = False
            return
        self.stats.sensor = self.beams.describe()
        log.info("sensor: %s", self.stats.sensor)

    def _with_rings(self, scan: Scan) -> Scan:
        """Fill what the driver left out: the ring from the beam table and, for clouds
        stored beam by beam in firing order, the per-point time from the azimuth."""
        if not (self.beams and len(scan)):
            return scan
        need_ring = scan.ring is None
        need_time = scan.time is None and self.beams.layout and self._layout_time
        if need_ring or need_time:  # one pass: the azimuth computed once for both
            ring, t = self.beams.fill(scan.xyz, self._period, ring=need_ring, time=need_time)
            if need_ring:
                scan.ring = ring
            if need_time and self._layout_trusted:
                scan.time = t
            elif need_time:
                scan.layout_time = t
        return scan

    def _feed(self, scan: Scan) -> Iterator[Scan]:
        """A kept scan: held while the first ``source.beam_scans`` build the beam model."""
        self._last = float(scan.stamp)
        self._kept += 1
        n = self.config.beam_scans
        if self.beams is None and n > 0:
            self._buffer.append(scan)
            if len(self._buffer) >= n:
                yield from self._flush()
            return
        yield self._with_rings(scan)

    def _flush(self) -> Iterator[Scan]:
        """Estimate the beam model from the held scans (if not yet), then release them."""
        if not self._buffer:
            return
        if self.beams is None:
            stamps = np.array([s.stamp for s in self._buffer])
            if len(stamps) > 1 and 0.0 < np.median(np.diff(stamps)) < 1.0:
                self._period = float(np.median(np.diff(stamps)))  # the sweep period (s)
            self._estimate_beams(self._buffer)
        held, self._buffer = self._buffer, []
        for scan in held:
            yield self._with_rings(scan)

    # ------------------------------------------------------------------ stamps and skips
    def _skip(self, item: SkippedMessage) -> Iterator[SkippedMessage]:
        """Count a message that cannot be used; one warning per reason (strict: stop)."""
        if self.strict:
            raise InputError(f"message {item.index}: {item.detail} (--strict stops at the first)")
        if self.stats.skipped[item.reason] == 0:
            log.warning(
                "skipping message %d: %s (further '%s' messages are skipped and counted "
                "without a warning)",
                item.index,
                item.detail,
                item.reason,
            )
        self.stats.skipped[item.reason] += 1
        yield item

    def _consume(self, item: Item) -> Iterator[Item]:
        """One input item: a damaged message is skipped; a scan goes on the run's clock."""
        if isinstance(item, SkippedMessage):
            yield from self._skip(item)
            return
        if self._offset:
            item.stamp = float(item.stamp) + self._offset
        yield from self._place(item)

    def _place(self, item: Scan) -> Iterator[Item]:
        """A scan on the run's clock: kept, or held back when not after the last one (until
        the next scan in order, or STAMP_RUN_LIMIT of them show the clock stepped back)."""
        last = self._last
        if last is not None and not float(item.stamp) > last:
            if self.strict:
                yield from self._skip(_out_of_order(item, last))
            self._held_back.append((item, last))
            if len(self._held_back) >= STAMP_RUN_LIMIT:
                yield from self._clock_stepped_back()
            return
        yield from self._settle_held_back()
        yield from self._feed(item)

    def _settle_held_back(self) -> Iterator[SkippedMessage]:
        """The scans held back were out of order: skipped and counted."""
        for scan, last in self._held_back:
            yield from self._skip(_out_of_order(scan, last))
        self._held_back = []

    def _clock_stepped_back(self) -> Iterator[Item]:
        """STAMP_RUN_LIMIT scans in a row not after the last kept one. When their stamps go
        on at the sweep period, the clock stepped back (a PTP/NTP correction, a driver that
        restarted its clock): unless ``source.stamps`` is "header" (stamps exactly as
        recorded), every scan from there on is stamped on the run's clock (the step added,
        one warning), the held scans included. Else, or forced, the run stops (bad input)."""
        run = [scan for scan, _ in self._held_back]
        t = np.array([scan.stamp for scan in run])
        step = np.diff(t)
        steady = bool(np.all(step > 0) and 0.5 < np.median(step) / self._period < 1.5)
        if not steady or self._clock in ("header", "record"):
            raise InputError(self._stamps_gone_wrong(self._held_back[-1][1], steady))
        # the reorder buffer holds the scans recorded before the step (after the last kept
        # one) and maybe some after it: those before go first, as they are
        last = self._last
        held = self._reorder.drain()
        before = [scan for scan in held if scan.stamp > last]
        later = [scan for scan in held if not scan.stamp > last]
        for scan in before:
            yield from self._feed(scan)
        offset = self._last + self._period - float(t[0])
        self._offset += offset
        self._note_clock_step(run[0].index, float(t[0]), offset)
        for scan in later:
            scan.stamp = float(scan.stamp) + self._offset
        for scan in run:
            scan.stamp = float(scan.stamp) + offset
        self._held_back = []
        for scan in sorted(run + later, key=lambda s: s.stamp):
            yield from self._place(scan)

    def _note_clock_step(self, index: int, t0: float, offset: float) -> None:
        """One warning and one source note for a clock step followed at message ``index``."""
        log.warning(
            "the clock of the stamps stepped back by %.3f s at message %d (%.9f s after "
            "%.9f s): this and every later scan is stamped %.3f s later, on the clock of the "
            "scans before (set source.stamps=header to stop instead)",
            offset - self._period, index, t0, self._last, offset,
        )  # fmt: skip
        self.stats.clock_steps.append((index, offset))
        if self._notes is not None:
            self._notes.append(
                f"the clock of the stamps stepped back by {offset - self._period:.3f} s at "
                f"message {index}: the scans from there on are stamped {offset:.3f} s "
                "later than their header stamps"
            )

    def _stamps_gone_wrong(self, last: float, steady: bool) -> str:
        """The message of a run stopped by STAMP_RUN_LIMIT stamps in a row not after ``last``
        (``steady``: they go on at the sweep period, the run was told to keep them as is)."""
        run = [(scan.index, float(scan.stamp)) for scan, _ in self._held_back]
        (i0, t0), (i1, t1) = run[0], run[-1]
        if t0 == t1 == last:
            how = f"all equal the last kept scan's ({last:.9f} s): the stamps are not set?"
        else:
            how = (
                f"all before the last kept scan's ({last:.9f} s; the first one by "
                f"{last - t0:.3f} s): "
            )
            how += (
                f"the clock stepped back and source.stamps={self._clock} takes them as they are."
                if steady
                else "and not at the sweep period: the clock is broken?"
            )
        if self._clock == "record":
            advice = "the bag's record times repeat: try --set source.stamps=header"
        elif steady:
            advice = "--set source.stamps=auto goes on across the step"
        elif self._has_record:
            advice = "use the bag's record time instead: --set source.stamps=record"
        else:
            advice = "give the input increasing stamps"
        return (
            f"the stamps of the last {len(run)} messages ({i0} to {i1}) are {how} Every "
            f"further scan would be dropped, so the run stops here; {advice}"
        )


def _out_of_order(item: Scan, last: float) -> SkippedMessage:
    kind = "duplicated stamp" if item.stamp == last else "stamp out of order"
    detail = (
        f"stamp {item.stamp:.9f} s is not after the previous scan's {last:.9f} s"
        " (dropped: the trajectory is never written out of order)"
    )
    return SkippedMessage(item.index, kind, detail)
