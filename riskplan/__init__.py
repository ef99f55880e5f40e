"""riskplan: risk-averse sensor planning with distributed CVaR policy gradients."""

__version__ = "0.1.0"
