"""Output folders: checked before use, claimed fresh, written atomically; paths written as Hydra override values."""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import json
import os
import shutil
from pathlib import Path

from riskplan.util.errors import BadInput

VIRTUAL = ("/proc", "/sys", "/dev")  # kernel filesystems: writing results there is never what a user meant


def undecoded(text: str | Path) -> bool:
    """Whether a name holds bytes the system's locale could not decode (Python keeps them as lone surrogates, e.g.
    a UTF-8 name under LC_ALL=C without UTF-8 mode, or a Latin-1 one): riskplan writes paths into UTF-8 files
    (configs, logs, tables), where such a name cannot go."""
    return any("\udc80" <= ch <= "\udcff" for ch in str(text))


def shown_bytes(text: str | Path) -> str:
    """A name as its bytes, undecodable ones escaped (\\xc3): printable on any terminal, whatever its locale."""
    return os.fsencode(str(text)).decode("ascii", "backslashreplace")


def check_decoded(text: str | Path, what: str) -> None:
    """BadInput naming `what` when `text` holds bytes the locale could not decode (`undecoded`)."""
    if undecoded(text):
        shown, label = shown_bytes(text), shown_bytes(what)  # `what` may be the path itself (the Python API's key)
        raise BadInput(
            shown if label == shown else f"{label} {shown}",
            "holds bytes this system's locale cannot decode, and riskplan writes its paths into UTF-8 files; run "
            "under a UTF-8 locale (LC_ALL=C.UTF-8, or PYTHONUTF8=1) or use an ASCII name",
        )


def claim_dir(root: Path, suffix: str = "") -> Path:
    """Create root/<YYYY-MM-DD_HH-MM-SS><suffix>, or with _1, _2, ... when taken: mkdir is the lock."""
    check_output_dir(root, str(root))
    base = Path(root) / f"{dt.datetime.now():%Y-%m-%d_%H-%M-%S}{suffix}"
    candidate, number = base, 1
    while True:
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            candidate = base.with_name(f"{base.name}_{number}")
            number += 1
        except OSError as err:
            raise BadInput(str(root), f"cannot be written ({err.strerror}); give a directory you can write") from None


def check_output_dir(path: Path | str, key: str) -> Path:
    """A directory riskplan may write into (existing or to be made): BadInput naming `key` otherwise.

    Refused: an empty or blank path, a name the locale could not decode, the filesystem root, /proc, /sys and
    /dev, a path through a .hydra folder, a file (or a path through one), and a directory on a read-only filesystem
    or without write permission.
    """
    text = str(path)
    if not text.strip() or "\x00" in text:
        raise BadInput(key, f"got {text!r}; give a directory path")
    _check_no_detour(text, key)
    resolved = Path(os.path.abspath(os.path.expanduser(text)))
    check_decoded(resolved, key)  # the Python API's paths too (the command line's are checked on arrival)
    _check_name_lengths(resolved, key)  # before a lookup: a name too long fails even to be looked up
    _check_links(resolved, text, key)
    resolved = Path(os.path.realpath(resolved))
    if resolved == Path(resolved.anchor):
        raise BadInput(key, f"{text} is the filesystem root; give a directory of its own, e.g. outputs/runs/mine")
    _check_on_disk(resolved, text, key, "a directory")
    if ".hydra" in resolved.parts:  # Hydra's record of a run's config: jobs written there are taken for it
        raise BadInput(
            key, f"{text} is inside a .hydra folder, where Hydra keeps a run's config; give another directory"
        )
    if resolved.exists() and not resolved.is_dir():
        raise BadInput(key, f"{text} is a file; expected a directory")
    existing = resolved
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise BadInput(key, f"{text} cannot be made: {existing} is a file")
    if _read_only(existing) or not os.access(existing, os.W_OK | os.X_OK):
        why = "is on a read-only filesystem" if _read_only(existing) else "is not writable"
        raise BadInput(key, f"{text} {why}; give a directory you can write")
    return Path(text)


