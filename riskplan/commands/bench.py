"""`riskplan bench`: the speed and memory targets, each printed with its baseline (the measures are riskplan.bench's)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    """Add `riskplan bench` to the CLI."""

    @app.command()
    def bench(
        quick: bool = typer.Option(False, "--quick", help="Fewer repeats and a shorter training run (about 15 s)."),
        json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the figures to this JSON file."),
    ) -> None:
        """Speed, memory, JIT and team-scaling targets, each with a baseline measured in the same run."""
        import numba
        from rich.console import Console

        from riskplan.bench import bench_checkpoints, bench_jit, bench_rollout, bench_team, bench_training

        console = Console(soft_wrap=True)  # one line per figure, also in a log file
        console.print(f"numba {numba.__version__}, {numba.get_num_threads()} threads "
                      f"({numba.config.THREADING_LAYER} layer), {os.cpu_count()} cores")
        rows: list[dict] = []
        for section in (lambda: bench_rollout(quick), lambda: bench_training(quick),
                        lambda: bench_checkpoints(quick), bench_jit, lambda: bench_team(quick)):
            for row in section():  # printed as each section ends: the whole benchmark takes ~20 s
                mark = "met" if row["ok"] else "NOT MET"
                console.print(f"[bold]{row['measure']}[/bold]: {row['value']:.4g} {row['unit']}  "
                              f"(target {row['target']}: {mark})")
                console.print(f"    baseline {row['baseline']:.4g}, ratio {row['ratio']:.3g}; {row['note']}")
                rows.append(row)
        if json_out:
            json_out.write_text(json.dumps(rows, indent=2, default=float))
