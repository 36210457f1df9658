"""Files written so that a crash leaves the old version or the new one, never half of one."""
from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path
from typing import BinaryIO, Callable


def atomic_write(path, write: Callable[[BinaryIO], object]) -> None:
    """Replace ``path`` with what ``write(handle)`` writes to a binary handle: into a
    temporary file beside it, fsync'd, renamed over ``path``, then the folder fsync'd so
    the rename survives a power loss too. The temporary name is this process's and
    thread's, so concurrent writers of one path never share one. OSError when the disk
    refuses; ``path`` is then as it was."""
    path = Path(path)
    temporary = path.with_name(f'{path.name}.{os.getpid()}.{threading.get_ident()}.tmp')
    try:
        with open(temporary, 'wb') as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
