"""The one exception type for bad user input (CLI exit code 2, one plain line), its kind for a missing extra, and
the closest valid option its line suggests for a mistyped one."""

import difflib
import errno
from collections.abc import Iterable


class BadInput(ValueError):
    """Bad user input; `str()` is the single line shown to the user, naming the key or path."""

    def __init__(self, where: str, problem: str):
        self.where = where
        self.problem = problem
        super().__init__(one_line(f"{where}: {problem}"))


def one_line(text: str) -> str:
    """text as one line whatever a user typed: line breaks, escape codes and other characters that do not print are
    shown escaped (\\n, \\x1b), so a value cannot break or forge a line of the terminal or a log."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def first_line(err: BaseException) -> str:
    """An error's first line for a one-line message, at most 200 characters (its type's name when it says nothing):
    a library's error may run to a page."""
    text = str(err).strip().splitlines()
    return text[0][:200] if text else type(err).__name__


class MissingExtra(BadInput):
    """An optional package that a chosen value needs (team.backend=ray: Ray) is not installed: bad input, whose line
    ends with the one `pip install` that fixes it. A sweep refuses it as a whole, before any job or folder."""


def did_you_mean(value: object, options: Iterable[object]) -> str:
    """ "; did you mean 'paper_single'?" for the option closest to a mistyped value, or "" when none is close (a
    cutoff above difflib's 0.6, which would offer 'none' for 'cosine')."""
    close = difflib.get_close_matches(str(value), [str(option) for option in options], n=1, cutoff=0.7)
    return f"; did you mean '{close[0]}'?" if close else ""


def remedy(err: OSError) -> str:
    """What fixes a failed write, for its line: 'free space' for a full disk, and the cause's own fix otherwise (a
    file size limit is not a full disk)."""
    return {
        errno.ENOSPC: "free space",
        errno.EDQUOT: "free space (a disk quota is reached)",
        errno.EFBIG: "raise the file size limit (ulimit -f)",
        errno.EACCES: "make the directory writable",
        errno.EPERM: "make the directory writable",
        errno.EROFS: "give a directory on a writable disk",
        errno.ENOENT: "restore the directory (it was removed)",
    }.get(err.errno, "fix the cause")
