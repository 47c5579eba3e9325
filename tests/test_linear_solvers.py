"""The structured Riccati solve must give the same Newton steps (hence the same iterates and solution) as
the general sparse LU on the same system; the paper's least-squares options must reach an equilibrium too."""
import dataclasses

import numpy as np
import pytest

from bench.merging import merging_problem
from solver_cpp import Solver, solve


@pytest.mark.parametrize("cars, seed", [(2, 0), (3, 1), (5, 2), (8, 1)])
def test_riccati_matches_sparse_lu(cars, seed):
    a = solve(merging_problem(cars, seed), linear=dict(solver="riccati"))
    b = solve(merging_problem(cars, seed), linear=dict(solver="sparse_lu"))
    assert a.status == b.status == "converged"
    assert a.iterations == b.iterations
    np.testing.assert_allclose(a.x, b.x, atol=1e-9, rtol=0)
    np.testing.assert_allclose(a.u, b.u, atol=1e-9, rtol=0)


def test_riccati_is_used_when_no_constraint_is_an_equality():
    s = Solver(merging_problem(8, 1))
    info = s._solver.solve(None).info
    assert info.riccati_solves == info.iterations > 0  # this instance never holds a constraint as an equality


@pytest.mark.parametrize("cars, seed", [(2, 0), (3, 1)])
def test_riccati_with_active_bounds_matches_sparse_lu(cars, seed):
    # Speed caps 0.2 m/s below every car's initial speed: violated at the start, so they are held as
    # equalities (multiplier rows); the Riccati path eliminates them by a Schur complement instead of LU.
    p = merging_problem(cars, seed)
    cap = [a.x0[2] - 0.2 for a in p.agents]
    p = dataclasses.replace(p, agents=[dataclasses.replace(a, x_max=np.array([np.inf, np.inf, c, np.inf]))
                                       for a, c in zip(p.agents, cap)])
    ric, lu = Solver(p, linear=dict(solver="riccati"))._solver.solve(None), Solver(p, linear=dict(solver="sparse_lu"))._solver.solve(None)
    assert ric.info.active_constraints > 0 and lu.info.symbolic_factorizations > 0  # equality rows present
    assert ric.info.symbolic_factorizations == 0 and ric.info.riccati_solves == ric.info.iterations
    assert ric.info.iterations == lu.info.iterations
    np.testing.assert_allclose(np.stack(ric.u), np.stack(lu.u), atol=1e-9, rtol=0)
    np.testing.assert_allclose(np.stack(ric.x), np.stack(lu.x), atol=1e-9, rtol=0)
    for i, c in enumerate(cap):  # the converged plan keeps the caps (k >= 1; x_0 is given)
        assert np.max(np.stack(ric.x)[i][1:, 2]) <= c + 1e-6


def _normal_matrices(n, density, count, rng, seed):
    """count matrices J'J of one pattern (random J with a stored diagonal, so J'J is nonsingular)."""
    import scipy.sparse as sp

    pattern = (sp.random(n, n, density=density, random_state=seed, format="csc") + sp.identity(n)).tocsc()
    pattern.data[:] = 1.0
    mats = []
    for _ in range(count):  # same pattern, new values (successive iterations)
        J = pattern.copy()
        J.data = rng.normal(size=J.nnz)
        A = (J.T @ J).tocsc()
        A.sort_indices()
        mats.append(A)
    assert all(m.nnz == mats[0].nnz for m in mats)
    return mats


