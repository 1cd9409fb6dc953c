import numpy as np
import pytest
import scipy.stats

from safestab.errors import ParameterError
from safestab.montecarlo import clopper_pearson


@pytest.mark.parametrize("n", [1, 2, 7, 50, 1000])
@pytest.mark.parametrize("confidence", [0.9, 0.95, 0.99])
def test_clopper_pearson_matches_scipy_binomtest(n, confidence):
    for k in sorted({0, 1, n // 3, n // 2, n - 1, n}):
        ref = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=confidence, method="exact")
        lo, hi = clopper_pearson(k, n, confidence)
        # both are beta quantiles from scipy; they agree to the root finder's rounding
        assert lo == pytest.approx(ref.low, abs=1e-12)
        assert hi == pytest.approx(ref.high, abs=1e-12)


def test_clopper_pearson_edges_and_monotone():
    assert clopper_pearson(0, 10)[0] == 0.0
    assert clopper_pearson(10, 10)[1] == 1.0
    # closed form at k = 0: high = 1 - (alpha/2)^(1/n)
    assert clopper_pearson(0, 10)[1] == pytest.approx(1 - 0.025 ** (1 / 10), rel=1e-12)
    lows = [clopper_pearson(k, 20)[0] for k in range(21)]
    assert np.all(np.diff(lows) > 0)


@pytest.mark.parametrize(
    "args, match",
    [
        ((3, 2), "need 0 <= successes <= trials"),
        ((-1, 2), "need 0 <= successes <= trials"),
        ((0, 0), "trials >= 1"),
        ((1.5, 2), "successes must be an integer"),
        ((1, True), "trials must be an integer"),
        ((1, 2, 1.0), r"confidence must be in \(0, 1\)"),
        ((1, 2, 0.0), r"confidence must be in \(0, 1\)"),
    ],
)
def test_clopper_pearson_rejects_bad_input(args, match):
    with pytest.raises(ParameterError, match=match):
        clopper_pearson(*args)
