"""Progress bars for long work, always on stderr so stdout stays parseable."""

from __future__ import annotations

import sys
from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, unit: str = "it") -> Iterable[T]:
    """Wrap ``iterable`` in a tqdm bar on stderr.

    ``disable=None`` lets tqdm hide the bar when stderr is not a terminal
    (CI logs, pipes), so logs do not fill with carriage returns.
    """
    return tqdm(iterable, desc=desc, total=total, unit=unit, file=sys.stderr, disable=None, leave=False)


def stage_bar(total: int, desc: str) -> tqdm:
    """A bar advanced by hand (``bar.update()``) over the stages of a command; use as a context manager."""
    return tqdm(total=total, desc=desc, unit="stage", file=sys.stderr, disable=None, leave=False)
