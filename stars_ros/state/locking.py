"""One process holds a state store: ``state.lock`` in the record folder is flock'd while the
store is open and names its holder, so a second store on the folder is refused naming it."""
from __future__ import annotations

import fcntl
import os
import socket
from pathlib import Path

from stars_ros.errors import StoreLockedError

LOCK_FILE = 'state.lock'


def holder_text() -> str:
    return f'pid {os.getpid()} on {socket.gethostname()}'


def hold(folder: Path, holder: str):
    """The open lock file of ``folder``, flock'd and naming ``holder``; StoreLockedError
    naming the other holder when another process holds it."""
    handle = open(folder / LOCK_FILE, 'a+')
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        other = handle.read().strip() or 'another process'
        handle.close()
        raise StoreLockedError(f'the state store in {folder} is held by {other}: one store per node; '
                               'give this node its own record_folder (the default is named after the '
                               'node)') from None
    except OSError:
        handle.close()
        raise
    handle.seek(0)
    handle.truncate()
    handle.write(holder + '\n')
    handle.flush()
    return handle
