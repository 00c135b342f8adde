"""Universal kriging (a Gaussian process with a GLS trend) split by job; :class:`crashfuse.gp.kriging.KrigingGP` is
the estimator that composes them.

``kernels`` correlation, trend basis, nugget factorisation ; ``likelihood`` concentrated likelihood and gradient,
GLS ; ``optimise`` restarts, bounds, theta bound by grouped CV ; ``subsets`` hyperparameter-fit and conditioning
rows ; ``posterior`` conditioning and predictive equations ; ``grouped`` leave-one-test-out residuals, CV density,
band calibration, test-to-test scatter ; ``sampling`` joint draws ; ``threads`` BLAS thread control.
"""
