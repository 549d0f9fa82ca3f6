"""Where a command's output files go, and that writing them never costs an input or a run.

Every command that writes files checks its outputs before any work starts
(:func:`output_file`, :func:`output_dir`): an output must not replace a file the command
reads (:func:`command_inputs`, :func:`refuse_inputs` — also through a link, ``..`` or a hard
link), must be a file in a folder where one can be created, and a report folder's files must
be replaceable — so that a tuning run is never spent before a crash at its end. An existing
output file is replaced; whether an existing study or dataset folder may be started afresh
(``--force``) is each command's decision, taken before these checks.

Writing is atomic (:func:`write_output`): a temporary file beside the target, flushed to the
disk, renamed over it, so that a full disk or a file made read-only meanwhile leaves the old
file whole; what could not be written is saved to the temporary folder, and the error says
where (:class:`~kftune.errors.RunFailedError`, exit 1). :func:`writing` gives the same
error around writers that write their files themselves (a report, a figure, a table).

The configuration and the options every command shares are :mod:`kftune.cli._common`'s.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from kftune.cli._common import pick, split_model_file
from kftune.errors import ConfigError, RunFailedError

#: A file a command reads, with what it is for messages: ``(path, "the tuned file")``.
Input = tuple[Path, str]


def command_inputs(
    args: argparse.Namespace, config: Mapping[str, Any], *, study: bool = True
) -> list[Input]:
    """Every file the command of ``args`` reads, which none of its outputs may replace:
    the dataset's files (manifest and recordings), the configuration, a model file, the
    tuned file (``params``) and, with ``study``, the study (``storage``: every widening
    round's file with SQLite's side files). What a command lacks is left out; a dataset
    that cannot be read gives none (the command refuses it before writing anything)."""
    found: list[Input] = []
    given = vars(args)
    if "dataset" in given or "dataset" in config:
        found += dataset_inputs(pick(args, dict(config), "dataset", None))
    if given.get("config") is not None:
        found.append((Path(given["config"]), "the configuration (--config)"))
    model = pick(args, dict(config), "model", None)
    mf = split_model_file(model) if isinstance(model, str) else None
    if mf is not None:
        found.append((mf[0], "the model file"))
    if given.get("params") is not None:
        found.append((Path(given["params"]), "the tuned-parameters file"))
    if study and given.get("storage") is not None:
        from kftune.optim import study_files
        from kftune.optim.widen import WIDEN_ROUNDS, round_storage

        rounds = [round_storage(given["storage"], k) for k in range(WIDEN_ROUNDS + 1)]
        found += [
            (f, "a file of the study (--storage)")
            for r in rounds
            if r is not None
            for f in study_files(r)
        ]
    return found


def dataset_inputs(spec: str | Path | None) -> list[Input]:
    """The files of the dataset ``spec`` names on a command line (``None``: the bundled
    one): a kftune dataset's manifest and the recordings it lists, or every file of a
    folder in the revs-250lm layout; none when it cannot be read."""
    from kftune.data.io import DEFAULT_DATASET, bundled_dataset_path, dataset_files
    from kftune.errors import DataError

    path = bundled_dataset_path() if spec is None or str(spec) == DEFAULT_DATASET else Path(spec)
    what = f"a file of the dataset {spec or DEFAULT_DATASET}"
    try:
        return [(f, what) for f in dataset_files(path)]
    except DataError:
        pass
    try:
        return [(f, what) for f in path.iterdir() if f.is_file()] if path.is_dir() else []
    except OSError:
        return []


def same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file: the same path once ``..`` and links are
    resolved (also for a file not yet made), or the same device and inode (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def refuse_inputs(
    path: Path,
    option: str,
    inputs: Iterable[Input],
    why: str = "writing there would replace it: choose another name",
) -> None:
    """Refuse to write (or delete) ``path`` when it is one of the command's ``inputs``
    (:func:`command_inputs`): an output must never replace what the command reads.

    Raises:
        ConfigError: naming ``option``, the path, which input it is and ``why`` not.
    """
    for source, what in inputs:
        if same_file(path, source):
            also = "" if str(source) == str(path) else f" ({source})"
            raise ConfigError(f"{option} {path}: is {what}{also}, which this command reads; {why}")


def output_file(path: Path, option: str, inputs: Iterable[Input] = ()) -> Path:
    """``path`` if a file can be written there; checked before any work starts, so that no
    run is spent before a crash at the end.

    Raises:
        ConfigError: naming ``option``, when ``path`` is one of ``inputs`` (see
            :func:`refuse_inputs`), a folder, a pipe, socket or other non-file, an existing
            file that cannot be replaced, a link into a missing folder, its folder is
            missing (or a file) or lets no file be created (tried, not inferred from
            permission bits, which do not hold for root or read-only mounts).
    """
    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a folder; expected a file name")
    refuse_inputs(path, option, inputs)
    real = Path(os.path.realpath(path))  # the file a link points to, also a dangling one
    where = f"{option} {path}" + (f" (a link to {real})" if path.is_symlink() else "")
    if real.exists():
        mode = real.stat().st_mode
        if not (stat.S_ISREG(mode) or stat.S_ISCHR(mode)):  # a FIFO would block forever
            raise ConfigError(f"{where}: is not a regular file (a pipe, socket or device)")
        if not os.access(real, os.W_OK):
            raise ConfigError(f"{where}: the file cannot be written (read-only or immutable)")
    if not real.parent.is_dir():
        existing = _existing_ancestor(real.parent)
        if not existing.is_dir():
            raise ConfigError(f"{where}: {existing} is a file, not a folder")
        raise ConfigError(f"{where}: the folder {real.parent} does not exist")
    _check_can_create(real.parent, where)
    return path


def _existing_ancestor(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (a file or a folder)."""
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


