"""Where the disk's part of a forget runs while the node serves (docs/privacy.md).

Erasing a person from the state store and rewriting every bag without them takes seconds to
minutes on a full record folder; on the node's executor, every ranking would wait for it.
``Erasing`` runs those steps on one thread of its own, one at a time in the order they were
asked (two rewrites of one bag never overlap), and hands each outcome back to the executor:
the thread only queues it and calls ``wake``; ``finished`` (called by the executor's
``work``) returns what is done. While a person's erase runs, ``NodeRecords`` leaves out of the
recording every message that names them (``withheld``: the owner of people says who), so the
bag file the erase rotates to holds nothing of them either.
"""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass, field
from typing import Callable


@dataclass
class Erase:
    """One erase: ``run()`` on the erasing thread, then ``then(result, error)`` on the executor."""
    run: Callable[[], dict]
    then: Callable[[dict | None, BaseException | None], None]
    result: dict | None = None
    error: BaseException | None = None
    done: threading.Event = field(default_factory=threading.Event)


class Erasing:
    """One background thread running ``Erase`` jobs in order; see the module docstring."""

    def __init__(self, wake: Callable[[], None]):
        self._wake = wake
        self._jobs = collections.deque()
        self._finished = collections.deque()
        self._condition = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name='stars-erasing', daemon=True)
        self._thread.start()

    def submit(self, erase: Erase) -> Erase:
        with self._condition:
            if self._closed:
                raise RuntimeError('the node is closing: nothing more is erased')
            self._jobs.append(erase)
            self._condition.notify()
        return erase

    def _loop(self):
        while True:
            with self._condition:
                while not self._jobs and not self._closed:
                    self._condition.wait()
                if not self._jobs:
                    return
                erase = self._jobs[0]
            try:
                erase.result = erase.run()
            except BaseException as error:  # noqa: BLE001 - handed to the executor, which reports it
                erase.error = error
            with self._condition:
                self._jobs.popleft()
                self._finished.append(erase)
            erase.done.set()
            self._wake()

    def busy(self) -> bool:
        """True while an erase waits or runs."""
        with self._condition:
            return bool(self._jobs)

    def finished(self) -> list:
        """The erases done since the last call, in order (the executor runs their ``then``)."""
        with self._condition:
            done = list(self._finished)
            self._finished.clear()
        return done

    def close(self, timeout: float) -> bool:
        """Let the erase running finish (up to ``timeout`` s) and start no other: a forget
        waiting has its intent record already (``erasure.record_intent``), so the next start
        finishes it. True when the thread ended."""
        with self._condition:
            self._closed = True
            while len(self._jobs) > 1:  # the first one runs
                self._jobs.pop()
            self._condition.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()
