"""Hydra's multirun, launched in this process, its printed output going to sweep.log."""

from __future__ import annotations

from pathlib import Path




def launch(argv: list[str], log_file: Path) -> str | None:
    """Run Hydra's multirun, its printed output going to sweep.log; return the launcher's error, if any."""
    import contextlib

    from riskplan.app import run_hydra

    with open(log_file, "a", buffering=1) as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            run_hydra(argv)
        except SystemExit as stop:  # Hydra prints an exception in the launcher, then exits 1
            if stop.code not in (0, None):
                return _launcher_error(log_file)
        except KeyboardInterrupt:
            return "interrupted (Ctrl-C)"
        except Exception as err:  # noqa: BLE001 - the jobs' own records say what finished
            import traceback

            traceback.print_exc()
            return f"the launcher stopped: {type(err).__name__}: {err} (see {log_file})"
    return None


def _launcher_error(log_file: Path) -> str:
    """The last line of the error Hydra printed into sweep.log."""
    try:
        lines = [line.strip() for line in log_file.read_text().splitlines() if line.strip()]
    except OSError:
        lines = []
    errors = [line for line in lines if "Error" in line.split(":")[0] or "Exception" in line.split(":")[0]]
    last = errors[-1] if errors else (lines[-1] if lines else "no message")
    return f"the launcher stopped: {last[:300]} (see {log_file})"
