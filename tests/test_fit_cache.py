"""The GP fit cache (safestab/learning/_fit_cache.py): same model, nothing stale, safe to lose."""

from __future__ import annotations

import json
import os
import warnings

import numpy as np
import pytest

import safestab as ss
import safestab.learning._fit_cache as fit_cache
import safestab.learning._likelihood as likelihood
from safestab.errors import ConvergenceWarning
from safestab.learning import GaussianProcessModel

FIELDS = ("amplitude_", "noise_", "mean_", "lengthscale_", "log_marginal_likelihood_",
          "start_log_marginal_likelihoods_", "n_iter_", "converged_", "loo_coverage_",
          "alpha_")  # fmt: skip


def _data(q=60, seed=0, shift=0.0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-2, 2, (q, 2))
    y = np.stack([np.sin(x[:, 0]) + shift, 0.5 * x[:, 1]], -1) + 0.01 * rng.normal(size=(q, 2))
    return x, y


@pytest.fixture
def cache(tmp_path):
    before = ss.fit_cache_dir()
    folder = ss.enable_fit_cache(tmp_path / "fits")
    yield folder
    _restore(before)


def _restore(folder):
    if folder is None:
        ss.disable_fit_cache()
    else:
        ss.enable_fit_cache(folder)


#: L-BFGS-B runs per component: the default model's 2 data-driven and 2 random starts
STARTS = 4


@pytest.fixture
def count_optimisations(monkeypatch):
    """One entry per L-BFGS-B run (:data:`STARTS` per component optimised)."""
    calls = []
    real = likelihood.optimise_start

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(likelihood, "optimise_start", counted)
    return calls


def _same(a, b):
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert a.optimizer_status_ == b.optimizer_status_


def test_a_second_fit_reads_the_first_and_gives_the_same_model(cache, count_optimisations):
    x, y = _data()
    ss.disable_fit_cache()
    fresh = GaussianProcessModel().fit(x, y, seed=3)
    assert len(count_optimisations) == 2 * STARTS  # both components, nothing written
    assert not cache.exists() or not list(cache.glob("*.json"))
    ss.enable_fit_cache(cache)
    first = GaussianProcessModel().fit(x, y, seed=3)
    assert len(count_optimisations) == 4 * STARTS and len(list(cache.glob("*.json"))) == 2
    second = GaussianProcessModel().fit(x, y, seed=3)
    assert len(count_optimisations) == 4 * STARTS  # read back, not optimised
    _same(fresh, first)
    _same(fresh, second)


@pytest.mark.parametrize(
    "change",
    [
        lambda m, x, y: (m, x, y + np.array([1e-9, 0.0])),  # the data, in the last bits
        lambda m, x, y: (GaussianProcessModel(jitter=1e-8), x, y),  # the data, in the last bits
        lambda m, x, y: (m, x[::-1], y[::-1]),  # the same rows in another order (the subset)
        lambda m, x, y: (GaussianProcessModel(kernel="matern52"), x, y),
        lambda m, x, y: (GaussianProcessModel(n_restarts=3), x, y),
        lambda m, x, y: (GaussianProcessModel(max_iter=50), x, y),
        lambda m, x, y: (GaussianProcessModel(noise=0.01), x, y),
        lambda m, x, y: (GaussianProcessModel(mean="constant"), x, y),
    ],
)
def test_any_change_of_the_problem_misses(cache, count_optimisations, change):
    x, y = _data()
    GaussianProcessModel().fit(x, y, seed=3)
    GaussianProcessModel().fit(x, y, seed=3)  # the control: the same problem is read back
    n = len(count_optimisations)
    assert n == 2 * STARTS
    model, x2, y2 = change(GaussianProcessModel(), x, y)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(x2, y2, seed=3)
    assert len(count_optimisations) > n


def test_a_broken_entry_is_refitted_and_replaced(cache, count_optimisations):
    x, y = _data()
    first = GaussianProcessModel().fit(x, y, seed=3)
    entries = sorted(cache.glob("*.json"))
    good = [json.loads(e.read_text()) for e in entries]
    broken = [
        lambda doc: "{not json",  # unreadable
        lambda doc: json.dumps({**doc, "key": "another"}),  # another problem's
        lambda doc: "[]",  # not an entry
        lambda doc: json.dumps({**doc, "results": doc["results"][:1]}),  # too few starts
        lambda doc: json.dumps({**doc, "results": [{**r, "theta": r["theta"][:2]}
                                                   for r in doc["results"]]}),  # short theta
        lambda doc: json.dumps({**doc, "results": [{**r, "value": "0x1p99999"}
                                                   for r in doc["results"]]}),  # overflow
    ]  # fmt: skip
    for k, make in enumerate(broken):
        entries[k % 2].write_text(make(good[k % 2]))
        again = GaussianProcessModel().fit(x, y, seed=3)
        assert len(count_optimisations) == (3 + k) * STARTS
        _same(first, again)
    for e in entries:
        assert json.loads(e.read_text())["key"] == e.stem


def test_warnings_of_a_fit_are_given_again_from_the_cache(cache):
    """A fit that did not converge warns on a cache hit too (the results are replayed)."""
    x, y = _data()
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        GaussianProcessModel(max_iter=2).fit(x, y, seed=3)
    with pytest.warns(ConvergenceWarning, match="did not converge"):
        GaussianProcessModel(max_iter=2).fit(x, y, seed=3)


def test_an_unwritable_folder_only_costs_time(tmp_path, count_optimisations):
    blocker = tmp_path / "file"
    blocker.write_text("")
    before = ss.fit_cache_dir()
    ss.enable_fit_cache(blocker / "fits")  # its parent is a file: cannot be created
    try:
        x, y = _data()
        a = GaussianProcessModel().fit(x, y, seed=3)
        b = GaussianProcessModel().fit(x, y, seed=3)
        assert len(count_optimisations) == 4 * STARTS
        _same(a, b)
    finally:
        _restore(before)
    assert not list(tmp_path.rglob("*.tmp"))


def test_environment_and_command_line_switches(tmp_path, monkeypatch):
    before = ss.fit_cache_dir()
    try:
        _switches(tmp_path, monkeypatch)
    finally:
        _restore(before)


def _switches(tmp_path, monkeypatch):
    monkeypatch.setenv("SAFESTAB_FIT_CACHE", "off")
    assert fit_cache.configure_fit_cache_from_environment() is None
    assert ss.fit_cache_dir() is None
    monkeypatch.setenv("SAFESTAB_FIT_CACHE", str(tmp_path / "here"))
    assert fit_cache.configure_fit_cache_from_environment() == tmp_path / "here"
    monkeypatch.setenv("SAFESTAB_FIT_CACHE", "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert fit_cache.configure_fit_cache_from_environment() == tmp_path / "xdg/safestab/fits"
    ss.disable_fit_cache()
    from typer.testing import CliRunner

    from safestab.cli import app

    ss.enable_fit_cache(tmp_path / "cli")
    monkeypatch.setenv("SAFESTAB_FIT_CACHE", str(tmp_path / "cli"))
    result = CliRunner().invoke(app, ["--no-fit-cache", "run", "--help"])
    assert ss.fit_cache_dir() is None, result.output
    assert os.environ["SAFESTAB_FIT_CACHE"] == "off"  # for worker processes