def _check_no_detour(text: str, key: str) -> None:
    """BadInput for a '..' that leaves a folder which does not exist (`a/../b`): making the path would make that
    folder, then leave it empty behind."""
    here = Path(os.path.expanduser(text))
    walked = Path(here.anchor)
    for part in here.parts[1:] if here.anchor else here.parts:
        if part == ".." and not walked.exists():
            raise BadInput(
                key,
                f"{text} goes into {walked} and back out with '..', but {walked} does not exist (making the path would "
                f"leave it behind, empty); give {os.path.normpath(text)}",
            )
        walked = walked / part


def check_outside_runs(path: Path | str, runs: list[Path], key: str) -> None:
    """BadInput when `path` is one of the run folders `runs`, or inside one: what is written there changes the run,
    and a later read of its folder takes it for one of the run's files, or for a run of its own."""
    resolved = Path(os.path.realpath(os.path.abspath(os.path.expanduser(str(path)))))
    for run in runs:
        run = Path(os.path.realpath(run))
        if resolved == run or run in resolved.parents:
            raise BadInput(key, f"{path} is inside the run folder {run}; give a folder outside the runs")


def file_path(text: str | Path, key: str, ending: str) -> Path:
    """A file's path as typed, not empty and not named as a folder (a trailing '/'), which typer's Path would read as
    '.' and as the file without the '/'. `ending` names the file types, for the message."""
    text = str(text)
    if not text.strip() or "\x00" in text:
        raise BadInput(key, f"got {text!r}; give a file path ending {ending}")
    if text.endswith(("/", os.sep)):
        raise BadInput(key, f"{text} ends in '/', which names a folder; give a file path ending {ending}")
    return Path(text)


def _check_on_disk(resolved: Path, text: str, key: str, what: str) -> None:
    """BadInput when a resolved path lies in a kernel filesystem (VIRTUAL): /dev/full.png was written."""
    for virtual in VIRTUAL:
        if resolved == Path(virtual) or Path(virtual) in resolved.parents:
            raise BadInput(key, f"{text} is under {virtual}, a kernel filesystem; give {what} on a disk")


def _check_links(path: Path, text: str, key: str) -> None:
    """BadInput for a symbolic link on the path that leads nowhere (its target is gone) or round in a loop: a
    directory could not be made there, and the error would read 'File exists'."""
    for part in (path, *path.parents):
        if not part.is_symlink():
            continue
        try:
            part.resolve(strict=True)
        except (RuntimeError, OSError) as err:  # a loop: RuntimeError before Python 3.13, ELOOP since
            if isinstance(err, RuntimeError) or err.errno == errno.ELOOP:
                raise BadInput(key, f"{text}: {part} is a symbolic link in a loop; give a directory path") from None
            raise BadInput(
                key,
                f"{text}: {part} is a symbolic link to {os.readlink(part)}, which does not exist; give a directory "
                f"path, or make the link's target first",
            ) from None


def check_output_file(text: str | Path, key: str, ending: str) -> Path:
    """A file riskplan may write (--draw's picture, bench's --json), as typed: its folder exists and can be written,
    and it is not a folder itself (nor named as one, with a trailing '/'); checked before the work that writes it.
    `ending` names the file types, for the message."""
    path = file_path(text, key, ending)
    _check_on_disk(Path(os.path.realpath(os.path.abspath(os.path.expanduser(path)))), str(path), key, "a file")
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise BadInput(key, f"{path} is a folder; give a file path ending {ending}")
    if not folder.is_dir():
        why = f"{folder} is a file, not a folder" if folder.exists() else f"no folder {folder}"
        raise BadInput(key, f"{path} cannot be written: {why}; give a path in an existing folder")
    probe = folder / f".{path.name}.probe"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise BadInput(key, f"{path} cannot be written ({err.strerror}); give a path in a writable folder") from None
    return path


INSIDE = 64  # bytes left under PATH_MAX for the files a command writes inside (tests/run checks a run's fit)


