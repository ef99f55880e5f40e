"""The world as Gymnasium and PettingZoo environments; imported as `riskplan.envs`."""
