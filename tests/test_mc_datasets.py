"""The Monte Carlo statistics: the data set as the unit, intervals that respect clustering,
and a claimed probability only where a controller's beta carries one (issue 27, section 2)."""

from types import SimpleNamespace

import numpy as np
import pytest

from safestab.errors import ParameterError
from safestab.montecarlo import MonteCarloSpec, clopper_pearson
from safestab.montecarlo.loop import RECORD_FIELDS
from safestab.montecarlo.runner import MonteCarloRun
from safestab.montecarlo.stats import GUARANTEES, empirical_bernstein, summarize


def test_empirical_bernstein_by_hand():
    z = np.array([1.0, 1.0, 0.5, 0.0, 1.0])
    log_term = np.log(4 / 0.05)
    var = np.sum((z - z.mean()) ** 2) / 4
    half = np.sqrt(2 * var * log_term / 5) + 7 * log_term / (3 * 4)
    assert empirical_bernstein(z) == (max(0.0, z.mean() - half), min(1.0, z.mean() + half))
    # many data sets of small spread: a narrow interval around the mean
    lo, hi = empirical_bernstein(np.full(1000, 0.9) + np.linspace(-0.01, 0.01, 1000))
    assert 0.88 < lo < 0.9 < hi < 0.92


@pytest.mark.parametrize("bad", [[0.5], [0.2, 1.5], [-0.1, 0.3]])
def test_empirical_bernstein_refuses_bad_values(bad):
    with pytest.raises(ParameterError, match=r"values must be at least 2 numbers in \[0, 1\]"):
        empirical_bernstein(bad)


def test_clustered_trials_need_the_interval_over_data_sets():
    """Trials that share a data set: pooling them as independent (the old interval) covers
    the per-trial probability far less often than 95 %; the interval over data sets covers
    it at least that often."""
    rng = np.random.default_rng(0)
    a, b, k_sets, per_set = 0.4, 0.1, 40, 10  # strongly clustered: p_j near 0 or 1
    truth = a / (a + b)
    pooled = grouped = 0
    reps = 300
    for _ in range(reps):
        p = rng.beta(a, b, k_sets)
        safe = rng.random((k_sets, per_set)) < p[:, None]
        lo, hi = clopper_pearson(int(safe.sum()), safe.size)
        pooled += lo <= truth <= hi
        lo, hi = empirical_bernstein(safe.mean(1))
        grouped += lo <= truth <= hi
    assert pooled / reps < 0.8
    assert grouped / reps >= 0.95


def _run(safe_by_set, controllers, k_sets, delta=0.01, n_comp=3):
    """A MonteCarloRun with the given per-trial safe flags (N, C) and i mod K data sets."""
    safe = np.asarray(safe_by_set, bool)
    n = safe.shape[0]
    c = len(controllers)
    records = {k: np.zeros((n, c)) for k in RECORD_FIELDS}
    records["min_h"] = np.where(safe, 1.0, -1.0)
    records["first_bad_status"] = np.zeros((n, c), int)
    gp = [i for i, name in enumerate(controllers) if name.startswith("GP")]
    records["lemma2_violations"] = np.full((n, c), -1)
    records["lemma2_violations"][:, gp] = np.where(safe[:, gp], 0, 3)
    hyper = SimpleNamespace(components=tuple(range(n_comp)))
    sets = [
        SimpleNamespace(hyper=hyper, betas={k: np.ones(3) for k in controllers},
                        held_out_coverage={k: 1.0 for k in controllers})
        for _ in range(k_sets)
    ]  # fmt: skip
    spec = MonteCarloSpec(controllers=tuple(controllers), delta=delta)
    return MonteCarloRun(
        scenario=None, study=SimpleNamespace(h_unit="m"), spec=spec, seed=0,
        controllers=tuple(controllers), records=records, dataset_index=np.arange(n) % k_sets,
        datasets=sets, backend="local", timings={},
    )  # fmt: skip


def test_summary_counts_data_sets_and_claims_only_where_a_beta_carries_one():
    names = ["true model", "GP-robust", "GP-robust Lemma 2", "GP-robust conformal"]
    k_sets, per_set = 20, 5
    rng = np.random.default_rng(1)
    safe = rng.random((k_sets * per_set, len(names))) < 0.97
    safe[:, 0] = True
    s = summarize(_run(safe, names, k_sets))
    set_of = np.arange(k_sets * per_set) % k_sets
    for c, name in enumerate(names):
        e = s["controllers"][name]
        all_safe = [safe[set_of == j, c].all() for j in range(k_sets)]
        assert e["safe_per_dataset"]["count"] == sum(all_safe)
        assert e["safe_per_dataset"]["ci95"] == list(clopper_pearson(sum(all_safe), k_sets))
        fractions = [safe[set_of == j, c].mean() for j in range(k_sets)]
        assert e["safe"]["count"] == safe[:, c].sum()
        if name != "true model":  # one value: no interval over data sets of zero spread
            assert e["safe"]["ci95"] == list(empirical_bernstein(fractions))
        assert "Bernstein" in e["safe"]["interval"]
    c = s["controllers"]
    assert c["true model"]["guarantee"] is None and c["GP-robust"]["guarantee"] is None
    lemma, conf = c["GP-robust Lemma 2"]["guarantee"], c["GP-robust conformal"]["guarantee"]
    assert lemma["claimed_probability"] == pytest.approx(0.99**3)
    assert lemma["measured_by"] == "safe_per_dataset"
    assert lemma["consistent"] == (c["GP-robust Lemma 2"]["safe_per_dataset"]["ci95"][1] >= 0.99**3)
    assert conf["claimed_probability"] == pytest.approx(0.99)
    assert conf["measured_by"] == "safe"
    assert lemma["assumptions"] == GUARANTEES["GP-robust Lemma 2"]["assumptions"]
    assert any("rkhs_norm" in a for a in lemma["assumptions"])
    assert "top" not in s and "claimed_probability" not in s  # no claim for every controller


@pytest.mark.parametrize("k_sets, word", [(1, "conditional"), (12, "one trial per data set")])
def test_per_trial_interval_is_exact_where_trials_are_independent(k_sets, word):
    safe = np.ones((12, 2), bool)
    safe[3, 1] = False
    s = summarize(_run(safe, ["true model", "GP-robust"], k_sets))
    e = s["controllers"]["GP-robust"]["safe"]
    assert word in e["interval"]
    assert e["ci95"] == list(clopper_pearson(11, 12))


def test_markdown_table_is_written_from_the_summary():
    from safestab.montecarlo.report import markdown_table

    names = ["true model", "GP-robust", "GP-robust Lemma 2"]
    safe = np.ones((30, 3), bool)
    safe[4, 1] = False  # trial 4 is in data set 4 mod 10
    s = summarize(_run(safe, names, 10))
    text = markdown_table({"summary": s})
    rows = {line.split(" | ")[0][2:]: line for line in text.splitlines()[2:]}
    assert set(rows) == set(names)
    assert "| 9/10 [" in rows["GP-robust"] and "| 10/10 [" in rows["true model"]
    assert "0.9703 (per data set)" in rows["GP-robust Lemma 2"]
    assert "0.9703" not in rows["GP-robust"] and "0.9703" not in rows["true model"]
