"""The `riskplan` command line: one typer app, assembled here from the command modules (nothing imports this one).

Bad input: one plain line on stderr and exit code 2; a failure at run time: one line and exit code 1.
"""

from __future__ import annotations

import inspect
import sys
import warnings

import typer

from riskplan.commands import bench, check, export, report, reproduce, sweep, train
from riskplan.commands.common import OneLineErrors
from riskplan.util.blas_threads import single_threaded_blas
from riskplan.util.collector import command_line_process
from riskplan.util.errors import BadInput
from riskplan.util.limits import check_numba_threads

app = typer.Typer(
    cls=OneLineErrors,
    name="riskplan",
    help="Risk-averse sensor planning with (distributed) CVaR policy gradients: train, sweep, report, reproduce.",
    no_args_is_help=True,
    add_completion=True,  # riskplan --install-completion [bash|zsh|fish|powershell]
    pretty_exceptions_enable=False,
)
warnings.formatwarning = lambda message, *args, **kwargs: f"warning: {message}\n"  # one plain line, no path


def _register_commands() -> None:
    """Add every command, in the order `riskplan --help` lists them, each listed by its docstring's first paragraph
    as one flowing line (rich markup keeps a docstring's line breaks there, which broke sentences mid-line)."""
    for module in (train, check, report, bench, sweep, reproduce, export):
        module.register(app)
    for command in app.registered_commands:
        if command.short_help is None and command.callback.__doc__:
            command.short_help = " ".join(inspect.cleandoc(command.callback.__doc__).split("\n\n")[0].split())


_register_commands()


def main() -> None:
    """Entry point of the `riskplan` script and `python -m riskplan`."""
    single_threaded_blas()  # before numpy loads: riskplan.util.blas_threads
    try:
        check_numba_threads()  # before numba loads, which would fail with a traceback
    except BadInput as err:
        typer.echo(f"error: {err}", err=True)
        raise SystemExit(2) from None
    command_line_process()
    app(prog_name="riskplan")


if __name__ == "__main__":
    sys.exit(main())
