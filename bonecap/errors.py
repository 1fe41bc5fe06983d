"""Exception hierarchy.

Every error that bonecap raises on purpose derives from :class:`BonecapError`,
so the CLI can turn it into one line, ``bonecap: error: PATH: what is wrong``,
and exit with code 1, while a genuine bug still shows its traceback.
"""

from __future__ import annotations

import os


class BonecapError(Exception):
    """Root of bonecap's errors.

    Parameters
    ----------
    message : str
        What is wrong, in one line, without the path.
    path : str or os.PathLike, optional
        The file or folder the problem is about; shown first in the message.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        self.message = message
        self.path = None if path is None else os.fspath(path)
        super().__init__(f"{self.path}: {message}" if self.path else message)


class InputError(BonecapError):
    """The input cannot be used: missing, unreadable, or of the wrong kind."""


class FormatError(InputError):
    """A file is not a valid instance of the format its name or content claims."""


class DataError(InputError):
    """A file is readable but its content is inconsistent (a missing slice, uneven spacing...)."""


class OutputError(BonecapError):
    """An output could not be written."""
