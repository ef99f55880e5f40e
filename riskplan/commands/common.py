"""What every command shares: one-line usage errors, the bad-input and run-time error exits, Hydra pass-through."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import typer
from typer.core import TyperGroup

from riskplan.config.user_files import check_config_files
from riskplan.util.errors import BadInput, remedy
from riskplan.util.interrupt import Interrupted
from riskplan.util.paths import check_decoded, hydra_quote

# typer vendors click in recent releases and depends on it in older ones: find click's base exception either way
ClickException = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class OneLineErrors(TyperGroup):
    """Click's usage errors (unknown command, missing option value, ...) as one plain line, exit code 2."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            _check_decoded_arguments(sys.argv[1:] if args is None else args)
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except BadInput as err:
            typer.echo(f"error: {err}", err=True)
            code = 2
        except ClickException as err:
            if type(err).__name__ == "NoArgsIsHelpError":  # bare `riskplan`: the help, as click shows it
                err.show()
            else:
                where = err.ctx.command_path if getattr(err, "ctx", None) else self._path(prog_name, args)
                message = " ".join(err.format_message().split())
                typer.echo(f"error: {where}: {message} (see {where} --help)", err=True)
            code = err.exit_code
        except typer.Abort:
            typer.echo("aborted", err=True)
            code = 1
        if not standalone_mode:
            return code
        sys.exit(code if isinstance(code, int) else 0)

    def _path(self, prog_name: str | None, args: list[str] | None) -> str:
        """The command an error without click's context belongs to ('riskplan bench' for `bench --quick=3`)."""
        args = sys.argv[1:] if args is None else list(args)
        name = prog_name or "riskplan"
        return f"{name} {args[0]}" if args and args[0] in self.commands else name

    def invoke(self, ctx):
        """A signal that stopped a command which did not answer it itself (a benchmark's scratch run, a Ctrl-C
        while it computes): one line and the shell's code for the signal, not a traceback (click answers Ctrl-C
        with a bare Abort, recent typer with a silent exit 130)."""
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            typer.echo("error: interrupted by SIGINT", err=True)
            raise typer.Exit(130) from None
        except Interrupted as stop:
            typer.echo(f"error: interrupted by {stop.name}", err=True)
            raise typer.Exit(stop.exit_code) from None


def _check_decoded_arguments(args: list[str]) -> None:
    """BadInput for an argument, or the working directory (where outputs/ goes), that holds bytes the locale could
    not decode: found before anything is written, not when a path reaches a UTF-8 file at a run's end."""
    for arg in args:
        check_decoded(arg, "argument")
    check_decoded(os.getcwd(), "the working directory")


PASS_THROUGH = {"allow_extra_args": True, "ignore_unknown_options": True}
HYDRA_FLAGS = {"--cfg", "-c", "--package", "-p", "--resolve", "--info", "-i"}
MULTIRUN_FLAGS = {"-m", "--multirun"}
OVERRIDES_HELP = (
    "Hydra overrides, e.g. risk=neutral risk.beta=0.2 train.samples=2000 world.size=[16,16] "
    "experiment=paper_team team.graph=ring."
)
TRAIN_OVERRIDES_HELP = OVERRIDES_HELP + (
    " Hydra flags --cfg job|hydra|all, --package, --resolve, --info pass through to Hydra."
)


def jobs_option(help: str):
    """--jobs / -j, shared by sweep and reproduce: a whole number from 1, or None when left out (`help` says the
    default)."""
    return typer.Option(None, "--jobs", "-j", min=1, show_default=False, help=help)


def bad_input_exits(command):
    """Turn BadInput into one line on stderr and exit code 2, and a failure to read or write files at run time
    (a full disk) into one line and exit code 1: never a traceback."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except BadInput as err:
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(2) from None
        except OSError as err:
            where = f" {err.filename}" if err.filename else ""
            typer.echo(
                f"error: cannot write{where}: {err.strerror or err}; {remedy(err)} (or give another directory), then "
                f"run the same command again: what finished is kept",
                err=True,
            )
            raise typer.Exit(1) from None

    return wrapper


CONFIG_DIR_FLAGS = ("--config-dir", "-cd")
CONFIG_DIR_HELP = (  # "\\[": rich markup would take [file://DIR] for a style tag and drop it
    " --config-dir DIR (-cd DIR) adds DIR to the config search path, after riskplan's own conf/: your own "
    "experiment=mine then loads DIR/experiment/mine.yaml (the same as hydra.searchpath=\\[file://DIR])."
)


def with_config_dirs(args: list[str]) -> list[str]:
    """Hydra's `--config-dir DIR` / `-cd DIR` (or `--config-dir=DIR`) as the override it amounts to,
    `hydra.searchpath=[file://DIR]` (merged into a hydra.searchpath the user typed): Hydra puts both after the
    primary config directory. A directory that does not exist is bad input."""
    rest, dirs, flags = [], [], iter(args)
    for arg in flags:
        flag, given, value = arg.partition("=")
        if flag not in CONFIG_DIR_FLAGS:
            rest.append(arg)
            continue
        value = value if given else next(flags, None)
        if not value:
            raise BadInput(f"option '{flag}'", "needs a directory, e.g. -cd my_configs")
        path = Path(value).expanduser().resolve()
        if not path.is_dir():
            raise BadInput(
                f"option '{flag}'",
                f"{value} is not a directory; give the folder that holds your config groups "
                f"(e.g. my_configs, with my_configs/experiment/mine.yaml)",
            )
        from riskplan.config.typed import check_file_value  # the schema imports Hydra, which --help does not

        check_config_files(path, check_file_value)
        dirs.append(hydra_quote(f"file://{path}"))
    if not dirs:
        return rest
    typed = [i for i, arg in enumerate(rest) if arg.split("=", 1)[0].lstrip("+") == "hydra.searchpath"]
    if typed:  # the user's list first, then the directories
        key, _, value = rest[typed[-1]].partition("=")
        inner = value.strip()[1:-1].strip() if value.strip().startswith("[") else value.strip()
        rest[typed[-1]] = f"{key}=[{', '.join(([inner] if inner else []) + dirs)}]"
    else:
        rest.append(f"hydra.searchpath=[{', '.join(dirs)}]")
    return rest


def reject_hydra_flags(args: list[str], instead: str) -> None:
    """Hydra's flags (--cfg, ...) belong to `train`; elsewhere they are bad input with a pointer."""
    flags = sorted(HYDRA_FLAGS & set(args))
    if flags:
        raise BadInput(f"option '{flags[0]}'", f"only riskplan train passes Hydra's flags through; {instead}")


INPUT = "a run, sweep or reproduce directory"  # what report and export read


def path_option(text: str | None, key: str, what: str = "a directory path") -> Path | None:
    """A path option or argument as typed, None when not given. Paths are taken as str, not typer's Path, which
    would turn '' into '.' (the current directory, written into or searched in silence) and drop a trailing '/'."""
    if text is None:
        return None
    if not text.strip() or "\x00" in text:
        raise BadInput(key, f"got {text!r}; give {what}")
    return Path(text)


def check_out_dir(text: str | None) -> Path | None:
    """An --out directory that exists or can be made; a file there is bad input."""
    path = path_option(text, "--out")
    if path is not None and path.exists() and not path.is_dir():
        raise BadInput("--out", f"{path} is a file; expected a directory (new, or one riskplan wrote)")
    return path
