"""The scan stream (slam/io/stream.py): clean scans in stamp order, skips counted."""

from __future__ import annotations

import numpy as np
import pytest

from slam.config import SourceConfig
from slam.errors import InputError
from slam.io.stream import ScanStream
from slam.types import Scan, SkippedMessage


def _scan(i: int, t: float) -> Scan:
    return Scan(stamp=t, xyz=np.zeros((1, 3)), index=i)


def _items():
    """Stamps 0.0..0.9 s; message 3 damaged, 5 and 6 swapped, 8 a duplicate of 7's stamp."""
    stamps = [0.0, 0.1, 0.2, None, 0.4, 0.6, 0.5, 0.7, 0.7, 0.9]
    out = []
    for i, t in enumerate(stamps):
        out.append(SkippedMessage(i, "corrupt message", "x") if t is None else _scan(i, t))
    return out


def test_the_stream_yields_clean_scans_and_counted_skips():
    stream = ScanStream(_items(), SourceConfig())
    out = list(stream)
    scans = [s for s in out if isinstance(s, Scan)]
    skipped = [s for s in out if isinstance(s, SkippedMessage)]
    assert [s.stamp for s in scans] == [0.0, 0.1, 0.2, 0.4, 0.5, 0.6, 0.7, 0.9]
    assert sorted(s.reason for s in skipped) == ["corrupt message", "duplicated stamp"]
    assert dict(stream.stats.skipped) == {"corrupt message": 1, "duplicated stamp": 1}
    assert stream.beams is False  # one-point scans: no beam model, the run goes on


def test_start_max_frames_stop_and_strict():
    assert [s.index for s in ScanStream(_items(), SourceConfig(), start=4, max_frames=3)
            if isinstance(s, Scan)] == [4, 6, 5]  # fmt: skip
    seen: list[int] = []
    stream = ScanStream(_items(), SourceConfig(reorder_window=0, beam_scans=0))
    out = list(stream.items(stop=lambda: len(seen) >= 2, on_message=seen.append))
    assert seen == [1, 2] and [s.index for s in out] == [0, 1]
    with pytest.raises(InputError, match="message 3: x"):
        list(ScanStream(_items(), SourceConfig(), strict=True))
