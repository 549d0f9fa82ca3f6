"""Persistent studies: every proposal and every result of a run in one SQLite file.

Write protocol (what makes a run survive SIGKILL):

1. before an evaluation starts, its proposal is inserted with state ``running`` and the
   transaction is committed;
2. when the result arrives the row is updated to ``complete``/``failed`` and committed
   before the optimiser is asked for the next point.

SQLite commits are atomic, so a process killed at any instant leaves the file with a prefix
of finished rows plus at most one ``running`` row. The database runs in WAL mode with
``synchronous=NORMAL``: a committed transaction survives the process being killed at any
moment (the WAL is in the OS's hands once the commit returns); only an OS crash or power cut
can lose the last commits (``synchronous=FULL`` would also cover that, at about 1.5 ms per
commit instead of 0.03 ms — two commits per evaluation). An interrupted write is rolled back
by SQLite on the next open.

One process at a time: opening a study takes an exclusive, non-blocking ``flock`` on the
side file ``<study>.lock``; a second process gets :class:`StudyInUseError` at once. The OS
drops the lock when the holder exits, however it exits (SIGKILL included), so no stale lock
is ever left behind. (On Windows ``msvcrt.locking`` plays the same role.)

A study remembers the settings it was created with (method, seed, budget, search space,
method options, and the caller's description of the objective, e.g. the dataset and cost of
a tuning problem); resuming with different settings is refused with a :class:`ConfigError`
naming the setting, because the replay could not reproduce the stored proposals.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import weakref
from pathlib import Path
from typing import Any

from kftune.errors import ConfigError, KftuneError
from kftune.optim.result import COMPLETE, FAILED, RUNNING, EvalRecord, jsonable

#: Bumped when the table layout changes.
FORMAT_VERSION = 1
_APP = "kftune-study"


class StudyError(KftuneError):
    """A study file cannot be used as asked (exists without resume, corrupt, …)."""


class StudyInUseError(StudyError):
    """Another process holds the study open."""


#: Open lock files of this process (weakly: a study dropped without close() still frees its
#: lock when it is collected); a forked child closes its copies (see below).
_HELD: weakref.WeakSet[Any] = weakref.WeakSet()


def _close_inherited_locks() -> None:  # pragma: no cover - runs in forked children
    """After ``fork``: close the child's copies of the lock files. ``flock`` belongs to the
    open file description, which the parent keeps, so its lock stays held; but a child that
    outlives a killed parent (an evaluation worker) no longer keeps the study locked."""
    for fh in list(_HELD):
        with contextlib.suppress(OSError):
            fh.close()
    _HELD.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_inherited_locks)


class _FileLock:
    """Exclusive non-blocking lock on ``path`` (released by the OS when the process dies;
    not inherited by forked children)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: Any = None

    def acquire(self) -> bool:
        fh = open(self.path, "a+b")  # noqa: SIM115 - kept open while the lock is held
        try:
            if os.name == "nt":  # pragma: no cover - exercised on Windows only
                import msvcrt

                fh.seek(0)
                msvcrt.locking(fh.fileno(), msvcrt.LK_NBLCK, 1)
            else:
                import fcntl

                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            return False
        self._fh = fh
        _HELD.add(fh)
        return True

    def release(self) -> None:
        if self._fh is not None and self._fh.closed:  # a forked child's copy, closed at fork
            self._fh = None
        if self._fh is not None:
            try:
                if os.name == "nt":  # pragma: no cover
                    import msvcrt

                    self._fh.seek(0)
                    msvcrt.locking(self._fh.fileno(), msvcrt.LK_UNLCK, 1)
                else:
                    import fcntl

                    fcntl.flock(self._fh.fileno(), fcntl.LOCK_UN)
            finally:
                _HELD.discard(self._fh)
                self._fh.close()
                self._fh = None


