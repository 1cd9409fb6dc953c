"""The kernel objects: formulas against tinygp and 50 digits, derivatives, names, one source."""

import dataclasses
import io
import re
import tokenize
from pathlib import Path

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest
from tinygp import kernels as tinygp_kernels
from tinygp import transforms

import safestab.learning as learning
from safestab import ParameterError
from safestab.learning import GaussianProcessModel, Matern52, SparseGP, SquaredExponential
from safestab.learning.kernels import KERNEL_NAMES, KERNELS, StationaryKernel, as_kernel

SRC = Path(__file__).resolve().parents[1] / "src" / "safestab"
# squared scaled distances from coincident points to far in the tails (k about 1e-13)
R2 = np.concatenate([[0.0, 1e-300, 1e-20, 1e-8], np.geomspace(1e-4, 60.0, 60)])


def _mp_of_r2(name, r2):
    """The unit-amplitude kernel at ``r2`` (an mp number) in mpmath (independent)."""
    if name == "se":
        return mp.exp(-r2 / 2)
    t = mp.sqrt(5 * r2)
    return (1 + t + t * t / 3) * mp.exp(-t)


def _mp_exact(x):
    """An mp number equal to the float64 or longdouble ``x``: its float64 head and tail."""
    hi = np.float64(x)
    return mp.mpf(float(hi)) + mp.mpf(float(np.float64(x - type(x)(hi))))


def _tinygp_own(name, amp, ls):
    """tinygp's own ExpSquared, or its Matern52 with the Euclidean distance."""
    base = (
        tinygp_kernels.ExpSquared()
        if name == "se"
        else tinygp_kernels.Matern52(distance=tinygp_kernels.distance.L2Distance())
    )
    return amp**2 * transforms.Linear(1.0 / ls, base)


#: A tinygp kernel's matrix as one compiled program (the kernel is a pytree argument): called
#: eagerly, tinygp's vmaps compile each of their operations for its shapes.
_matrix = jax.jit(lambda k, x1, x2: k(x1, x2))
#: The kernel's formula and its derivative as compiled programs (the kernel a static value).
_of_r2 = jax.jit(lambda r2, kernel: kernel.of_r2(r2), static_argnames="kernel")
_d_of_r2 = jax.jit(lambda r2, kernel: kernel.d_of_r2(r2), static_argnames="kernel")


def test_the_registry_names_each_kernel_once_and_the_objects_are_static_values():
    assert KERNEL_NAMES == ("se", "matern52")
    assert [type(k) for k in KERNELS] == [SquaredExponential, Matern52]
    for k in KERNELS:
        assert as_kernel(k.name) == k and as_kernel(k) is k
        # equal, hashable values: a static jit argument compiles once per kernel
        assert type(k)() == k and hash(type(k)()) == hash(k)
    assert SquaredExponential() != Matern52()
    f = jax.jit(lambda r2, kernel: kernel.of_r2(r2), static_argnames="kernel")
    assert float(f(jnp.asarray(0.0), kernel=Matern52())) == 1.0
    assert {"Matern52", "SquaredExponential", "StationaryKernel"} <= set(learning.__all__)


@pytest.mark.parametrize("kernel", KERNELS, ids=KERNEL_NAMES)
def test_of_r2_equals_tinygps_own_kernel_matrix(kernel):
    rng = np.random.default_rng(3)
    x1, x2 = rng.uniform(-3, 3, (40, 3)), rng.uniform(-3, 3, (30, 3))
    x2[:5] = x1[:5]  # coincident points: r2 = 0
    amp, ls = 1.7, np.array([0.4, 1.3, 2.5])
    want = np.asarray(_matrix(_tinygp_own(kernel.name, amp, jnp.asarray(ls)), x1, x2))
    ours = np.asarray(_matrix(kernel.tinygp(amp, jnp.asarray(ls)), x1, x2))
    r2 = np.sum(((x1[:, None] - x2[None]) / ls) ** 2, -1)
    direct = amp**2 * np.asarray(_of_r2(r2, kernel=kernel))
    # tinygp's Matern forms sqrt(5) sqrt(r2) where the objects take sqrt(5 r2), and the
    # distances are rounded differently: a few ulp of amp^2, well above 1e-15
    np.testing.assert_allclose(ours, want, rtol=0, atol=1e-14 * amp**2)
    np.testing.assert_allclose(direct, want, rtol=0, atol=1e-14 * amp**2)
    np.testing.assert_array_equal(np.diag(ours[:5, :5]), amp**2)


