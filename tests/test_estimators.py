"""scikit-learn's estimator checks on the kriging GP and the two bias models built on it.

The checks fit on sklearn's small synthetic data sets (up to 200 rows, 10 inputs), so the instances here use one
likelihood start and no minimum cluster size; every other setting is the default.
"""

from __future__ import annotations

import operator

import numpy as np
import pytest
from sklearn.utils.estimator_checks import parametrize_with_checks

from crashfuse.gp.kriging import KrigingGP
from crashfuse.method.mixture import GMMGPBias
from crashfuse.method.onset import OnsetCorrectedBias


class OnsetOnRowBlocks(OnsetCorrectedBias):
    """:class:`OnsetCorrectedBias` given five blocks of consecutive rows as its tests when ``fit`` gets no groups.

    The onset correction is fitted on leave-one-test-out residuals, so ``fit`` requires ``groups``; sklearn's
    checks call ``fit(X, y)``. Everything else is the class under test.
    """

    def fit(self, X, y, groups=None):
        if groups is None and y is not None:
            n = len(np.asarray(y))
            groups = np.arange(n) * 5 // max(n, 1)
        return super().fit(X, y, groups)


def _bias_model():
    # min_cluster_points=1: the default (3 points per GP parameter, 39 in 10-D) exceeds most check data sets.
    return GMMGPBias(n_restarts=0, min_cluster_points=1, random_state=0)


ESTIMATORS = [
    KrigingGP(n_restarts=0, random_state=0),
    _bias_model(),
    # time: the first input; the window keeps the correction on the rows where it is below 0.5; both
    # corrections on, as in the state default.
    OnsetOnRowBlocks(base=_bias_model(), time=operator.itemgetter((slice(None), 0)), window=(0.0, 0.5),
                     shrink_width=0.1),
]


# Every check applies and passes; sklearn itself skips check_array_api_input (the estimators are NumPy and
# LAPACK code and declare no array API support).
@parametrize_with_checks(ESTIMATORS)
def test_sklearn_estimator_checks(estimator, check):
    check(estimator)


def _plain(value):
    """Whether ``value`` is data a model file can store field by field: arrays, numbers, strings, containers of
    them, or an estimator whose own ``__dict__`` is plain."""
    if value is None or isinstance(value, (str, bytes, bool, int, float, np.generic, np.ndarray)):
        return True
    if isinstance(value, (list, tuple)):
        return all(_plain(v) for v in value)
    if isinstance(value, dict):
        return all(_plain(k) and _plain(v) for k, v in value.items())
    if hasattr(value, "get_params"):
        return all(_plain(v) for k, v in vars(value).items() if k != "time")  # the onset model's time map is a setting
    return False


def test_fitted_state_is_plain_data():
    """No closures, bound methods or other callables among the fitted attributes, at any depth."""
    X = np.random.default_rng(0).uniform(size=(60, 2))
    y = np.sin(3 * X[:, 0]) + X[:, 1]
    model = ESTIMATORS[2].fit(X, y, np.repeat(np.arange(6), 10))
    assert model.onset_gp_ is not None and model.shrink_ is not None and _plain(model)
    assert not _plain({"f": np.sin})


@pytest.mark.parametrize("method", ["predict", "predict_cov", "sample_functions"])
def test_kriging_refuses_another_feature_count(method):
    X = np.random.default_rng(0).uniform(size=(20, 2))
    gp = KrigingGP(n_restarts=0, random_state=0).fit(X, X.sum(axis=1))
    with pytest.raises(ValueError, match="X has 3 features, but KrigingGP is expecting 2"):
        getattr(gp, method)(np.ones((4, 3)))
