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
can lose the last commit (``synchronous=FULL`` would also cover that). An interrupted write
is rolled back by SQLite on the next open.

The named file is self-contained after every finished evaluation: each result's commit is
followed by a checkpoint that copies the WAL into the database file, so a copy of the
``.db`` file alone (without ``<study>-wal``), also one taken after a SIGKILL, holds every
finished evaluation — all but the last one if the kill fell inside that evaluation's
checkpoint (a window of a few milliseconds; the ``.db`` with its ``-wal``, which a resume
reads, holds that one too). A checkpoint is two or three ``fsync`` calls (``benchmarks/study_io.py``
measures them against an evaluation). It is passive: while another process is reading the
study it copies what it can, and the next one catches up.

A write that fails (disk full, file-size limit, a folder made read-only) raises
:class:`StudyWriteError`: the transaction is rolled back, every evaluation finished before
stays in the file, and the message says how many and how to resume.

One process at a time: opening a study takes an exclusive, non-blocking ``flock`` on the
database file itself, so deleting a file beside it cannot let a second process in; a second
process gets :class:`StudyInUseError` at once. The OS drops the lock when the holder exits,
however it exits (SIGKILL included), so no stale lock is ever left behind. ``flock`` locks
are independent of the POSIX record locks SQLite takes on the same file on Linux; on systems
where the two kinds interact (the BSDs, macOS) and on Windows (``msvcrt.locking``) the lock
sits on the side file ``<study>.lock`` instead (Windows cannot delete a file held open).

A study remembers the settings it was created with (method, seed, budget, search space,
method options, and the caller's description of the objective, e.g. the dataset and cost of
a tuning problem); resuming with different settings is refused with a :class:`ConfigError`
naming the setting, because the replay could not reproduce the stored proposals. One
exception: a larger budget for a method whose proposals never depend on it
(``Optimizer.budget_independent``: TR-BO, random, the Optuna samplers, CMA-ES) continues a
finished study — the stored evaluations are proposed again as they were, then the run goes
on, exactly as a run started with the larger budget. TSBO and GA plan their run by the
budget and are refused.

:func:`read_study` reads a study without writing to it or taking its lock.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import stat
import sys
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeGuard

from kftune.errors import ConfigError, KftuneError, ObjectiveMismatchError, RunFailedError
from kftune.optim.result import COMPLETE, FAILED, RUNNING, EvalRecord, jsonable

#: Bumped when the table layout changes.
FORMAT_VERSION = 1
_APP = "kftune-study"

#: Whether ``flock`` on the database file leaves SQLite's own (POSIX record) locks on it
#: alone — Linux documents that the two kinds never interact; the BSDs and macOS do not.
_LOCK_THE_DATABASE = sys.platform.startswith("linux")
#: Files SQLite keeps beside a study ``s.db``: ``s.db-wal``, ``s.db-shm``, ``s.db-journal``.
_SIDE_FILES = ("-wal", "-shm", "-journal")


def study_files(path: str | os.PathLike[str]) -> list[Path]:
    """The files of the study ``path``: itself, SQLite's side files beside it and the lock
    file some systems keep there (existing or not)."""
    p = Path(path)
    return [p, *(p.with_name(p.name + e) for e in (*_SIDE_FILES, ".lock"))]


