"""Risk measures as objects: `base` says what a measure is, each built-in measure has its own module, `spectral`
holds the measures given by a distortion function (riskplan.risk.distortion), and `registry` finds a measure by
its name, built in or from an installed package's entry point (group `riskplan.risk_measures`)."""
