"""The typer commands, one module per family; riskplan.cli assembles them into one app."""