def is_study(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a study file kftune made: a regular file (a FIFO would block the
    open) holding an SQLite database (by its header) whose ``meta`` table names kftune as
    its application. Read without changing the file or creating any beside it (SQLite's
    ``immutable`` mode); a study whose creation is still in its write-ahead log only is
    read through that log."""
    p = Path(path)
    try:
        if not stat.S_ISREG(os.stat(p).st_mode):
            return False
        with open(p, "rb") as fh:
            if fh.read(16) != b"SQLite format 3\x00":
                return False
    except OSError:
        return False
    wal = p.with_name(p.name + "-wal").exists()
    for mode in ("immutable=1", *(("mode=ro",) if wal else ())):
        try:
            uri = f"{p.resolve().as_uri()}?{mode}"
            with contextlib.closing(sqlite3.connect(uri, uri=True)) as conn:
                row = conn.execute("SELECT value FROM meta WHERE key = 'application'").fetchone()
        except (sqlite3.Error, OSError, ValueError):
            continue
        if row is not None and row[0] == _APP:
            return True
    return False


class StudyError(KftuneError):
    """A study file cannot be used as asked (exists without resume, corrupt, …)."""


class StudyInUseError(StudyError):
    """Another process holds the study open."""


class StudyWriteError(StudyError, RunFailedError):
    """Writing to the study failed (disk full, file-size limit, read-only folder); what
    was committed before is kept (a run failure, not bad input: the CLI exits with 1)."""


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
    """Exclusive non-blocking lock on ``path`` (created if absent; released by the OS when
    the process dies; not inherited by forked children)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fh: Any = None

    def acquire(self) -> bool:
        """Take the lock; False if another process holds it.

        Raises:
            OSError: the file cannot be opened for writing.
        """
        if self._held_here():
            return False
        fh = open(self.path, "a+b")  # noqa: SIM115 - kept open while the lock is held
        try:
            if sys.platform == "win32":  # pragma: no cover - exercised on Windows only
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

    def _held_here(self) -> bool:
        """Whether this process holds the lock already. Checked without opening the file:
        closing a second descriptor of it would drop every POSIX lock this process holds
        on it, those of SQLite included."""
        try:
            st = os.stat(self.path)
        except OSError:
            return False
        return any(
            not fh.closed and os.path.samestat(os.fstat(fh.fileno()), st) for fh in list(_HELD)
        )

    def release(self) -> None:
        if self._fh is not None and self._fh.closed:  # a forked child's copy, closed at fork
            self._fh = None
        if self._fh is not None:
            try:
                if sys.platform == "win32":  # pragma: no cover
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
    def open(
        cls,
        path: str | os.PathLike[str],
        settings: dict[str, Any],
        *,
        resume: bool,
        extendable: bool = False,
    ) -> Study:
        """Create a study, or reopen one to resume it.

        Args:
            path: the SQLite file (created if absent).
            settings: ``method``, ``seed``, ``budget``, ``space`` (dict), ``options`` (dict).
            resume: reopen an existing study (an absent file simply starts a new one).
            extendable: the method's proposals do not depend on its budget
                (``Optimizer.budget_independent``), so a resume may ask for a larger budget
                than the stored one: the stored trials are proposed again as they were and
                the run continues after them; the stored budget becomes the new one. Without
                it a larger budget is refused, saying why.

        Raises:
            StudyInUseError: another process has the study open.
            StudyError: the file exists and ``resume`` is False; it is not a kftune study or
                a row is damaged; or it cannot be opened for writing.
            StudyWriteError: the new study cannot be written (disk full, file-size limit).
            ConfigError: resuming with settings other than the stored ones (names the one).
        """
        p = Path(path)
        settings = jsonable(settings)
        # The lock follows the real file, so two paths to one study (a symlink, a relative
        # and an absolute path) share it.
        real = p.resolve()
        created = not real.exists()
        lock = _FileLock(real if _LOCK_THE_DATABASE else real.with_name(real.name + ".lock"))
        try:
            held = lock.acquire()
        except OSError as exc:
            raise StudyError(f"cannot open study {p} for writing: {exc.strerror or exc}") from None
        if not held:
            raise StudyInUseError(
                f"study {p} is in use by another process (it holds the lock on "
                f"{lock.path.name}); wait for it to finish or use another storage file"
            )
        try:
            conn = cls._connect(p, settings, resume=resume, extendable=extendable)
        except BaseException:
            if created:  # nothing finished can be in it: remove what the failed start left
                for leftover in (real, *(real.with_name(real.name + e) for e in _SIDE_FILES)):
                    with contextlib.suppress(OSError):
                        leftover.unlink()
            lock.release()
            raise
        return cls(p, conn, lock, settings)

    @classmethod
    def _connect(
        cls, p: Path, settings: dict[str, Any], *, resume: bool, extendable: bool = False
    ) -> sqlite3.Connection:
        """Open the database, then create the study in it or check the stored settings."""
        existed = p.exists() and p.stat().st_size > 0
        try:
            conn = sqlite3.connect(str(p), isolation_level=None)
        except sqlite3.Error as exc:
            raise StudyError(f"cannot open study {p}: {exc}") from None
        try:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            if existed:
                stored = cls._read_meta(p, conn)
                if not resume:
                    n = conn.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
                    raise StudyError(
                        f"study {p} already exists ({n} evaluations stored); pass "
                        "resume=True to continue it or choose another storage file"
                    )
                _check_settings(p, stored, settings, extendable=extendable)
                if stored.get("budget") != settings.get("budget"):  # a larger one, allowed
                    with _transaction(conn):
                        conn.execute(
                            "UPDATE meta SET value = ? WHERE key = 'settings'",
                            (json.dumps(settings, allow_nan=False, sort_keys=True),),
                        )
            else:
                cls._create(conn, settings)
        except BaseException as exc:
            with contextlib.suppress(sqlite3.Error):
                conn.close()
            if isinstance(exc, sqlite3.OperationalError):  # disk full, read-only, locked
                raise StudyWriteError(f"cannot create or open study {p}: {exc}") from None
            if isinstance(exc, sqlite3.DatabaseError):
                raise StudyError(f"study {p} is not a readable SQLite file: {exc}") from None
            raise
        return conn

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
        try:
            settings = json.loads(meta["settings"])
        except (KeyError, TypeError, ValueError, RecursionError):
            settings = None
        if not isinstance(settings, dict):
            raise StudyError(f"study {p}: its stored settings (table meta) are damaged")
        return settings

    # ------------------------------------------------------------------ rows
    def records(self) -> tuple[list[EvalRecord], list[float] | None]:
        """The stored finished records in order, and the unit-cube point of a trailing
        ``running`` proposal (the one in flight when the previous process stopped), if any.

        Raises:
            StudyError: rows are not numbered 0..n−1, a running row is not the last, or a
                row is damaged (named by its trial number; its content is not quoted).
        """
        done, running = self.rows()
        n = len(done) + len(running)
        for i in running:
            if i != n - 1:
                raise StudyError(f"study {self.path}: running trial {i} is not the last")
        return done, running.get(n - 1)

    def rows(self) -> tuple[list[EvalRecord], dict[int, list[float]]]:
        """The stored finished records in trial order, and the unit-cube points of the
        ``running`` proposals (in flight when the previous process stopped) by trial
        number — anywhere in the study: a batched run has up to a batch of them.

        Raises:
            StudyError: rows are not numbered 0..n−1, or a row is damaged (named by its
                trial number; its content is not quoted).
        """
        try:
            rows = self._conn.execute(
                "SELECT number, state, u, record FROM trials ORDER BY number"
            ).fetchall()
        except sqlite3.DatabaseError as exc:
            raise StudyError(f"study {self.path} cannot be read: {exc}") from None
        return _parse_rows(self.path, rows)

    def write_proposal(self, number: int, u: list[float]) -> None:
        """Store a proposal (state ``running``) before it is evaluated; committed on return.

        Raises:
            StudyWriteError: the write failed (nothing finished is lost).
        """
        self._write(
            f"store proposal {number}",
            "INSERT OR REPLACE INTO trials (number, state, u) VALUES (?, ?, ?)",
            (number, RUNNING, json.dumps(u)),
        )

    def write_result(self, record: EvalRecord) -> None:
        """Store a finished evaluation, committed and copied into the database file on
        return (see the module docstring).

        Raises:
            StudyWriteError: the write failed; this evaluation is evaluated again on resume,
                every one finished before is kept.
            StudyError: no running proposal of this number is stored.
        """
        what = f"store the result of evaluation {record.number} (evaluated again on resume)"
        changed = self._write(
            what,
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
        if changed != 1:
            raise StudyError(f"study {self.path}: no running proposal {record.number} to complete")
        try:
            self._conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
        except sqlite3.Error as exc:
            what = f"copy evaluation {record.number} from the -wal file into the database file"
            raise StudyWriteError(self._write_failure(what, exc)) from None

    def is_finished(self, number: int) -> bool:
        """Whether the result of trial ``number`` is stored (complete or failed)."""
        row = self._conn.execute("SELECT state FROM trials WHERE number = ?", (number,)).fetchone()
        return row is not None and row[0] in (COMPLETE, FAILED)

    def _write(self, what: str, sql: str, params: tuple[Any, ...]) -> int:
        """Run one statement in its own committed transaction; the number of rows changed."""
        try:
            with _transaction(self._conn):
                return self._conn.execute(sql, params).rowcount
        except sqlite3.Error as exc:
            raise StudyWriteError(self._write_failure(what, exc)) from None

    def _write_failure(self, what: str, exc: sqlite3.Error) -> str:
        try:
            n = self._conn.execute(
                "SELECT COUNT(*) FROM trials WHERE state IN (?, ?)", (COMPLETE, FAILED)
            ).fetchone()[0]
            kept = f"it keeps the {n} evaluations finished so far"
        except sqlite3.Error:
            kept = "it keeps the evaluations finished so far"
        return (
            f"study {self.path}: cannot {what} ({exc}); {kept}; make room on the disk "
            "(or make the folder writable), then run the same command again with the option "
            "--resume to continue the study"
        )

    def close(self) -> None:
        """Close the database and release the lock (idempotent)."""
        if self._conn is not None:
            with contextlib.suppress(sqlite3.Error):  # e.g. a checkpoint on a full disk
                self._conn.close()
            self._conn = None  # type: ignore[assignment]  # closed: nothing reads it again
        self._lock.release()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class StoredStudy:
    """What a study file holds, read without changing it (:func:`read_study`).

    Attributes:
        path: the SQLite file.
        settings: ``method``, ``seed``, ``budget``, ``space`` (``{"params": [{name, low,
            high, scale}, …]}``), ``options``, ``objective`` (and ``batch``), as stored.
        records: the finished evaluations (complete or failed), in trial order.
        running: the trial numbers stored as ``running`` (in flight when its process
            stopped, or still running in another process).
    """

    path: Path
    settings: dict[str, Any]
    records: list[EvalRecord]
    running: list[int]


def read_study(path: str | os.PathLike[str]) -> StoredStudy:
    """Read a study without writing to it or taking its lock: a study that a ``tune`` run
    holds open can be looked at while it runs. Opened read-only through its write-ahead
    log where one lies beside it (it may hold the newest evaluations), otherwise as
    immutable (nothing is created beside it, also in a read-only folder).

    Raises:
        StudyError: the file is missing, not a regular file, not a kftune study, of another
            format version, or a row is damaged (named by its trial number).
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except OSError as exc:
        raise StudyError(f"study {p}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise StudyError(f"study {p}: is not a regular file (expected a kftune study file)")
    if not is_study(p):
        raise StudyError(
            f"{p} is not a kftune study (expected the SQLite file that tune --storage writes)"
        )
    wal = p.with_name(p.name + "-wal").exists()
    uri = f"{p.resolve().as_uri()}?{'mode=ro' if wal else 'immutable=1'}"
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True)) as conn:
            settings = Study._read_meta(p, conn)
            rows = conn.execute(
                "SELECT number, state, u, record FROM trials ORDER BY number"
            ).fetchall()
    except sqlite3.Error as exc:
        raise StudyError(f"study {p} cannot be read: {exc}") from None
    done, running = _parse_rows(p, rows)
    return StoredStudy(path=p, settings=settings, records=done, running=sorted(running))


def _parse_rows(
    path: Path, rows: list[tuple[Any, ...]]
) -> tuple[list[EvalRecord], dict[int, list[float]]]:
    """The finished records and the running proposals of a study's ``trials`` rows
    ``(number, state, u, record)`` in trial order (see :meth:`Study.rows`)."""
    done: list[EvalRecord] = []
    running: dict[int, list[float]] = {}
    for i, (number, state, u, record) in enumerate(rows):
        if number != i:
            raise StudyError(f"study {path}: trial numbers have a gap at {i}")
        if state not in (RUNNING, COMPLETE, FAILED):
            raise StudyError(f"study {path}: trial {i} has an unknown state")
        try:
            if state == RUNNING:
                running[i] = [float(v) for v in json.loads(u)]
            else:
                rec = EvalRecord.from_dict(json.loads(record))
                if rec.number != i or rec.state != state:
                    raise ValueError("the record disagrees with its row")
                done.append(rec)
        except (
            TypeError,
            ValueError,
            KeyError,
            AttributeError,
            ArithmeticError,
            RecursionError,
        ):
            column = "u" if state == RUNNING else "record"
            raise StudyError(
                f"study {path}: trial {i} ({state}) is damaged: column {column!r} "
                "does not hold what kftune wrote there; resume from an intact copy of the "
                "study or start a new one"
            ) from None
    return done, running


class _transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT`` on an autocommit connection; rolled back when the
    body or the commit fails (a failed rollback — SQLite may have rolled back already — is
    not an error of its own)."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self.conn = conn

    def __enter__(self) -> None:
        self.conn.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            try:
                self.conn.execute("COMMIT")
                return
            except sqlite3.Error:
                self._rollback()
                raise
        self._rollback()

    def _rollback(self) -> None:
        with contextlib.suppress(sqlite3.Error):
            self.conn.execute("ROLLBACK")


def _check_settings(
    p: Path, stored: dict[str, Any], current: dict[str, Any], *, extendable: bool = False
) -> None:
    """Refuse to resume with other settings, naming the first that differs (inside the
    method's options: the option). A larger budget passes where ``extendable``; elsewhere
    it is refused with the reason (the method plans its run by the budget)."""
    for key in sorted(set(stored) | set(current)):
        old, new = stored.get(key), current.get(key)
        if old == new or (key == "objective" and _same_objective(old, new)):
            continue
        if key == "budget" and _is_count(old) and _is_count(new) and new > old:
            if extendable:
                continue
            raise ConfigError(
                f"study {p} was created with budget {old}, and its method "
                f"{stored.get('method')!r} plans its run by the budget (how long each stage "
                f"or generation lasts), so with budget {new} it would not propose the stored "
                f"evaluations again; resume it with budget {old}, or start a new study for "
                f"budget {new} (the methods whose proposals do not depend on the budget — "
                "trbo, random, optuna-tpe, optuna-gp, cma — can be continued so)"
            )
        if key == "options" and isinstance(old, dict) and isinstance(new, dict):
            sub = next(k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k))
            key, old, new = f"{key}.{sub}", old.get(sub, "(not set)"), new.get(sub, "(not set)")
        if (
            isinstance(old, dict)
            and isinstance(new, dict)
            and "summary" in old
            and "summary" in new
        ):
            # an objective's fingerprint: what it is, not its hash
            raise ObjectiveMismatchError(
                f"study {p} was created for another {key}: {old['summary']}; this run's is "
                f"{new['summary']}"
                + ("" if old["summary"] != new["summary"] else " (the data differ)")
                + "; resume it on the same data, cost and model, or use another storage file",
                stored=old["summary"],
                current=new["summary"],
                dataset=old.get("dataset"),
            )
        raise ConfigError(
            f"study {p} was created with {key} = {json.dumps(old, ensure_ascii=False)}, but "
            f"this run asks for {key} = {json.dumps(new, ensure_ascii=False)}; resume it with "
            "the same settings or use another storage file"
        )


#: Keys of a study's objective that describe it without being part of it: the dataset's
#: name and where it was read (a dataset moved elsewhere is the same objective).
OBJECTIVE_NOTES = ("dataset",)


def _same_objective(old: Any, new: Any) -> bool:
    """Whether two objectives are equal but for :data:`OBJECTIVE_NOTES` (a study made before
    the dataset was recorded resumes with a run that records it)."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        return False
    drop = set(OBJECTIVE_NOTES)
    return {k: v for k, v in old.items() if k not in drop} == {
        k: v for k, v in new.items() if k not in drop
    }


def _is_count(v: Any) -> TypeGuard[int]:
    """Whether ``v`` is an evaluation count (an int, not a bool)."""
    return isinstance(v, int) and not isinstance(v, bool)
