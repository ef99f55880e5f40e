"""Output directories of `riskplan report` and `riskplan landscape`: owned through a manifest, written atomically.

Ownership. Each of these commands writes `.riskplan-manifest.json` into its output directory, listing every file
it writes there (relative paths) and which command wrote them. A directory is accepted as `--out` when it is
missing or empty, or when it holds that command's manifest and nothing but the files listed in it (plus leftovers
of an interrupted atomic write). Anything else is refused (BadInput, before anything is written), so a report never
overwrites files riskplan did not write. The manifest is written first, before any other file, so a run that is
interrupted half-way still owns its directory and can be re-run into it.

A directory written before manifests existed is refused like any other that holds files: nothing in it is
overwritten or removed, and the command writes into a new directory instead.

Atomicity. The files are written as one set: each is staged in a synced temp file beside its target, and only
when all are written are they renamed into place, the files they replace set aside first and put back if a rename
fails. So a full disk, a read-only file or an error half-way leaves the previous set whole (never one file of the
new set beside the old ones) and no temp file; the failure is WriteFailed, one line naming the file (the CLI prints
it and exits 1). A killed writer may leave temp files, which the next run into the directory tolerates.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Callable, Iterable
from pathlib import Path

from riskplan.run.run_files import OUTPUT_MANIFEST, output_manifest
from riskplan.util import lock
from riskplan.util.errors import BadInput, remedy
from riskplan.util.paths import check_output_dir, temp_name, write_atomic
from riskplan.version import __version__

MANIFEST = OUTPUT_MANIFEST  # named where a run directory tells itself from another command's output
TEMP = re.compile(r"\..+\.\d+\.tmp")  # paths.temp_name: what a killed writer leaves behind (staged or set aside)


class WriteFailed(OSError):
    """A file of the report or landscape could not be written (a full disk, a read-only mount, ...)."""


def _entries(root: Path) -> tuple[list[str], list[str]]:
    """(files, directories) below root, as relative POSIX paths, but for the writers' lock; symlinks count as
    files."""
    files, dirs = [], []
    for base, subdirs, names in os.walk(root):
        rel = Path(base).relative_to(root)
        for d in list(subdirs):
            if (Path(base) / d).is_symlink():
                files.append((rel / d).as_posix())
                subdirs.remove(d)
            else:
                dirs.append((rel / d).as_posix())
        files.extend((rel / n).as_posix() for n in names if not (n == lock.LOCK and rel == Path(".")))
    return sorted(files), sorted(dirs)


def read_manifest(out: Path) -> dict | None:
    """The manifest in out, or None when there is none; BadInput-free: a damaged one reads as {}."""
    data = output_manifest(out)
    if data is None:
        return None
    if not (isinstance(data.get("files"), list) and all(isinstance(f, str) for f in data["files"])):
        return {}
    return data


def _is_temp(name: str) -> bool:
    return TEMP.fullmatch(Path(name).name) is not None


def claim_output(out: Path | str, kind: str, key: str) -> list[str] | None:
    """Check that `riskplan <kind>` may write into `out`; BadInput naming `key` (e.g. --out) otherwise.

    Returns the files a previous run of the same command listed in its manifest (None for a new directory).
    Nothing is written.
    """
    check_output_dir(out, key)
    out = Path(out)
    if not out.exists():
        return None
    pid = lock.holder(out)
    if pid is not None:  # refused now, not after the work: the writer's lock says so again when it writes
        raise BadInput(
            str(out),
            f"is in use by another riskplan process (pid {pid}); one process writes a {kind} directory at a time: "
            f"wait for it to end or stop it",
        )
    files, dirs = _entries(out)
    if not files and not dirs:
        return None
    manifest = read_manifest(out)
    if manifest is None:
        foreign = [f for f in files if not _is_temp(f)] or dirs or files
        raise BadInput(
            key,
            f"{out} holds files riskplan {kind} did not write ({_examples(foreign)}); give a new "
            f"or empty directory, or one a previous riskplan {kind} wrote",
        )
    if not manifest or not isinstance(manifest.get("kind"), str):
        raise BadInput(
            key, f"{out} holds a damaged {MANIFEST} (not the list riskplan writes); give a new or empty directory"
        )
    if manifest["kind"] != kind:
        raise BadInput(
            key,
            f"{out} holds the output of riskplan {_examples([manifest['kind']])}; give riskplan "
            f"{kind} a directory of its own",
        )
    listed = {f for f in manifest["files"] if _safe(f)}
    parents = {p.as_posix() for f in listed for p in Path(f).parents if p.as_posix() != "."}
    foreign = [f for f in files if f != MANIFEST and f not in listed and not _is_temp(f)]
    foreign += [d for d in dirs if d not in parents]
    foreign += [f for f in files if f in listed and ((out / f).is_symlink() or not (out / f).is_file())]
    if foreign:
        raise BadInput(
            key,
            f"{out} holds files riskplan {kind} did not write ({_examples(sorted(set(foreign)))}); "
            f"give a new or empty directory, or remove them",
        )
    return sorted(listed)


def _safe(name: str) -> bool:
    """A manifest entry that stays inside the directory."""
    p = Path(name)
    return bool(name) and not p.is_absolute() and ".." not in p.parts and name != MANIFEST and "\x00" not in name


def _examples(names: list[str]) -> str:
    shown = ", ".join(repr(n)[1:-1] for n in names[:3])
    return shown + (f" and {len(names) - 3} more" if len(names) > 3 else "")


class Output:
    """A claimed output directory, written as one set of files under a manifest.

    output = Output(out, "report", previous)    # previous: what claim_output() returned
    with output.writing(["report.html", ...]):  # the lock, then the manifest (old and new files) first
        output.write("report.html", text)       # staged: a synced temp file beside its target
    # leaving the block commits the set: the files it replaces are set aside, the staged ones renamed into place,
    # then the previous run's leftovers go; a failure puts the previous files back, so they stay whole

    `locked()` holds the directory's lock around a longer block (a landscape's computation), so that a second
    writer is refused when it starts rather than after its work.
    """

    def __init__(self, out: Path | str, kind: str, previous: list[str] | None):
        self.out = Path(out)
        self.kind = kind
        self.claimed = previous  # what claim_output saw: None for a new or empty directory
        self.previous = list(previous or [])
        self.planned: list[str] = []
        self.staged: dict[str, Path] = {}  # name -> its synced temp file, renamed into place by _commit
        self.folders: list[Path] = []  # folders made for staged files, removed again on a failure
        self.created = False
        self.begun = False

    def _fail(self, name: str, err: OSError) -> WriteFailed:
        why = err.strerror or str(err) or type(err).__name__
        return WriteFailed(
            f"{self.out / name}: could not be written ({why}); nothing was replaced: the files there before stay as "
            f"they were; {remedy(err)}, then run the command again"
        )

    def begin(self, planned: Iterable[str]) -> None:
        """Create the directory and write the manifest listing the previous and the planned files."""
        self.planned = list(dict.fromkeys(planned))
        self._make()
        self._manifest(sorted(set(self.previous) | set(self.planned)))
        self.begun = True

    def _manifest(self, files: list[str]) -> None:
        """The manifest, written at once (not staged): it claims the directory before any other file changes."""
        data = json.dumps(
            {"kind": self.kind, "written_by": f"riskplan {self.kind} {__version__}", "files": files}, indent=1
        )
        try:
            write_atomic(self.out / MANIFEST, data)
        except OSError as err:
            raise self._fail(MANIFEST, err) from None

    def path(self, name: str) -> contextlib.AbstractContextManager[Path]:
        """Context manager yielding a temp path to write `name` to (renamed into place when the set is committed)."""
        return _staged(self, name)

    def write(self, name: str, data: str | bytes) -> None:
        with self.path(name) as tmp:
            if isinstance(data, str):
                tmp.write_text(data, encoding="utf-8")
            else:
                tmp.write_bytes(data)

    def write_with(self, name: str, writer: Callable[[Path], object]) -> None:
        """Write `name` by calling writer(temp path), e.g. lambda p: frame_to_parquet(table, p)."""
        with self.path(name) as tmp:
            writer(tmp)

    @contextlib.contextmanager
    def locked(self):
        """Hold the directory's lock for the block (making the directory when missing; re-entrant): another writer
        is refused from now on, naming this process. The directory must still be as claim_output found it. On a
        failure, a directory this command made is removed again when it holds nothing else."""
        try:
            self._make()
            with lock.hold_lock(self.out, f"{self.kind} directory"):
                try:
                    self._check_unchanged()
                    yield self
                except BaseException:
                    self.abandon()  # under the lock: its file is this process's to remove
                    raise
        except BaseException:
            self.abandon()  # outside the lock (refused, say): a lock file there is another's, and stays
            raise

    @contextlib.contextmanager
    def writing(self, names: list[str]):
        """Plan `names`, which the block writes; then commit them as one set and drop the previous run's leftovers.
        A failure leaves the directory as it was, and is one WriteFailed line (a full disk, ...)."""
        with self.locked():
            try:
                self.begin(names)
                yield self
                self._commit()
            except BaseException as err:
                self._discard()
                if isinstance(err, OSError) and not isinstance(err, WriteFailed):
                    raise self._fail("", err) from None
                raise
            self.finish()

    def _make(self) -> None:
        try:
            if not self.out.exists():
                self.out.mkdir(parents=True)
                self.created = True
        except FileExistsError as err:  # another writer made it meanwhile: its lock then refuses one of the two
            if not self.out.is_dir():
                raise self._fail("", err) from None
        except OSError as err:
            raise self._fail("", err) from None

    def _check_unchanged(self) -> None:
        """Under the lock: the directory is as claim_output found it. Another riskplan of this kind that wrote into
        it meanwhile would otherwise have its files mixed with this one's, or lost."""
        files, dirs = _entries(self.out)
        if self.claimed is None:
            changed = bool([f for f in files if not _is_temp(f)] or dirs)
        else:
            manifest = read_manifest(self.out)
            listed = manifest.get("files") if isinstance(manifest, dict) else None
            changed = not isinstance(listed, list) or {f for f in listed if _safe(f)} != set(self.claimed)
        if changed:
            raise BadInput(
                str(self.out),
                f"was written by another riskplan {self.kind} while this one ran; run the command again (it "
                f"replaces that output) or give another directory",
            )

    def _commit(self) -> None:
        """Every staged file renamed into place, once every file it replaces has been set aside (the last file
        written, such as a landscape's status.json, is placed last). A reader meanwhile finds old files or new
        ones, never both; on a failure the new ones go and the old ones come back."""
        aside: list[tuple[Path, Path]] = []  # (target, where its previous file was set aside)
        placed: list[Path] = []
        name = ""
        try:
            for name in self.staged:
                target = self.out / name
                if target.exists() or target.is_symlink():
                    backup = target.with_name(temp_name(f"{target.name}.old", os.getpid()))
                    os.replace(target, backup)
                    aside.append((target, backup))
            for name, tmp in self.staged.items():
                os.replace(tmp, self.out / name)
                placed.append(self.out / name)
        except BaseException as err:
            for target in placed:
                with contextlib.suppress(OSError):
                    target.unlink()
            for target, backup in reversed(aside):
                with contextlib.suppress(OSError):
                    os.replace(backup, target)
            if isinstance(err, OSError):
                raise self._fail(name, err) from None
            raise
        self.staged.clear()
        for _, backup in aside:
            with contextlib.suppress(OSError):
                backup.unlink()

    def _discard(self) -> None:
        """After a failure: the staged files and the folders made for them removed, and the manifest as it was
        (none where there was none)."""
        for tmp in self.staged.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.staged.clear()
        for folder in reversed(self.folders):
            with contextlib.suppress(OSError):
                folder.rmdir()
        if self.begun:
            with contextlib.suppress(OSError):
                if self.claimed is None:
                    (self.out / MANIFEST).unlink()
                else:
                    self._manifest(sorted(self.claimed))

    def finish(self) -> None:
        """Remove files of the previous run that this one did not write again; the manifest lists this run's."""
        for name in set(self.previous) - set(self.planned):
            target = self.out / name
            if _safe(name) and target.is_file() and not target.is_symlink():
                with contextlib.suppress(OSError):
                    target.unlink()
        with contextlib.suppress(OSError):  # the new set is in place; a manifest listing more still claims it
            self._manifest(sorted(self.planned))

    def abandon(self) -> None:
        """After a failure: a directory this run created and left empty is removed, with what this run wrote there:
        its manifest, and the lock file only while this process holds it. A writer that made the directory but lost
        its lock to another (two runs into one new --out) leaves it, with the winner's lock and manifest, alone."""
        if not self.created:
            return
        self.created = False  # once: later, the directory may be another writer's
        mine = {MANIFEST} if self.begun else set()
        with contextlib.suppress(OSError):
            left = set(os.listdir(self.out))
            if left - mine - {lock.LOCK}:
                return
            if lock.LOCK in left and not lock.remove_held(self.out):
                return  # another process's lock: the directory is its now
            for name in left & mine:
                (self.out / name).unlink()
            self.out.rmdir()


@contextlib.contextmanager
def _staged(output: Output, name: str):
    """A temp path beside `name`'s target, synced when the block succeeds and kept for Output._commit; removed
    when it fails (WriteFailed naming the file)."""
    target = output.out / name
    tmp = target.with_name(temp_name(target.name, os.getpid()))
    try:
        missing = [p for p in target.parents if output.out in p.parents and not p.exists()]
        for folder in reversed(missing):
            folder.mkdir()
            output.folders.append(folder)
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(err, OSError) and not isinstance(err, WriteFailed):
            raise output._fail(name, err) from None
        raise
    output.staged[name] = tmp
