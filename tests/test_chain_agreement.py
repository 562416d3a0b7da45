"""The chain benchmark's variants agree: lieax (every mode), hand-written and jaxlie give the same
values and Jacobians to 1e-10, on the very functions that `benchmarks/chain.py` times.

Also checks the hand-written closed form against central finite differences of the chain, so that
the floor the benchmark compares against is itself right, and runs the benchmark's `main` on tiny
sizes so that it cannot rot.
"""

import importlib.util
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

BENCHMARKS = pathlib.Path(__file__).resolve().parent.parent / "benchmarks"


def _load_chain():
    sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("lieax_bench_chain", BENCHMARKS / "chain.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


chain = _load_chain()

TOLERANCE = 1e-10
CHAINS = 4


@pytest.mark.parametrize("group", ["SO3", "SE3"])
@pytest.mark.parametrize("length", [1, 3])  # a first, an interior and a last element
def test_chain_variants_agree(group, length):
    params, v = chain.chain_inputs(jax.random.PRNGKey(length), group, CHAINS, length)
    variants = chain.CHAIN_VARIANTS[group]
    y_ref, J_ref = chain.batched(variants[chain.HAND])(params, v)
    tangent_dim = {"SO3": 3, "SE3": 6}[group]
    assert J_ref.shape == (CHAINS, length, 3, tangent_dim)
    for name, fn in variants.items():
        y, J = chain.batched(fn)(params, v)
        assert J.shape == J_ref.shape, name
        np.testing.assert_allclose(y, y_ref, rtol=0, atol=TOLERANCE, err_msg=name)
        np.testing.assert_allclose(J, J_ref, rtol=0, atol=TOLERANCE, err_msg=name)


@pytest.mark.parametrize("group", ["SO3", "SE3"])
def test_hand_written_chain_matches_finite_differences(group):
    """Central differences of `y(X_i ⊕ δ e_k)` with lieax's rplus, in float64."""
    length = 3
    params, v = chain.chain_inputs(jax.random.PRNGKey(10), group, 1, length)
    params, v = params[0], v[0]
    cls = {"SO3": chain.lieax.SO3, "SE3": chain.lieax.SE3}[group]
    _, J = chain.so3_chain_hand(params, v) if group == "SO3" else chain.se3_chain_hand(params, v)
    elements = [cls(params[i]) for i in range(length)]
    evaluate = jax.jit(chain.so3_chain)
    eps = 1e-6
    for i in range(length):
        for k in range(cls.tangent_dim):
            step = jnp.zeros(cls.tangent_dim).at[k].set(eps)
            plus = [e.rplus(step) if j == i else e for j, e in enumerate(elements)]
            minus = [e.rplus(-step) if j == i else e for j, e in enumerate(elements)]
            column = (evaluate(plus, v) - evaluate(minus, v)) / (2 * eps)
            np.testing.assert_allclose(J[i, :, k], column, rtol=0, atol=1e-8)


def test_icp_variants_agree():
    inputs = chain.icp_inputs(jax.random.PRNGKey(3), 50)
    r_ref, J_ref = jax.jit(chain.icp_hand)(*inputs)
    assert J_ref.shape == (50, 6)
    for name, fn in chain.ICP_VARIANTS.items():
        r, J = jax.jit(fn)(*inputs)
        np.testing.assert_allclose(r, r_ref, rtol=0, atol=TOLERANCE, err_msg=name)
        np.testing.assert_allclose(J, J_ref, rtol=0, atol=TOLERANCE, err_msg=name)


def test_benchmark_runs_on_tiny_sizes(capsys):
    chain.main(
        [
            "--chains",
            "2",
            "--lengths",
            "2",
            "--repeats",
            "1",
            "--points",
            "20",
            "--tables",
            "so3,icp",
        ]
    )
    out = capsys.readouterr().out
    assert "| N | hand-written | lieax |" in out
    assert "Point-to-plane ICP" in out
    assert "lieax within 1.3× of hand-written" in out


def test_benchmark_rejects_bad_lengths():
    with pytest.raises(SystemExit):
        chain.parse_args(["--lengths", "0,2"])
