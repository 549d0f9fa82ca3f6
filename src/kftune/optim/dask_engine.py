"""Evaluate on a Dask cluster (``dask.distributed``; the ``dask`` extra).

::

    with DaskEngine(problem, workers=4) as engine:            # a LocalCluster of processes
        result = kftune.minimize(problem, problem.space, execution=Execution(engine=engine))
    DaskEngine(problem, scheduler="tcp://10.0.0.5:8786")      # an existing cluster

What travels where
    The objective (a :class:`~kftune.tuning.problem.TuningProblem` holds the manoeuvres) is
    scattered to every worker once, with ``broadcast=True``, when the engine starts; a task
    then carries only a point (d floats) and, when a batch is split across manoeuvres, a
    list of manoeuvre indices; it returns a float, or a few numbers per manoeuvre.

How work is split
    One task per candidate point when the batch has at least as many points as the cluster
    has worker threads; otherwise (a tuning problem only) each point's manoeuvres are split
    into ``threads // points`` balanced chunks, one task each, and the client pools the
    chunks' scores in manoeuvre order exactly as :meth:`TuningProblem.evaluate` does — so
    the cost is the sequential one bit for bit, however the work was split.

Workers that die
    A task whose worker dies (killed, out of memory, a segfault in the objective) is sent
    again, at most ``retries`` times; then the point is recorded as failed with the reason
    and the run goes on. On a :class:`LocalCluster` this engine starts, the scheduler hands
    such a task back at the first death (``allowed-failures = 0``) so that ``retries`` is the
    whole bound; an external scheduler first applies its own ``allowed-failures`` (Dask's
    default: 3 further attempts) before this engine's retries.

A scheduler that is lost
    A run whose scheduler goes away (killed, its machine gone) raises
    :class:`SchedulerLostError` as soon as the client sees the connection close (it
    cancels every task in flight then: those points are not failed evaluations); every
    evaluation finished before is in the study, which a later run resumes.

What is trusted
    distributed's client allocates whatever length the first 8 bytes from the scheduler
    announce (junk on the port asked for 3 EiB). Before a ``tcp://`` address is handed to
    it, the engine reads the scheduler's first message itself, with a bound
    (:func:`_preflight`). distributed's log lines are silenced while the engine runs: what
    matters reaches the caller as an error or as a failed evaluation's reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from kftune.errors import ConfigError
from kftune.optim.engine import Engine, EngineLostError, Outcome, describe, evaluate_point

#: [s] how long connecting to a scheduler, and waiting for its first worker, may take.
CONNECT_TIMEOUT = 10.0
#: Re-submissions of a task whose worker died, before its point is recorded as failed.
DEFAULT_RETRIES = 2
MISSING_EXTRA = (
    "running on Dask needs the 'dask' extra of kftune: pip install 'kftune[dask]' "
    "(or pip install 'dask[distributed]')"
)


class DaskMissingError(ConfigError):
    """The ``dask`` extra is not installed (a configuration problem: exit code 3)."""


class SchedulerLostError(EngineLostError):
    """The scheduler went away during a run (a run-time failure: exit code 1); what was
    finished before is in the study.

    Attributes:
        scheduler: the scheduler's address.
    """

    def __init__(self, message: str, *, scheduler: str) -> None:
        super().__init__(message)
        self.scheduler = scheduler


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise DaskMissingError(MISSING_EXTRA) from None
    return distributed


def _task_point(fun: Callable[[np.ndarray], float], x: np.ndarray) -> Outcome:
    """A worker's task: one point's outcome."""
    return evaluate_point(fun, x)


def _task_chunk(problem: Any, x: np.ndarray, indices: list[int]) -> tuple[Any, ...]:
    """A worker's task: a point's scores on some manoeuvres; ``("ok", scores, t)``, or
    ``("error", reason, t, index)`` for the first manoeuvre whose run failed."""
    t0 = time.perf_counter()
    scores = []
    for i in indices:
        try:
            scores.extend(problem.score_manoeuvres(x, [i]))
        except Exception as exc:
            return "error", describe(exc), time.perf_counter() - t0, i
    return "ok", scores, time.perf_counter() - t0


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while worker processes start (they keep it ignored: a Ctrl-C in the
    terminal reaches the whole process group, and each worker printed its traceback), then
    the caller's handler again. Only in the main thread, where handlers can be set."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _silenced_logs() -> Iterator[None]:
    """distributed's log lines to standard error silenced but for critical ones (its own
    facility, as :class:`distributed.LocalCluster` uses): a lost scheduler printed 30 lines
    of tracebacks before the engine could say what happened."""
    from distributed.utils import silence_logging_cmgr

    with silence_logging_cmgr(logging.CRITICAL):
        yield


#: How long past the connect timeout a handshake may take before the address is given up
#: on (something that is not a Dask scheduler accepts the connection and never answers).
HANDSHAKE_GRACE = 5.0


#: [bytes] the most a scheduler's first message may announce: its handshake (a few
#: Python and pickle versions) takes under 100 bytes.
HANDSHAKE_MAX_BYTES = 64 * 1024
#: The most frames a handshake may announce (it has one).
HANDSHAKE_MAX_FRAMES = 16


class NotDaskError(ConfigError):
    """The service at the address does not answer in Dask's protocol (exit code 3)."""


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    """``n`` bytes from ``sock`` (``n`` bounded by the caller), or ConnectionError when
    the peer closes first."""
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("the connection was closed before the handshake")
        data += chunk
    return bytes(data)


