"""Exit codes of the ``kftune`` command.

Exit codes:
    0  success
    1  the job ran but failed (e.g. every evaluation failed, a filter diverged, a study or
       output file could not be written while it ran, the Dask scheduler was lost)
    2  usage error: bad command-line options (argparse's convention), or ``--json`` with
       standard output closed
    3  bad input: a data file, manifest, configuration or study file is unusable, or an
       output path cannot be written (refused before any work starts)
    130 interrupted (Ctrl-C); whatever finished has been saved
    141 stdout was closed early (``kftune dataset info | head``), as for SIGPIPE in a shell
    143 terminated (SIGTERM: a batch scheduler, ``timeout --preserve-status``); handled as
        Ctrl-C is

A module of their own so that the subcommand modules, which :mod:`kftune.cli` imports, do
not import :mod:`kftune.cli` back.
"""

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_BAD_INPUT = 3
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
EXIT_BROKEN_PIPE = 141
