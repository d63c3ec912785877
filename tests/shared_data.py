"""Where the real recordings of ``../shared/data`` are, relative to this repository.

Tests that need them call :func:`shared_path`; a missing file fails the test loudly
(never a skip: CI always has ``shared/`` beside the clone).
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """``../shared/data/<parts>``; fails the calling test when it does not exist."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.fail(
            f"real test data missing: {path} (expected ../shared/data beside the repository)",
            pytrace=False,
        )
    return path
