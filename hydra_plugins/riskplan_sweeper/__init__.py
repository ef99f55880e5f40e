"""riskplan's sweeper for Hydra (`riskplan sweep` on a grid): see plan_sweeper."""
