"""`python -m riskplan`: the same command line as the `riskplan` script."""

from riskplan.cli import main

main()
