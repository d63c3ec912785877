"""A message or file that cannot become a Scan costs one frame: :class:`FrameError` names why,
:func:`skip` turns it into the ``SkippedMessage`` a reader yields in the Scan's place."""

from __future__ import annotations

from slam.errors import InputError
from slam.types import Scan, SkippedMessage

# Skip reasons (SkippedMessage.reason): short categories the scan stream counts.
CORRUPT_MESSAGE = "corrupt message"
CORRUPT_FILE = "corrupt file"
EMPTY_MESSAGE = "empty message"
EMPTY_FILE = "empty file"
NO_FINITE_POINTS = "no finite points"
ABSURD_POINTS = "absurd coordinates"
BAD_DATATYPE = "bad field datatype"
NO_XYZ = "no x/y/z fields"


class FrameError(InputError):
    """One message/file of an input is unusable; the rest may be fine.

    ``reason`` is one of the categories above. Raised by the decoders, caught by the
    readers (which yield a SkippedMessage), so a direct decoder call still gets an
    InputError with the full explanation.
    """

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def skip(index: int, exc: BaseException, where: str) -> SkippedMessage:
    """The SkippedMessage for ``exc`` raised while reading item ``index`` of ``where``."""
    reason = exc.reason if isinstance(exc, FrameError) else CORRUPT_MESSAGE
    text = str(exc) or type(exc).__name__
    return SkippedMessage(index=index, reason=reason, detail=f"{where}: {text}")


def checked(
    scan: Scan, n_raw: int, where: str, *, empty: str = EMPTY_MESSAGE
) -> Scan | SkippedMessage:
    """``scan``, or a SkippedMessage when it kept no point: ``empty`` when the item had
    none (``n_raw`` == 0), "no finite points" when all ``n_raw`` had a NaN/inf coordinate."""
    if len(scan):
        return scan
    if n_raw == 0:
        return SkippedMessage(scan.index, empty, f"{where}: no points")
    return SkippedMessage(
        scan.index, NO_FINITE_POINTS, f"{where}: all {n_raw} points have a NaN/inf coordinate"
    )