class Study:
    """An open study file. Use :meth:`open`; close with :meth:`close` (or ``with``).

    Attributes:
        path: the SQLite file.
        settings: what the study was created with (``method``, ``seed``, ``budget``,
            ``space``, ``options``), JSON-normalised.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, lock: _FileLock, settings: dict):
        self.path = path
        self._conn = conn
        self._lock = lock
        self.settings = settings

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, path: str | os.PathLike[str], settings: dict[str, Any], *, resume: bool) -> Study:
        """Create a study, or reopen one to resume it.

        Args:
            path: the SQLite file (created if absent).
            settings: ``method``, ``seed``, ``budget``, ``space`` (dict), ``options`` (dict).
            resume: reopen an existing study (an absent file simply starts a new one).

        Raises:
            StudyInUseError: another process has the study open.
            StudyError: the file exists and ``resume`` is False; or it is not a kftune study.
            ConfigError: resuming with settings other than the stored ones (names the one).
        """
        p = Path(path)
        settings = jsonable(settings)
        # The lock sits beside the real file, so two paths to one study (a symlink, a
        # relative and an absolute path) share it.
        real = p.resolve()
        lock = _FileLock(real.with_name(real.name + ".lock"))
        if not lock.acquire():
            raise StudyInUseError(
                f"study {p} is in use by another process (lock {lock.path.name} is held); "
                "wait for it to finish or use another storage file"
            )
        try:
            existed = p.exists() and p.stat().st_size > 0
            try:
                conn = sqlite3.connect(str(p), isolation_level=None)
                conn.execute("PRAGMA journal_mode=WAL")
                conn.execute("PRAGMA synchronous=NORMAL")
            except sqlite3.DatabaseError as exc:
                raise StudyError(f"study {p} is not a readable SQLite file: {exc}") from None
            try:
                if existed:
                    stored = cls._read_meta(p, conn)
                    if not resume:
                        n = conn.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
                        raise StudyError(
                            f"study {p} already exists ({n} evaluations stored); pass "
                            "resume=True to continue it or choose another storage file"
                        )
                    _check_settings(p, stored, settings)
                else:
                    cls._create(conn, settings)
            except BaseException:
                conn.close()
                raise
        except BaseException:
            lock.release()
            raise
        return cls(p, conn, lock, settings)

    @staticmethod
    def _create(conn: sqlite3.Connection, settings: dict[str, Any]) -> None:
        with _transaction(conn):
            conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute(
                "CREATE TABLE trials ("
                " number INTEGER PRIMARY KEY,"
                " state TEXT NOT NULL,"
                " u TEXT NOT NULL,"
                " value REAL,"
                " reason TEXT,"
                " record TEXT)"
            )
            conn.executemany(
                "INSERT INTO meta VALUES (?, ?)",
                [
                    ("application", _APP),
                    ("format_version", str(FORMAT_VERSION)),
                    ("settings", json.dumps(settings, allow_nan=False, sort_keys=True)),
                ],
            )

    @staticmethod
    def _read_meta(p: Path, conn: sqlite3.Connection) -> dict[str, Any]:
        try:
            meta = dict(conn.execute("SELECT key, value FROM meta").fetchall())
            conn.execute("SELECT number, state, u, value, reason, record FROM trials LIMIT 1")
        except sqlite3.DatabaseError as exc:
            raise StudyError(f"{p} is not a kftune study ({exc})") from None
        if meta.get("application") != _APP:
            raise StudyError(f"{p} is not a kftune study (meta.application missing)")
        if meta.get("format_version") != str(FORMAT_VERSION):
            raise StudyError(
                f"study {p} has format version {meta.get('format_version')}, this kftune "
                f"reads version {FORMAT_VERSION}"
            )
        return json.loads(meta["settings"])

    # ------------------------------------------------------------------ rows
    def records(self) -> tuple[list[EvalRecord], list[float] | None]:
        """The stored finished records in order, and the unit-cube point of a trailing
        ``running`` proposal (the one in flight when the previous process stopped), if any.

        Raises:
            StudyError: rows are not numbered 0..n−1 or a running row is not the last.
        """
        rows = self._conn.execute(
            "SELECT number, state, u, record FROM trials ORDER BY number"
        ).fetchall()
        done: list[EvalRecord] = []
        running: list[float] | None = None
        for i, (number, state, u, record) in enumerate(rows):
            if number != i:
                raise StudyError(f"study {self.path}: trial numbers have a gap at {i}")
            if state == RUNNING:
                if i != len(rows) - 1:
                    raise StudyError(f"study {self.path}: running trial {i} is not the last")
                running = json.loads(u)
            elif state in (COMPLETE, FAILED):
                done.append(EvalRecord.from_dict(json.loads(record)))
            else:
                raise StudyError(f"study {self.path}: trial {i} has unknown state {state!r}")
        return done, running

    def write_proposal(self, number: int, u: list[float]) -> None:
        """Store a proposal (state ``running``) before it is evaluated; committed on return."""
        with _transaction(self._conn):
            self._conn.execute(
                "INSERT OR REPLACE INTO trials (number, state, u) VALUES (?, ?, ?)",
                (number, RUNNING, json.dumps(u)),
            )

    def write_result(self, record: EvalRecord) -> None:
        """Store a finished evaluation; committed on return."""
        with _transaction(self._conn):
            cur = self._conn.execute(
                "UPDATE trials SET state = ?, value = ?, reason = ?, record = ? "
                "WHERE number = ? AND state = ?",
                (
                    record.state,
                    record.value,
                    record.reason,
                    json.dumps(record.to_dict(), allow_nan=False),
                    record.number,
                    RUNNING,
                ),
            )
            if cur.rowcount != 1:
                raise StudyError(
                    f"study {self.path}: no running proposal {record.number} to complete"
                )

    def close(self) -> None:
        """Close the database and release the lock (idempotent)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None  # type: ignore[assignment]
        self._lock.release()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT`` (rolled back on error) on an autocommit connection."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self.conn = conn

    def __enter__(self) -> None:
        self.conn.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self.conn.execute("ROLLBACK" if exc_type is not None else "COMMIT")


def _check_settings(p: Path, stored: dict[str, Any], current: dict[str, Any]) -> None:
    for key in sorted(set(stored) | set(current)):
        if stored.get(key) != current.get(key):
            raise ConfigError(
                f"study {p} was created with {key} = {json.dumps(stored.get(key))}, but this "
                f"run asks for {key} = {json.dumps(current.get(key))}; resume it with the "
                "same settings or use another storage file"
            )