@pytest.mark.parametrize("n, density", [(60, 0.08), (400, 0.01), (1, 1.0), (7, 0.0)])
def test_levenberg_marquardt_ldlt_against_dense_solve(n, density):
    # The LM tries factorise J'J + nu I for several nu, analysing J'J's pattern once and reusing it while the
    # partition is unchanged (a supernodal LDL'). References: numpy's dense solve of the same shifted system, and
    # Eigen's SimplicialLDLT of the explicitly shifted matrix computed afresh.
    from solver_cpp import _core

    rng = np.random.default_rng(3)
    mats = _normal_matrices(n, density, 3, rng, seed=4)
    shifts = [1e-6, 1e-5, 1e-3, 1.0]
    b = rng.normal(size=n)
    ours, eigen, supernodes = _core.debug_shifted_ldlt(mats, shifts, b)
    assert len(ours) == len(eigen) == len(mats) * len(shifts)
    assert 1 <= supernodes <= n
    for q, (x, y) in enumerate(zip(ours, eigen)):
        A = mats[q // len(shifts)].toarray() + shifts[q % len(shifts)] * np.eye(n)
        scale = 1e-12 * np.linalg.cond(A) * np.abs(np.linalg.solve(A, b)).max()
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=0, atol=scale)
        np.testing.assert_allclose(x, y, rtol=0, atol=scale)


def test_levenberg_marquardt_ldlt_groups_columns_into_supernodes():
    # Five dense 30 x 30 diagonal blocks: each block's columns share one pattern, so each is one supernode (the
    # point of the supernodal factorisation: dense panel operations instead of entry-by-entry updates).
    import scipy.linalg
    import scipy.sparse as sp
    from solver_cpp import _core

    rng = np.random.default_rng(8)
    blocks = []
    for _ in range(5):
        g = rng.normal(size=(30, 30))
        blocks.append(g @ g.T + 30 * np.eye(30))
    A = sp.csc_matrix(scipy.linalg.block_diag(*blocks))
    A.sort_indices()
    b = rng.normal(size=150)
    ours, _, supernodes = _core.debug_shifted_ldlt([A], [0.0], b)
    np.testing.assert_allclose(ours[0], np.linalg.solve(A.toarray(), b), rtol=1e-10, atol=1e-12)
    assert supernodes == 5


def test_levenberg_marquardt_ldlt_reports_a_zero_pivot():
    import scipy.sparse as sp
    from solver_cpp import _core

    A = sp.csc_matrix(np.array([[1.0, 1.0], [1.0, 1.0]]))  # singular: the second pivot is exactly 0
    ours, eigen, _ = _core.debug_shifted_ldlt([A], [0.0, 1.0], np.ones(2))
    assert len(ours[0]) == 0 and len(eigen[0]) == 0  # failed, as Eigen's
    np.testing.assert_allclose(ours[1], np.linalg.solve(A.toarray() + np.eye(2), np.ones(2)), rtol=1e-14)


def test_normal_matrix_reuses_its_plan_and_equals_eigens_product():
    # The LM matrix J'J of successive iterations with one pattern of J: formed by Eigen's product on the first,
    # then from the kept pairs of entries, summed in the product's order: equal to a fresh product bit for bit.
    import scipy.sparse as sp
    from solver_cpp import _core

    rng = np.random.default_rng(5)
    pattern = sp.random(80, 50, density=0.1, random_state=6, format="csc")
    other = sp.random(80, 50, density=0.1, random_state=7, format="csc")
    js = []
    for p in (pattern, pattern, pattern, other, other):
        j = p.copy()
        j.data = rng.normal(size=j.nnz)
        j.data[::7] = -0.0  # signed zeros: the product stores +0 for a -0 sum, as Eigen's J'J + 0 I does
        js.append(j)
    ours, eigen, reused = _core.debug_normal_matrix(js)
    assert reused == [False, True, True, False, True]
    for j, a, b in zip(js, ours, eigen):
        np.testing.assert_array_equal(a.toarray(), b.toarray())
        np.testing.assert_allclose(a.toarray(), np.tril((j.T @ j).toarray()), rtol=1e-12, atol=1e-12)


def test_levenberg_marquardt_ldlt_refuses_another_pattern():
    import scipy.sparse as sp
    from solver_cpp import _core

    A = sp.csc_matrix(np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]]))
    B = sp.csc_matrix(np.array([[4.0, 0.0, 1.0], [0.0, 3.0, 1.0], [1.0, 1.0, 2.0]]))  # same count, other entries
    with pytest.raises(ValueError, match="pattern"):
        _core.debug_shifted_ldlt([A, B], [0.0], np.ones(3))
