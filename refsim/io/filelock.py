"""One writer per results file: an exclusive advisory lock beside the file (:class:`FileLock`)."""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

__all__ = ["FileLock", "WriterLockedError"]


class WriterLockedError(FileExistsError):
    """Another process holds the lock of a results file (it is writing it); nothing was touched."""

    def __str__(self) -> str:
        return str(self.strerror)


class FileLock:
    """An exclusive advisory lock (``fcntl.flock``) on ``.<name>.lock`` beside ``path``, for one writer.

    The lock file holds the pid of the holder. Taking it never blocks: a held lock raises
    :class:`WriterLockedError` naming the path and the holder. :meth:`release` unlinks the lock file while
    still holding it; a process that opened the old file meanwhile sees that its inode is no longer the
    path's and tries again, so two processes never both believe they hold the lock.

    Parameters
    ----------
    path : The file the lock protects.
    """

    def __init__(self, path) -> None:
        self.path = Path(path)
        self.lock_path = self.path.with_name(f".{self.path.name}.lock")
        self._fd: int | None = None
        for _ in range(10):
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "unknown"
                os.close(fd)
                raise WriterLockedError(
                    errno.EBUSY,
                    f"{self.path}: another process (pid {holder}) is writing this file (its lock "
                    f"{self.lock_path.name} is held); wait for it to finish or choose another path",
                ) from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
                self._fd = fd
                return
            os.close(fd)  # released and unlinked by its holder meanwhile: take the new one
        raise WriterLockedError(errno.EBUSY, f"{self.path}: cannot take the lock {self.lock_path.name}")

    def release(self) -> None:
        """Unlink the lock file and release the lock (idempotent)."""
        if self._fd is None:
            return
        try:
            self.lock_path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)
            self._fd = None
