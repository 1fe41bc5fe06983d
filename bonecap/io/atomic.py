"""Write-then-rename helpers so that a failed write leaves nothing behind."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; move it onto ``target`` on success.

    Parameters
    ----------
    target : path-like
        The final file (or folder, with ``directory=True``).
    directory : bool
        Yield a fresh empty temporary folder instead of a file path.

    Yields
    ------
    pathlib.Path
        Where the caller writes. On an exception it is removed and the
        exception propagates; ``target`` is untouched.

    Notes
    -----
    The temporary lives in the target's own folder so the final
    :func:`os.replace` is a rename on the same file system, which is atomic
    for files. A folder target that already exists is replaced as a whole.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{target.name}."
    if directory:
        tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=target.parent))
    else:
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=".tmp" + target.suffix, dir=target.parent)
        os.close(fd)
        tmp = Path(name)
    try:
        yield tmp
        # mkstemp/mkdtemp create 0600 files and 0700 folders; give the output
        # the permissions a plain open() or mkdir() would have given it.
        mask = os.umask(0)
        os.umask(mask)
        if tmp.exists():
            os.chmod(tmp, (0o777 if directory else 0o666) & ~mask)
        if directory:
            if target.exists():
                shutil.rmtree(target)
            os.replace(tmp, target)
        else:
            os.replace(tmp, target)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise
