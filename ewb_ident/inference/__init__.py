"""Fitting and uncertainty: least squares, the posterior, priors, start values, comparison of
fits, validation on another trace."""
