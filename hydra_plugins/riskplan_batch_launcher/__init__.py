"""riskplan's batch launcher for Hydra (`riskplan sweep --batch`): see batch_launcher."""
