"""The names of the merge's algorithmic choices, in a module that imports nothing, so that
the command line lists them (``merge --help``) without importing the code behind them
(NumPy, Numba, SciPy).  The implementing modules take their names from here; a test checks
:data:`WEIGHTINGS` against :data:`hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`."""

#: weighting functions ``w(z)`` of (7) (:data:`hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`)
WEIGHTINGS = ("triangle", "mann", "deneve", "gaussian", "uniform", "probabilistic", "direct", "optimal", "bounded")

#: choices for the variance factor ``sigma^-2(E, t_j)`` of (7)
VARIANCE_FACTORS = ("none", "photon", "codes", "model")