@pytest.mark.parametrize("dtype", [np.float64, np.longdouble])
@pytest.mark.parametrize("xp", [jnp, np], ids=["jax", "numpy"])
@pytest.mark.parametrize("kernel", KERNELS, ids=KERNEL_NAMES)
def test_of_r2_against_50_digits(kernel, xp, dtype):
    if xp is jnp and dtype is np.longdouble:
        pytest.skip("JAX has no extended precision")
    eps = float(np.finfo(dtype).eps)
    if dtype is np.longdouble and eps >= np.finfo(np.float64).eps:
        pytest.skip("longdouble is float64 on this platform")
    # r2 with digits beyond float64 where the dtype has them
    r2 = R2.astype(dtype) * (1 + dtype(eps) * 3)
    got = np.asarray(kernel.of_r2(xp.asarray(r2), xp))
    assert got.dtype == dtype
    worst = 0.0
    with mp.workdps(50):
        for r, k in zip(r2, got, strict=True):
            exact_r2 = _mp_exact(r)
            ref = _mp_of_r2(kernel.name, exact_r2)
            t = float(mp.sqrt(5 * exact_r2))
            # exp's and the factors' few roundings, and sqrt(5 r2)'s two carried through
            # exp(-t) (about t ulp): 4 (1 + t) ulp holds; a float64 constant in the
            # longdouble formula (sqrt(5) or 5/3 rounded at 1e-16) is 1,000 times this
            err = float(abs(_mp_exact(k) - ref) / ref) / eps
            assert err <= 4 * (1 + t), (float(exact_r2), err)
            worst = max(worst, err)
    assert worst > 0  # the dtype's rounding is seen: not evaluated in a higher precision


@pytest.mark.parametrize("kernel", KERNELS, ids=KERNEL_NAMES)
def test_d_of_r2_against_jax_grad_and_50_digits(kernel):
    r2 = R2[R2 > 1e-10]
    got = np.asarray(_d_of_r2(r2, kernel=kernel))
    auto = np.asarray(jax.jit(jax.vmap(jax.grad(kernel.of_r2)))(jnp.asarray(r2)))
    # two float64 evaluations of the same derivative, a few ulp times (1 + t) apart where
    # r2 >= 1e-4; below, autodiff's Matern cancels (about u / t relative; 6e-13 at 1e-8)
    # and the 50-digit check below is the one that holds
    far = r2 >= 1e-4
    np.testing.assert_allclose(got[far], auto[far], rtol=1e-13)
    with mp.workdps(50):
        for r, d in zip(r2, got, strict=True):
            ref = mp.diff(lambda s: _mp_of_r2(kernel.name, s), mp.mpf(float(r)))
            assert abs(float((mp.mpf(float(d)) - ref) / ref)) <= 1e-14 * (1 + np.sqrt(5 * r))
    # at r2 = 0 the derivative is the limit (-1/2, -5/6)
    assert float(_d_of_r2(0.0, kernel=kernel)) == {"se": -0.5, "matern52": -5 / 6}[kernel.name]


@pytest.mark.parametrize("kernel", KERNELS, ids=KERNEL_NAMES)
def test_the_kernel_matrix_is_differentiable_at_coincident_inputs(kernel):
    """Gradients of the tinygp kernel in its inputs and lengthscales are finite where two
    inputs coincide (the likelihood's diagonal), as tinygp's own kernels'."""
    x = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (6, 2)))

    def total(log_ls, x):
        return jnp.sum(kernel.tinygp(1.0, jnp.exp(log_ls))(x, x))

    def total_tinygp(log_ls, x):
        return jnp.sum(_tinygp_own(kernel.name, 1.0, jnp.exp(log_ls))(x, x))

    for argnum in (0, 1):
        g = jax.jit(jax.grad(total, argnum))(jnp.zeros(2), x)
        want = jax.jit(jax.grad(total_tinygp, argnum))(jnp.zeros(2), x)
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, want, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("bad", ["rbf", "SE", 3, None, tinygp_kernels.ExpSquared()], ids=repr)
def test_as_kernel_names_the_argument_what_it_got_and_what_it_expects(bad):
    pattern = (
        r"kernel must be one of 'se', 'matern52' or a StationaryKernel such as "
        r"SquaredExponential\(\) or Matern52\(\), got " + re.escape(repr(bad))
    )
    with pytest.raises(ParameterError, match=pattern):
        as_kernel(bad)
    with pytest.raises(ParameterError, match=pattern):
        GaussianProcessModel(kernel=bad)
    with pytest.raises(ParameterError, match=pattern):
        SparseGP(kernel=bad)


def test_a_kernel_the_models_cannot_store_by_name_is_refused():
    @dataclasses.dataclass(frozen=True)
    class Rational(SquaredExponential):  # a new formula under a name the models know
        def of_r2(self, r2, xp=jnp):
            return 1 / (1 + r2 / 2)

    with pytest.raises(ParameterError, match=r"StationaryKernel.*got .*Rational\(\)"):
        GaussianProcessModel(kernel=Rational())


