"""Python's cyclic garbage collector in a process that is the `riskplan` command line.

Importing numba, Hydra and pandas, composing the config and loading numba's kernels create about a million
objects that live until the process ends. Every full collection traverses all of them: during the start-up of
`riskplan train`, and again in the interpreter's last collections at exit, after the command's work is done
(docs/benchmarks.md has what they cost). Objects are still freed by reference counting throughout; only the
traversals are skipped. Only a process that `main` started is tuned: a notebook or a test that calls riskplan's
functions keeps its collector as it is.
"""

from __future__ import annotations

import atexit
import gc

_command_line = False  # set by `command_line_process`
_paused = False


def command_line_process() -> None:
    """This process is a `riskplan` command: its last collections at exit, over every object still alive, are
    skipped (files are closed and logs flushed before then; atexit handlers still run)."""
    global _command_line
    _command_line = True
    atexit.register(gc.freeze)


def pause_collection() -> None:
    """In a command-line process, no collections until `resume_collection`: a start-up allocates what it keeps."""
    global _paused
    if _command_line and gc.isenabled():
        gc.disable()
        _paused = True


def resume_collection() -> None:
    """Collections again, if `pause_collection` stopped them, over objects allocated from now on: the start-up's
    are moved out of the collector's reach (gc.freeze). A no-op otherwise, so library code may call it freely."""
    global _paused
    if _paused:
        _paused = False
        gc.freeze()
        gc.enable()