def _check_name_lengths(full: Path, key: str) -> None:
    """BadInput for a directory the filesystem would refuse to make (a name over its NAME_MAX bytes, or a path that
    leaves no room for the files inside under PATH_MAX): one line, not "File name too long" after work."""
    made = current = Path(full.anchor)  # `made`: the deepest folder that exists, which the limits are asked of
    for part in full.parts[1:]:
        limit = os.pathconf(made, "PC_NAME_MAX")
        size = len(os.fsencode(part))
        if size > limit:
            raise BadInput(
                key,
                f"names a folder of {size} bytes ({part[:24]}...); this filesystem takes names of at most {limit} "
                f"bytes: give a shorter one",
            )
        current = current / part
        if made == current.parent and os.path.isdir(current):  # never raises, however long
            made = current
    limit = os.pathconf(made, "PC_PATH_MAX")
    if len(os.fsencode(str(full))) + INSIDE > limit:
        raise BadInput(
            key,
            f"is {len(os.fsencode(str(full)))} bytes long as an absolute path; this filesystem takes paths of at most "
            f"{limit} bytes, with the files inside: give a shorter one",
        )


def _read_only(path: Path) -> bool:
    """Whether path lies on a filesystem mounted read-only (root ignores permission bits, not this)."""
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def temp_name(name: str, pid: int | str) -> str:
    """The temp file atomic_path writes `name` through in process `pid`: only a killed writer leaves it behind."""
    return f".{name}.{pid}.tmp"


@contextlib.contextmanager
def atomic_path(path: Path | str, durable: bool = True):
    """Yield a temp path beside `path`; rename it over `path` when the block succeeds, else remove it.

    Readers see the old file or the new one, never half of one; a failed write (a full disk) leaves no temp file.
    `durable=False` skips the fsync: for a file that is written again whenever it is needed (a job's `.hydra/`
    files, a starting job's status), where a power cut may lose it but a crash of the process cannot tear it.
    An OSError that names no file (a write, close or fsync that fails: a full disk) is given `path` as its
    filename, so that its one line names the file, not only the directory.
    """
    path = Path(path)
    tmp = path.with_name(temp_name(path.name, os.getpid()))
    try:
        yield tmp
        if durable:
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(err, OSError) and err.filename is None and err.errno is not None:
            err.filename = str(path)  # not without an errno: str(err) would read "[Errno None] None: ..."
        raise


def write_atomic(path: Path | str, data: str | bytes, durable: bool = True) -> None:
    """Write text or bytes to `path` atomically (see atomic_path)."""
    with atomic_path(path, durable) as tmp:
        if isinstance(data, str):
            tmp.write_text(data, encoding="utf-8")
        else:
            tmp.write_bytes(data)


def hydra_quote(value: Path | str) -> str:
    """A path (or key) as a quoted Hydra override value."""
    return "'" + str(value).replace("\\", "\\\\").replace("'", "\\'") + "'"


MARKER = "riskplan-export.json"  # what riskplan writes into a directory it exports, to know it again


def is_marked(target: Path, marker: dict, foreign) -> bool:
    """Whether `target` holds riskplan's MARKER with `marker` (an export that is already there, unchanged). A
    directory there without riskplan's marker, or with another exporter's (its `format`: a ROS 2 bag where
    TensorBoard would write), is not this exporter's to replace: `foreign()` is the error raised."""
    if not target.exists():
        return False
    try:
        found = json.loads((target / MARKER).read_text())
    except (OSError, ValueError):
        raise foreign() from None
    if not isinstance(found, dict) or found.get("format") != marker.get("format"):
        raise foreign()
    return found == marker


def replace_marked_dir(target: Path, marker: dict, fill) -> str:
    """A directory written whole or not at all: `fill(tmp)` writes a temporary sibling, marked with `marker`, that
    then takes target's place; "exported", or "replaced" (the old one is removed only after). If `fill` fails, the
    previous directory stays as it was."""
    existed = target.exists()
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.tmp-{os.getpid()}"
    trash = target.parent / f".{target.name}.old-{os.getpid()}"
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        fill(tmp)
        try:
            write_atomic(tmp / MARKER, json.dumps(marker, indent=2) + "\n")
        except OSError as err:
            if err.filename == str(tmp / MARKER):  # atomic_path named it in tmp, which goes; the caller names target
                raise OSError(err.errno, err.strerror) from None  # (a filename once set prints even as None)
            raise
        if existed:
            os.replace(target, trash)
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if trash.exists() and not target.exists():
            os.replace(trash, target)  # the previous export stays
        raise
    shutil.rmtree(trash, ignore_errors=True)
    return "replaced" if existed else "exported"