def _preflight(scheduler: str, timeout: float) -> None:
    """Read the first message of the scheduler at ``scheduler`` (a ``tcp://`` address)
    with a bound, before distributed does: its client allocates whatever the 8-byte length
    prefix of distributed's framing announces. A Dask scheduler sends its handshake as
    soon as a connection is accepted: one frame of a few dozen bytes. A refused connection
    is tried again until ``timeout`` (a scheduler that is still starting); the handshake
    may take ``timeout`` + :data:`HANDSHAKE_GRACE` seconds from the start. Other protocols
    (``tls://``: the client speaks first) are left to distributed.

    Raises:
        OSError: nothing accepts a connection there within ``timeout``.
        TimeoutError: something accepts it and sends nothing.
        NotDaskError: what it sends is not a Dask handshake.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    protocol, location = parse_address(scheduler)
    if protocol != "tcp":
        return
    host, port = parse_host_port(location)
    start = time.monotonic()
    while True:
        left = timeout - (time.monotonic() - start)
        try:
            sock = socket.create_connection((host, port), timeout=max(left, 0.1))
            break
        except ConnectionRefusedError:
            if left <= 0:
                raise
            time.sleep(min(0.2, max(left, 0.0)))
    with sock:
        sock.settimeout(max(timeout + HANDSHAKE_GRACE - (time.monotonic() - start), 0.1))
        try:
            (n,) = struct.unpack("Q", _recv_exactly(sock, 8))  # distributed.comm.tcp's
            if not 16 <= n <= HANDSHAKE_MAX_BYTES:
                raise NotDaskError(
                    f"its first message announces {n} bytes; a Dask scheduler's handshake "
                    f"takes 16 to {HANDSHAKE_MAX_BYTES}"
                )
            body = _recv_exactly(sock, n)
        except TimeoutError:
            raise TimeoutError("no answer in Dask's protocol: is it a Dask scheduler?") from None
        (frames,) = struct.unpack_from("Q", body)
        if not (1 <= frames <= HANDSHAKE_MAX_FRAMES and 8 * (1 + frames) <= n):
            raise NotDaskError(
                f"its first message announces {frames} frames in {n} bytes, not a handshake"
            )


def _connect(distributed: Any, scheduler: str, timeout: float) -> Any:
    """A client of the scheduler at ``scheduler``, or TimeoutError when none answers
    within ``timeout`` + :data:`HANDSHAKE_GRACE` seconds (distributed's own timeout does
    not cover a handshake with a service that is not Dask's: it waited for ever).

    Raises:
        OSError, TimeoutError: nothing answers there.
        NotDaskError: something answers, not in Dask's protocol — also when distributed
            fails on what it read (an allocation of an announced length that passed
            :func:`_preflight` on its own connection and not on distributed's).
    """
    _preflight(scheduler, timeout)
    box: dict[str, Any] = {}

    def connect() -> None:
        try:
            box["client"] = distributed.Client(scheduler, timeout=timeout)
        except (MemoryError, OverflowError, ValueError, struct.error) as exc:
            box["error"] = NotDaskError(f"its answer could not be read: {describe(exc)}")
        except OSError as exc:  # TimeoutError included; its message is all the caller uses
            box["error"] = OSError(str(exc))
        except BaseException as exc:  # handed to the caller
            box["error"] = exc
        if "error" in box:
            # The half-made client is garbage in a reference cycle: collected here, its
            # __del__ closes it; collected later on distributed's event-loop thread, it
            # waited for a lock the next client's start held (10 s, then a wrong error).
            gc.collect()

    thread = threading.Thread(target=connect, name="kftune-dask-connect", daemon=True)
    thread.start()
    thread.join(timeout + HANDSHAKE_GRACE)
    if thread.is_alive():
        raise TimeoutError("no answer in Dask's protocol: is it a Dask scheduler?")
    if "error" in box:
        raise box["error"]
    return box["client"]


def _check_address(scheduler: str) -> None:
    """Refuse a scheduler address that is not ``[PROTOCOL://]HOST:PORT`` with a port in
    1–65535 (before any connection is tried).

    Raises:
        ConfigError: naming the address and what was expected.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        port = parse_host_port(parse_address(scheduler)[1])[1]
    except (ValueError, TypeError):
        port = None
    if not (isinstance(port, int) and 1 <= port <= 65535):
        raise ConfigError(
            f"--scheduler {scheduler!r}: not a scheduler address; expected "
            "tcp://HOST:PORT (port 1–65535, e.g. tcp://10.0.0.5:8786) or 'local'"
        )


@runtime_checkable
class _ChunkedObjective(Protocol):
    """What the engine reads of a :class:`~kftune.tuning.problem.TuningProblem` to split a
    point's evaluation across workers by manoeuvre and pool the parts."""

    def manoeuvre_chunks(self, k: int) -> list[Any]: ...

    def _pool_scores(self, scores: Sequence[Any]) -> Any: ...


class DaskEngine(Engine):
    """Evaluates batches on a Dask cluster.

    Args:
        fun: the objective; a :class:`~kftune.tuning.problem.TuningProblem` can also be
            split across manoeuvres. It must pickle (a tuning problem does).
        scheduler: a scheduler address (``"tcp://host:8786"``), or ``None``/``"local"`` to
            start a :class:`distributed.LocalCluster` of ``workers`` processes (one thread
            each) for the engine's lifetime.
        workers: processes of the local cluster (ignored with a scheduler address).
        retries: re-submissions of a task whose worker died (see the module docstring).
        connect_timeout: [s] to reach the scheduler and see its first worker.

    Raises:
        DaskMissingError: the ``dask`` extra is not installed.
        ConfigError: the scheduler cannot be reached, or no worker joins it in time.
    """

    def __init__(
        self,
        fun: Callable[[np.ndarray], float],
        *,
        scheduler: str | None = None,
        workers: int = 1,
        retries: int = DEFAULT_RETRIES,
        connect_timeout: float = CONNECT_TIMEOUT,
    ) -> None:
        distributed = _distributed()
        import dask

        if not (isinstance(workers, int) and workers >= 1):
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        self.fun = fun
        # a tuning problem: its points may be split across workers by manoeuvre
        self._chunked = fun if isinstance(fun, _ChunkedObjective) else None
        self.retries = int(retries)
        self._cluster: Any = None
        self.client: Any = None
        self._quiet = contextlib.ExitStack()  # distributed's log lines, while the engine runs
        self._quiet.enter_context(_silenced_logs())
        try:
            self._start(distributed, dask, scheduler, workers, connect_timeout)
        except BaseException:
            self.close()
            raise

    def _start(
        self,
        distributed: Any,
        dask: Any,
        scheduler: str | None,
        workers: int,
        connect_timeout: float,
    ) -> None:
        """Start or reach the cluster, then ship the objective (see the class)."""
        if isinstance(scheduler, str) and scheduler.strip().lower() == "local":
            scheduler = "local"
        elif scheduler is not None:
            _check_address(scheduler)
        if scheduler in (None, "local"):
            with (
                dask.config.set({"distributed.scheduler.allowed-failures": 0}),
                _sigint_ignored(),  # the workers inherit it: Ctrl-C is the client's to handle
            ):
                self._cluster = distributed.LocalCluster(
                    n_workers=workers,
                    processes=True,
                    threads_per_worker=1,
                    dashboard_address=None,
                    silence_logs=logging.CRITICAL,  # in the worker processes too
                )
            self.client = distributed.Client(self._cluster)
        else:
            try:
                self.client = _connect(distributed, scheduler, connect_timeout)
            except NotDaskError as exc:
                raise NotDaskError(
                    f"the service at {scheduler!r} does not answer in Dask's protocol ({exc}): "
                    "is it a Dask scheduler? Start one with 'dask scheduler' and give its "
                    "tcp:// address"
                ) from None
            except (OSError, TimeoutError) as exc:
                raise ConfigError(
                    f"cannot reach the Dask scheduler at {scheduler!r} within "
                    f"{connect_timeout:g} s ({exc}); start one with 'dask scheduler' and "
                    "give its tcp:// address"
                ) from None
            try:
                self.client.wait_for_workers(1, timeout=connect_timeout)
            except (OSError, TimeoutError):
                raise ConfigError(
                    f"the Dask scheduler at {scheduler!r} has no worker (none joined within "
                    f"{connect_timeout:g} s); start some with 'dask worker {scheduler}'"
                ) from None
        self.scheduler = self.client.scheduler.address
        self.workers = self._threads()
        self._data = self._scatter()

    def _threads(self) -> int:
        info = self.client.scheduler_info(n_workers=-1)["workers"]
        return max(1, sum(int(w.get("nthreads", 1)) for w in info.values()))

    def _scatter(self) -> Any:
        """Ship the objective (with its dataset) to every worker, once."""
        return self.client.scatter(self.fun, broadcast=True, hash=False)

    def worker_pids(self) -> dict[str, int]:
        """Worker address → process id (e.g. to watch or kill one)."""
        import os

        return self.client.run(os.getpid)

    # ------------------------------------------------------------------ running
    def run(self, points: Sequence[np.ndarray]) -> Iterator[tuple[int, Outcome]]:
        """See :meth:`Engine.run`.

        Raises:
            SchedulerLostError: the scheduler went away; the points not yielded yet are
                not evaluated.
        """
        try:
            yield from self._run(points)
        except SchedulerLostError:
            raise
        except (Exception, asyncio.CancelledError) as exc:
            # A closed comm is the scheduler's connection going: the client may not have
            # marked itself disconnected yet when gather's stream closes under it.
            closed = isinstance(exc, _distributed().comm.CommClosedError)
            if self._connected() and not closed:
                raise
            raise self._lost(describe(exc)) from None

    def _connected(self) -> bool:
        """Whether the client is connected to its scheduler."""
        return self.client is not None and self.client.status == "running"

    def _lost(self, how: str) -> SchedulerLostError:
        """The error saying that the scheduler was lost (``how``: how it showed)."""
        return SchedulerLostError(
            f"lost the Dask scheduler at {self.scheduler!r} during the run ({how}); the "
            "run can go on when a scheduler with workers runs there again, or on another "
            "one (--scheduler)",
            scheduler=self.scheduler,
        )

    def _run(self, points: Sequence[np.ndarray]) -> Iterator[tuple[int, Outcome]]:
        distributed = _distributed()
        points = [np.asarray(x, dtype=float) for x in points]
        if not points:
            return
        # Splitting never changes a result, so it may follow the cluster's current size.
        k = self._threads() // len(points)
        chunked = self._chunked if k > 1 else None
        chunks: list[Any] = chunked.manoeuvre_chunks(k) if chunked is not None else [None]
        split = len(chunks) > 1
        # task future -> (point, chunk, attempt)
        tasks: dict[Any, tuple[int, int, int]] = {}
        for i, x in enumerate(points):
            for c in range(len(chunks)):
                tasks[self._submit(x, chunks[c])] = (i, c, 0)
        parts: dict[int, dict[int, tuple[Any, ...]]] = {i: {} for i in range(len(points))}
        done: set[int] = set()
        ac = distributed.as_completed(list(tasks))
        try:
            for fut in ac:
                i, c, attempt = tasks.pop(fut)
                if i in done:
                    continue
                if fut.status == "finished":
                    out = fut.result()
                else:
                    if fut.status == "cancelled" or not self._connected():
                        # the client cancels every task when it loses the scheduler: a
                        # point lost so is not a failed evaluation
                        raise self._lost("the connection to it closed")
                    exc = fut.exception()
                    if attempt < self.retries:
                        if self._data.status != "finished":  # every copy of it was lost
                            self._data = self._scatter()
                        new = self._submit(points[i], chunks[c])
                        tasks[new] = (i, c, attempt + 1)
                        ac.add(new)
                        continue
                    reason = (
                        f"evaluation lost {attempt + 1} times, the last time by "
                        f"{describe(exc)}; given up after {self.retries} retries"
                    )
                    out = ("error", reason, 0.0, -1) if split else (None, reason, 0.0)
                fut.release()
                if not split:
                    done.add(i)
                    yield i, out
                    continue
                parts[i][c] = out
                if len(parts[i]) == len(chunks):
                    done.add(i)
                    yield i, self._pool(parts[i], chunks)
        finally:
            for fut in tasks:  # a stopped run (Ctrl-C, an error) leaves nothing running
                fut.cancel()

    def _submit(self, x: np.ndarray, chunk: list[int] | None) -> Any:
        if chunk is None:
            return self.client.submit(_task_point, self._data, x, pure=False)
        return self.client.submit(_task_chunk, self._data, x, chunk, pure=False)

    def _pool(self, parts: dict[int, tuple[Any, ...]], chunks: list[Any]) -> Outcome:
        """One point's outcome from its chunks: the cost pooled in manoeuvre order, or the
        failure of the first manoeuvre that failed (the one :meth:`evaluate` names)."""
        t = sum(p[2] for p in parts.values())
        errors = [p for p in parts.values() if p[0] == "error"]
        if errors:
            first = min(errors, key=lambda p: (p[3] < 0, p[3]))  # a lost chunk last
            return None, first[1], t
        by_index: dict[int, Any] = {}
        for c, p in parts.items():
            by_index.update(zip(chunks[c], p[1]))
        scores = [by_index[j] for j in sorted(by_index)]
        if self._chunked is None:  # only a chunked objective's points come in parts
            raise RuntimeError("a point came back in parts from an objective without chunks")
        return float(self._chunked._pool_scores(scores).cost), None, t

    def close(self) -> None:
        """Close the client, and the local cluster this engine started. Nothing of it is
        needed any more: a failure to close (a scheduler already gone, a cluster slow to
        stop on a loaded machine) is not an error of the run."""
        client, self.client = self.client, None
        cluster, self._cluster = self._cluster, None
        with contextlib.suppress(Exception, asyncio.CancelledError):
            if client is not None:
                client.close()
        with contextlib.suppress(Exception, asyncio.CancelledError):
            if cluster is not None:
                cluster.close()
        self._quiet.close()
