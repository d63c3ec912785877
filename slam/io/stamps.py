"""Which clock stamps a scan, and the small reorder buffer of the scan stream (slam.io.stream).

A bag has two clocks per message: the header stamp the driver wrote (when the sweep was
taken) and the record time (when the recorder got it; the order AnyReader plays messages
back in). The header stamp is the right one, when it can be trusted. ``source.stamps``:

- ``header``: always the header stamp; ``record``: always the record time (bags only);
- ``auto``: the header stamp, unless over the first :data:`PROBE` messages fewer than 3 in
  4 of them would come out in order through the reorder buffer (stamps running backwards,
  all equal, jumping about); then the record time, with one note saying so. When neither
  clock increases, InputError says what is wrong and what to do.

The reorder buffer (:func:`reorder`) holds a few scans ordered by stamp, so that messages
recorded slightly out of order (two scans swapped by the recorder) are put back in order
instead of being dropped.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from slam.errors import InputError
from slam.types import Scan, SkippedMessage

log = logging.getLogger(__name__)

PROBE = 10  # messages whose stamps decide the clock in "auto" mode
MIN_IN_ORDER = 0.75  # share of the probed messages that must come out in order


def kept_in_order(stamps: Iterable[float], window: int) -> int:
    """How many of ``stamps`` (in arrival order) a reorder buffer holding ``window`` of them
    lets through in strictly increasing order (the scan stream drops the others)."""
    heap: list[float] = []
    kept, last = 0, -np.inf

    def emit(t: float) -> None:
        nonlocal kept, last
        if t > last:
            kept, last = kept + 1, t

    for t in stamps:
        heapq.heappush(heap, float(t))
        if len(heap) > window:
            emit(heapq.heappop(heap))
    while heap:
        emit(heapq.heappop(heap))
    return kept


def _pattern(stamps: np.ndarray, unset: str = "") -> str:
    """A few words on how a non-increasing stamp sequence goes (for the messages)."""
    d = np.diff(stamps)
    if np.all(d == 0):
        return f"are all {stamps[0]:.9f} s{unset}"
    if np.all(d <= 0):
        return f"run backwards ({stamps[0]:.3f} s down to {stamps[-1]:.3f} s)"
    return (
        f"jump back and forth ({int(np.sum(d > 0))} steps forward, "
        f"{int(np.sum(d <= 0))} back or repeated)"
    )


def choose_clock(
    header: np.ndarray, record: np.ndarray | None, window: int, where: str
) -> tuple[str, str | None]:
    """The clock ``auto`` uses from the first messages' ``header`` stamps and ``record``
    times (None: the input has no record time): ("header" | "record", a note or None);
    a switch to the record time is logged as one warning.

    Raises InputError when neither clock increases over them.
    """
    header = np.asarray(header, dtype=float)
    n = len(header)
    if n < 3:  # too few to tell
        return "header", None
    need = int(np.ceil(MIN_IN_ORDER * n))
    if kept_in_order(header, window) >= need:
        return "header", None
    unset = " (the driver does not set them?)"
    what = f"the header stamps of the first {n} messages of {where} {_pattern(header, unset)}"
    if record is not None:
        record = np.asarray(record, dtype=float)
        if kept_in_order(record, window) >= need:
            log.warning(
                "%s: the scans are stamped with the bag's record time instead (set "
                "source.stamps to header or record to choose)",
                what,
            )
            return "record", f"scans stamped with the bag's record time: {what}"
        raise InputError(
            f"{what}, and the bag's record times {_pattern(record)}: neither clock can "
            "order the scans. Rewrite the bag with increasing header stamps, or force one "
            "clock with --set source.stamps=header (or record)"
        )
    raise InputError(
        f"{what} and this input has no other clock: the scans cannot be ordered. "
        "Give it increasing stamps (e.g. a KITTI times.txt in recording order)"
    )


def with_clock(
    items: Iterable[tuple[Scan | SkippedMessage, float | None]],
    mode: str,
    window: int,
    where: str,
    on_note: Callable[[str], None] | None = None,
) -> Iterator[Scan | SkippedMessage]:
    """``items`` ((scan or skipped message, record time s or None)) with each scan stamped by
    the clock ``mode`` picks ("header", "record" or "auto": decided on the first
    :data:`PROBE` scans, see the module doc); the note of an "auto" switch goes to
    ``on_note``."""
    it = iter(items)
    head: list[tuple[Scan | SkippedMessage, float | None]] = []
    clock = mode
    cut: InputError | None = None  # the input ended in an error while probing
    if mode == "auto":
        n_scans = 0
        try:
            for pair in it:
                head.append(pair)
                n_scans += isinstance(pair[0], Scan)
                if n_scans >= PROBE:
                    break
        except InputError as exc:  # a bag cut before PROBE scans: keep the scans read
            cut, it = exc, iter(())
        probe = [(s.stamp, r) for s, r in head if isinstance(s, Scan)]
        record = [r for _, r in probe]
        clock, note = choose_clock(
            np.array([h for h, _ in probe]),
            None if any(r is None for r in record) else np.array(record),
            window,
            where,
        )
        if note and on_note is not None:
            on_note(note)
    for source in (head, it):
        for item, rec in source:
            if clock == "record" and isinstance(item, Scan):
                if rec is None:
                    raise InputError(
                        f"{where} has no record time: source.stamps=record needs a bag"
                    )
                item.stamp = float(rec)
            yield item
    if cut is not None:
        raise cut


class Reorder:
    """``items`` with up to ``window`` scans held back and released in stamp order (the
    earliest when the buffer is full, all at the end): scans recorded up to ``window``
    places out of order come out in order. A held scan that more than ``window`` later
    recorded scans overtake (each after the previous one let out) has a stamp ahead of its
    time (one glitched stamp): it is released as a SkippedMessage "stamp out of order"
    instead of sitting in the buffer to the end. Skipped messages pass at once. An
    InputError of the input (a truncated bag) first releases the scans held, then
    propagates; a consumer that stops on its own takes the scans still held with
    :meth:`drain`."""

    def __init__(self, items: Iterable[Scan | SkippedMessage], window: int) -> None:
        self.items, self.window = items, window
        self._heap: list[tuple[float, int, Scan]] = []
        self._overtaken: dict[int, int] = {}  # seq of a held scan -> later scans released
        self._last = -np.inf  # the stamp of the last scan released in order

    def drain(self) -> list[Scan]:
        """The scans still held, in stamp order (the buffer is empty afterwards)."""
        return [heapq.heappop(self._heap)[2] for _ in range(len(self._heap))]

    def _release(self) -> Iterator[Scan | SkippedMessage]:
        """The earliest held scan, and any held scan overtaken too often (skipped)."""
        t, seq, scan = heapq.heappop(self._heap)
        yield scan
        if not t > self._last:
            return  # the scan stream drops it: it overtakes nothing
        self._last = t
        ahead = []
        for entry in self._heap:
            if entry[1] < seq:
                n = self._overtaken[entry[1]] = self._overtaken.get(entry[1], 0) + 1
                if n > self.window:
                    ahead.append(entry)
        for entry in ahead:
            self._heap.remove(entry)
            self._overtaken.pop(entry[1], None)
            yield SkippedMessage(
                entry[2].index,
                "stamp out of order",
                f"stamp {entry[0]:.9f} s is ahead of the {self.window + 1} scans recorded "
                f"after it (up to {t:.9f} s): a glitch of the clock? (dropped)",
            )
        if ahead:
            heapq.heapify(self._heap)

    def __iter__(self) -> Iterator[Scan | SkippedMessage]:
        if self.window <= 0:
            yield from self.items
            return
        heap, seq = self._heap, 0
        try:
            for item in self.items:
                if not isinstance(item, Scan):
                    yield item
                    continue
                heapq.heappush(heap, (float(item.stamp), seq, item))
                seq += 1
                if len(heap) > self.window:
                    yield from self._release()
        except InputError:
            while heap:
                yield heapq.heappop(heap)[2]
            raise
        while heap:
            yield heapq.heappop(heap)[2]
