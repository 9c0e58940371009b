"""The fit: prepare a trace, build the regression system, select the law, profile, read out."""
