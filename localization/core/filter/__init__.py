"""The particle filter (``mcl.MonteCarloLocalizer``) and its resampling (``resampling``)."""