def test_a_kernel_object_fits_the_same_gp_as_its_name():
    rng = np.random.default_rng(5)
    x = rng.uniform(-2, 2, (40, 2))
    y = np.stack([np.sin(x[:, 0]), x[:, 0] * x[:, 1]], 1) + 0.05 * rng.normal(size=(40, 2))
    xq = rng.uniform(-2.5, 2.5, (9, 2))
    for kernel in KERNELS:
        by_object = GaussianProcessModel(kernel=kernel, n_restarts=0).fit(x, y)
        by_name = GaussianProcessModel(kernel=kernel.name, n_restarts=0).fit(x, y)
        assert by_object.kernel == kernel.name  # the name is what the model stores and saves
        for a, b in zip(
            by_object.predict(xq, return_std=True),
            by_name.predict(xq, return_std=True),
            strict=True,
        ):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(by_object.lengthscale_, by_name.lengthscale_)
    assert SparseGP(kernel=Matern52()).kernel == "matern52"


# The kernels' formulas as code could write them (comments and strings are not searched):
# SE's exp(-r2/2), Matern's sqrt(5 r2) (or a sqrt(5) constant), t^2/3 and its 5/3 or 5/6, and
# tinygp's own stationary kernels built directly.
FORMULA_PATTERNS = {
    "exp(-0.5 *": r"exp\(\s*-\s*0?\.5\s*\*",
    "exp(-r2 / 2": r"exp\(\s*-\s*r2\s*/\s*2\b",
    "sqrt(5": r"sqrt\(\s*(\w+\()?\s*5\b",
    "5 * r2": r"\b5(\.0)?\s*\*\s*r2\b",
    "t * t / 3": r"\b(\w+)\s*\*\s*\1\s*/\s*3\b",
    "5 / 3 or 5 / 6": r"\b5(\.0)?\s*/\s*[36]\b",
    "tinygp kernel": r"kernels\.(ExpSquared|Matern\d+)\(",
}


def _code_only(text):
    """``text`` with its comments and strings (docstrings included) blanked out."""
    offsets = np.cumsum([0] + [len(line) for line in text.splitlines(keepends=True)])
    chars = list(text)
    prose = {tokenize.COMMENT, tokenize.STRING, getattr(tokenize, "FSTRING_MIDDLE", -1)}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type in prose:
            start = offsets[tok.start[0] - 1] + tok.start[1]
            end = offsets[tok.end[0] - 1] + tok.end[1]
            chars[start:end] = [c if c == "\n" else " " for c in chars[start:end]]
    return "".join(chars)


def _formula_hits(text):
    code = _code_only(text)
    return sorted(name for name, p in FORMULA_PATTERNS.items() if re.search(p, code))


def test_the_kernel_formulas_are_written_only_in_kernels_py():
    own = SRC / "learning" / "kernels.py"
    # the patterns find the formulas where they are, so finding none elsewhere means something
    assert {"exp(-0.5 *", "5 * r2", "t * t / 3", "5 / 3 or 5 / 6"} <= set(
        _formula_hits(own.read_text())
    )
    elsewhere = {
        str(path.relative_to(SRC)): _formula_hits(path.read_text())
        for path in sorted(SRC.rglob("*.py"))
        if path != own
    }
    assert {path: hits for path, hits in elsewhere.items() if hits} == {}


@pytest.mark.parametrize(
    "code",
    [
        "k = amp**2 * jnp.exp(-0.5 * r2)",
        "return dtype(amp) ** 2 * np.exp(-r2 / 2)",
        "t = np.sqrt(dtype(5) * r2)",
        "r = jnp.sqrt(5.0 * r2)",
        "s5 = np.sqrt(5.0)",
        "k0 = (1.0 + r + r * r / 3.0) * e",
        "return amp**2 * (1.0 + s5 * r + 5.0 / 3.0 * r2) * jnp.exp(-s5 * r)",
        "dk0 = (5.0 / 3.0) * (1.0 + r) * e",
        "base = kernels.Matern52(distance=kernels.distance.L2Distance())",
    ],
)
def test_the_formula_check_finds_the_forms_the_kernels_had(code):
    assert _formula_hits(code), code


def test_the_formula_check_skips_prose_and_other_exponentials():
    text = 'bump = jnp.exp(-r2 / (2 * L * L))  # not exp(-0.5 * r2)\n"""t = sqrt(5 r2)"""\n'
    assert _formula_hits(text) == []


def test_stationary_kernel_is_abstract():
    with pytest.raises(TypeError):
        StationaryKernel()  # type: ignore[abstract]