#: Files of a report folder that ``compare`` and ``report`` replace.
#: (The names of kftune.report, which is not imported here: it loads matplotlib.)
REPORT_FILES = ("results.json", "traces.npz", "report.md")


def output_dir(path: Path, option: str, inputs: Iterable[Input] = ()) -> Path:
    """``path`` if it is, or can be created as, a writable folder; checked before any work.

    Raises:
        ConfigError: naming ``option``, when ``path`` or one of its ancestors is a file, no
            file can be created in the nearest existing ancestor, or one of the
            :data:`REPORT_FILES` in it is one of ``inputs`` or cannot be replaced (see
            :func:`output_file`).
    """
    inputs = list(inputs)
    for name in REPORT_FILES:
        refuse_inputs(path / name, option, inputs)
    existing = _existing_ancestor(path)
    if not existing.is_dir():
        where = "is a file" if existing == path else f"lies below the file {existing}"
        raise ConfigError(f"{option} {path}: {where}; expected a folder")
    _check_can_create(existing, f"{option} {path}")
    for name in REPORT_FILES:  # files a report replaces must be replaceable
        if (path / name).exists() or (path / name).is_symlink():
            output_file(path / name, option)
    return path


def _check_can_create(folder: Path, where: str) -> None:
    """Create and drop a nameless file in ``folder`` (``ConfigError`` naming ``where`` if
    that fails: read-only mount, immutable folder, ``/proc``, permissions)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ConfigError(
            f"{where}: no file can be created in {folder} ({exc.strerror or exc})"
        ) from None


def write_output(path: Path, text: str | bytes, option: str, keep: str = "") -> None:
    """Write ``text`` (or bytes) to ``path`` (an output checked by :func:`output_file`)
    atomically: into a temporary file beside the real target, flushed to the disk, then
    renamed over it, so a failure (disk full, the file made immutable meanwhile) never
    leaves a truncated file. A link is written through; a character device (``/dev/null``)
    is written in place, its errors (``/dev/full``) reported as any other's.

    Raises:
        RunFailedError: (exit 1) writing failed; ``text`` was saved to a fallback file in
            the temporary folder, which the message names — or, if that fails too, the
            message holds ``text`` itself — and says what else keeps the result (``keep``,
            e.g. the study).
    """
    real = Path(os.path.realpath(path))
    try:
        if real.exists() and not stat.S_ISREG(real.stat().st_mode):
            with open(real, "wb" if isinstance(text, bytes) else "w") as fh:
                fh.write(text)
        else:
            _replace(real, text)
        return
    except OSError as exc:
        reason = f"cannot write {option} {path} ({exc.strerror or exc})"
    also = f"; {keep}" if keep else ""
    fallback = Path(tempfile.gettempdir()) / f"kftune-{path.stem}-{os.getpid()}{path.suffix}"
    try:
        _replace(fallback, text)
    except OSError:
        if isinstance(text, bytes):
            raise RunFailedError(f"{reason}, nor in the temporary folder{also}") from None
        raise RunFailedError(
            f"{reason}, nor in the temporary folder{also}; here it is:\n{text}"
        ) from None
    raise RunFailedError(f"{reason}; it was written to {fallback} instead{also}")


def _replace(path: Path, text: str | bytes) -> None:
    """Write ``text`` into a temporary file beside ``path``, flush it to the disk (a
    deferred write error surfaces here, not after the rename) and rename it over ``path``
    (with the permissions a plain write would give: the old file's, or 0o666 less the
    umask)."""
    if path.exists():
        mode = path.stat().st_mode & 0o7777
    else:
        umask = os.umask(0o022)
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.chmod(tmp, mode)
        with os.fdopen(fd, "wb" if isinstance(text, bytes) else "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def writing(what: str, keep: str) -> Iterator[None]:
    """Run the body; an ``OSError`` in it (disk full, file-size limit, a folder made
    read-only meanwhile) becomes :class:`~kftune.errors.RunFailedError` (exit 1) saying
    what could not be written and what ``keep``s the result."""
    try:
        yield
    except OSError as exc:
        raise RunFailedError(f"cannot write {what} ({exc.strerror or exc}); {keep}") from None
