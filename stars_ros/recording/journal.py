"""The feedback journal, ``feedback.jsonl`` in the bag: every accepted feedback message as
one line of JSON, fsync'd before it counts as saved, so that a hard kill loses none of it
(``recovery.recover`` puts back what missed the MCAP files).

Entries the disk refused wait in memory, oldest first, and are written again by the next
``save`` or ``retry``. The fsync of a healthy save runs outside the journal's lock, so one
slow disk write never holds up the next message."""
from __future__ import annotations

import contextlib
import json
import os
import threading
from pathlib import Path

JOURNAL = 'feedback.jsonl'


class FeedbackJournal:
    """The journal file of one bag (opened by ``open``, reopened by ``retry`` after a failure)."""

    def __init__(self, path: Path):
        self.path = path
        self._handle = None
        self._waiting: list = []  # accepted entries the disk refused, oldest first
        self._syncing = 0         # entries written whose fsync is under way
        self._lock = threading.Lock()

    @property
    def unsaved(self) -> int:
        """Accepted entries that are not yet safe on disk."""
        with self._lock:
            return len(self._waiting) + self._syncing

    @property
    def healthy(self) -> bool:
        """Open, with nothing waiting for the disk."""
        with self._lock:
            return self._handle is not None and not self._waiting

    def waiting(self) -> list:
        """The entries the disk refused, oldest first."""
        with self._lock:
            return list(self._waiting)

    def open(self) -> None:
        """Open the file to append to (OSError when the disk refuses)."""
        with self._lock:
            if self._handle is None:
                self._handle = open(self.path, 'a')

    def save(self, entry: dict) -> tuple[list, OSError | None]:
        """Journal ``entry`` and, first, any entries waiting for the disk. Returns the
        entries saved by this call, in order, and the error that stopped it (None): an
        entry not saved waits for the next try."""
        with self._lock:
            if self._handle is None or self._waiting:  # the disk is failing: all of them, in order, now
                self._waiting.append(entry)
                return self._retry()
            try:
                descriptor = self._write(entry)
            except OSError as error:
                self._waiting.append(entry)
                return [], error
            self._syncing += 1
        failure = None
        try:
            os.fsync(descriptor)
        except OSError as error:
            failure = error
        finally:
            os.close(descriptor)
        with self._lock:
            self._syncing -= 1
            if failure is not None:
                self._waiting.insert(0, entry)
                return [], failure
        return [entry], None

    def retry(self) -> tuple[list, OSError | None]:
        """Reopen the file if a failure closed it and journal the entries waiting for the
        disk; returns them as ``save`` does."""
        with self._lock:
            return self._retry()

    def close(self) -> None:
        with self._lock:
            if self._handle is not None:
                self._handle.close()
                self._handle = None

    def _retry(self) -> tuple[list, OSError | None]:
        saved = []
        try:
            if self._handle is None:
                self._handle = open(self.path, 'a')
            while self._waiting:
                descriptor = self._write(self._waiting[0])
                try:
                    os.fsync(descriptor)
                finally:
                    os.close(descriptor)
                saved.append(self._waiting.pop(0))
        except OSError as error:
            self._drop_handle()
            return saved, error
        return saved, None

    def _write(self, entry: dict) -> int:
        """Write ``entry``'s line through to the OS; a duplicate of the file's descriptor to
        fsync. On OSError the handle is dropped, to be reopened by the next retry."""
        try:
            self._handle.write(json.dumps(entry) + '\n')
            self._handle.flush()
            return os.dup(self._handle.fileno())
        except OSError:
            self._drop_handle()
            raise

    def _drop_handle(self) -> None:
        if self._handle is not None:
            with contextlib.suppress(OSError):  # its unwritten buffer fails again: the entry waits
                self._handle.close()
            self._handle = None


def read_journal(path: Path) -> list:
    """The entries of a journal file; a line cut by a hard kill was never acknowledged as
    journaled and is passed over."""
    entries = []
    for line in Path(path).read_text().splitlines():
        try:
            entries.append(json.loads(line))
        except ValueError:
            continue
    return entries
