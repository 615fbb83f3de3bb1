"""Linear solvers of the compiled core: LAPACK LU and KLU from Fortran.

``flexmbs._core.dense_solve`` factors with dgetrf and solves with dgetrs;
``flexmbs._core.sparse_solve`` runs the KLU symbolic analysis once, factors and
solves, then refactors with new values of the same pattern and solves again
(the path the time loop takes at every Newton iteration).

Tolerances. For LU with partial pivoting the computed solution x of A x = b has
a normwise backward error eta = ||b - A x|| / (||A|| ||x|| + ||b||) of order
n u (u = 2.2e-16 the unit roundoff, growth factor of order one; Higham,
*Accuracy and Stability of Numerical Algorithms*, 2nd ed., thm 9.4 and
sec. 9.4), and a forward error ||x - x*|| / ||x*|| <= 2 kappa(A) eta
(thm 7.2). We assert eta <= 10 n u and the forward error <= 2 kappa (10 n u),
kappa from numpy's SVD. KLU pivots with a threshold (0.001) instead of the
largest entry, which allows a larger growth factor; its bound is taken 100
times looser (1000 n u), still far below anything a wrong solve would give.
"""
import importlib
import threading

import numpy as np
import pytest
import scipy.sparse as sp

import flexmbs as fx
from flexmbs import _core
from flexmbs.errors import SimulationError
from flexmbs.analysis.settings import SimulationSettings

U = np.finfo(float).eps / 2


def backward_error(a, x, b):
    """Normwise backward error of x as a solution of a x = b (infinity norms), per column."""
    a = a.toarray() if sp.issparse(a) else a
    r = b - a @ x
    na = np.abs(a).sum(axis=1).max()
    return np.abs(r).max(axis=0) / (na * np.abs(x).max(axis=0) + np.abs(b).max(axis=0))


def matrix_with_condition(n, kappa, rng):
    """A dense n x n matrix with 2-norm condition number kappa (log-spaced singular values)."""
    u, _ = np.linalg.qr(rng.standard_normal((n, n)))
    v, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return (u * np.logspace(0, -np.log10(kappa), n)) @ v.T


def csc_arrays(a):
    """0-based CSC arrays (int32 pattern, float values) of a scipy sparse matrix."""
    a = sp.csc_matrix(a)
    a.sort_indices()
    return a.indptr.astype(np.int32), a.indices.astype(np.int32), a.data.astype(float)


def relative_error(x, x_true):
    return np.abs(x - x_true).max() / np.abs(x_true).max()


# ------------------------------------------------------------------ dense LU (LAPACK)
@pytest.mark.parametrize("n, kappa", [(8, 10.0), (50, 1e3), (50, 1e8), (120, 1e12)])
def test_dense_solve_matches_numpy_within_condition_bound(n, kappa):
    """dense_solve on matrices of condition 10 to 1e12 with several right-hand sides.

    Backward error <= 10 n u (LU with partial pivoting, Higham thm 9.4) and forward
    error, against the known solution and against numpy.linalg.solve, <= 2 kappa 10 n u
    (Higham thm 7.2): the bound grows with kappa, the backward error does not.
    """
    rng = np.random.default_rng(int(n + np.log10(kappa)))
    a = matrix_with_condition(n, kappa, rng)
    x_true = rng.standard_normal((n, 3))
    b = a @ x_true
    x, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 0
    bound = 10 * n * U
    kappa_measured = np.linalg.cond(a)
    assert np.all(backward_error(a, x, b) <= bound)
    assert relative_error(x, x_true) <= 2 * kappa_measured * bound
    assert relative_error(x, np.linalg.solve(a, b)) <= 2 * kappa_measured * bound


def test_dense_solve_badly_scaled_rows_and_columns():
    """Rows and columns each scaled over 6 decades (kappa ~ 1e12 from the scaling alone).

    Partial pivoting is not scale-invariant, but the backward error of the scaled
    system stays at the n u level (Higham sec. 9.8); the solution is compared with
    numpy's LAPACK solve within the condition bound.
    """
    rng = np.random.default_rng(3)
    n = 40
    d1 = np.logspace(-3, 3, n)
    d2 = rng.permutation(np.logspace(-3, 3, n))
    a = (d1[:, None] * matrix_with_condition(n, 10.0, rng)) * d2[None, :]
    x_true = rng.standard_normal((n, 1)) / d2[:, None]
    b = a @ x_true
    x, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 0
    assert np.all(backward_error(a, x, b) <= 10 * n * U)
    kappa = np.linalg.cond(a)
    assert relative_error(x, np.linalg.solve(a, b)) <= 2 * kappa * 10 * n * U


def test_dense_solve_singular_matrix_gives_status_1():
    """A rank-deficient matrix (rank n-1, made of outer products) and a matrix with a zero
    column, and a matrix of condition 1e18 (beyond 1/u): the pivot test
    (min |u_ii| / max |u_ii| < 1e-14, linear_solver.f90) returns status 1 (LS_SINGULAR)
    instead of a meaningless solution; NaN values give status 4."""
    rng = np.random.default_rng(4)
    n = 30
    a = rng.standard_normal((n, n - 1)) @ rng.standard_normal((n - 1, n))
    b = rng.standard_normal((n, 1))
    _, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 1
    a = rng.standard_normal((n, n))
    a[:, 7] = 0.0
    _, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 1
    a[3, 7] = np.nan
    _, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 4
    # condition 1e18 > 1/u: singular in double precision, flagged by the pivot ratio
    a = matrix_with_condition(n, 1e18, rng)
    _, status = _core.dense_solve(np.asfortranarray(a), np.asfortranarray(b))
    assert status == 1


# ------------------------------------------------------------------ KLU
def random_sparse(n, density, rng, decades=0.0):
    """A random sparse nonsymmetric matrix with a dominant-ish diagonal; with decades > 0
    its rows and columns are scaled over that many decades (badly conditioned)."""
    a = sp.random(n, n, density=density, random_state=rng, data_rvs=rng.standard_normal)
    a = a + sp.diags(rng.choice([-2.0, 2.0], n))
    if decades:
        d1 = sp.diags(np.logspace(0, -decades / 2, n))
        d2 = sp.diags(rng.permutation(np.logspace(0, -decades / 2, n)))
        a = d1 @ a @ d2
    return sp.csc_matrix(a)


@pytest.mark.parametrize("n, density, decades", [(50, 0.05, 0), (400, 0.01, 0), (200, 0.02, 10)])
def test_klu_solve_and_refactor_match_scipy(n, density, decades):
    """KLU factor + solve, then refactor with new values of the same pattern + solve.

    Both solutions against scipy.sparse.linalg.spsolve (SuperLU) and the known
    solution, within the condition bound 2 kappa (1000 n u) (module docstring);
    backward errors <= 1000 n u.
    """
    from scipy.sparse.linalg import spsolve
    rng = np.random.default_rng(n)
    a = random_sparse(n, density, rng, decades)
    ap, ai, ax = csc_arrays(a)
    a2 = a.copy()
    a2.data = a.data * rng.uniform(0.5, 1.5, a.data.size)     # same pattern, new values
    ax2 = csc_arrays(a2)[2]
    x_true = rng.standard_normal((n, 2))
    b = a @ x_true
    b2 = a2 @ x_true
    x, x2, status = _core.sparse_solve(ap, ai, ax, ax2, np.asfortranarray(b), np.asfortranarray(b2))
    assert status == 0
    bound = 1000 * n * U
    for mat, sol, rhs in ((a, x, b), (a2, x2, b2)):
        kappa = np.linalg.cond(mat.toarray())
        assert np.all(backward_error(mat, sol, rhs) <= bound)
        assert relative_error(sol, x_true) <= 2 * kappa * bound
        ref = np.column_stack([spsolve(mat, rhs[:, k]) for k in range(rhs.shape[1])])
        assert relative_error(sol, ref) <= 2 * kappa * bound


def test_klu_refactor_with_a_pivot_that_becomes_zero():
    """Refactoring keeps the first pivot order; when the new values make one of those pivots
    zero the shim must fall back to a fresh factorization (klu_shim.c) and still solve.

    First matrix: diagonally dominant (KLU pivots on the diagonal). Second matrix: same
    pattern with a zero on the diagonal entry (0, 0) and a permutation-like coupling, still
    nonsingular. Solutions against numpy within 2 kappa (1000 n u)."""
    n = 6
    a = np.diag(np.full(n, 4.0)) + np.diag(np.ones(n - 1), 1) + np.diag(np.ones(n - 1), -1)
    a2 = a.copy()
    a2[0, 0] = 0.0                    # structurally present, numerically zero pivot
    a2[1, 1] = 0.0
    pattern = sp.csc_matrix((a != 0).astype(float))
    ap, ai, _ = csc_arrays(pattern)
    ax = np.array([a[i, j] for j in range(n) for i in ai[ap[j]:ap[j + 1]]])
    ax2 = np.array([a2[i, j] for j in range(n) for i in ai[ap[j]:ap[j + 1]]])
    rng = np.random.default_rng(6)
    b = rng.standard_normal((n, 1))
    x, x2, status = _core.sparse_solve(ap, ai, ax, ax2, np.asfortranarray(b), np.asfortranarray(b))
    assert status == 0
    bound = 1000 * n * U
    assert relative_error(x, np.linalg.solve(a, b)) <= 2 * np.linalg.cond(a) * bound
    assert relative_error(x2, np.linalg.solve(a2, b)) <= 2 * np.linalg.cond(a2) * bound


def robot_like_iteration_matrix():
    """The iteration matrix of eq. (7) of a clamped-pinned two-beam mechanism: a saddle-point
    matrix (zero constraint block) whose entries span beta' M ~ 1e7 to EI ~ 1e3 and k."""
    mat = fx.Material(E=72e9, nu=0.3, rho=2700)
    m = fx.Model()
    a1 = m.add_beam("a1", (0, 0), (0.6, 0.2), 2, material=mat,
                    section=fx.Tube.with_wall_ratio(0.05, 0.1))
    a2 = m.add_beam("a2", (0.6, 0.2), (1.0, -0.3), 3, material=mat, section=fx.Circle(0.02))
    m.pin(a1.first)
    m.drive_rotation(a1.first, 0.3)
    m.hinge(a1.last, a2.first)
    m.add_point_mass(a2.last, 1.0)
    from flexmbs.analysis.checks import generalized_alpha_beta_prime
    from flexmbs.analysis.simulate import system_matrices
    q = m.reference_coordinates()
    _, s = system_matrices(m, q, cm=generalized_alpha_beta_prime(5e-4, 0.5), kscale=1e8,
                           penalty=1e8)
    return s


def test_klu_and_dense_on_a_saddle_point_iteration_matrix():
    """A real iteration matrix (eq. 7, zero diagonal block of the multipliers: pivoting is
    required) solved by KLU on its sparsity pattern (factored, then refactored with the same
    values) and by dense LU, against numpy, within the condition bound of the module
    docstring."""
    s = robot_like_iteration_matrix()
    n = s.shape[0]
    rng = np.random.default_rng(7)
    x_true = rng.standard_normal((n, 1))
    b = s @ x_true
    kappa = np.linalg.cond(s)
    ap, ai, ax = csc_arrays(sp.csc_matrix(s))
    x, x2, status = _core.sparse_solve(ap, ai, ax, ax, np.asfortranarray(b), np.asfortranarray(b))
    assert status == 0
    # the refactorization keeps the first pivots without KLU's row scaling (klu_shim.c):
    # the same bounds, on this matrix of entries from 1e3 to 1e8
    for sol in (x, x2):
        assert np.all(backward_error(s, sol, b) <= 1000 * n * U)
        assert relative_error(sol, x_true) <= 2 * kappa * 1000 * n * U
    xd, status = _core.dense_solve(np.asfortranarray(s), np.asfortranarray(b))
    assert status == 0
    assert relative_error(xd, x_true) <= 2 * kappa * 10 * n * U


def test_klu_singular_and_nonfinite_status_codes():
    """Status codes of sparse_solve (10 * stage + LS code, flexmbs_api.f90): a numerically
    singular first matrix gives 21, a singular refactor 31, NaN values 24."""
    rng = np.random.default_rng(8)
    n = 20
    good = random_sparse(n, 0.1, rng)
    ap, ai, ax = csc_arrays(good)
    b = np.asfortranarray(rng.standard_normal((n, 1)))
    # singular: a whole column of values set to zero (pattern unchanged)
    bad = ax.copy()
    bad[ap[5]:ap[6]] = 0.0
    assert _core.sparse_solve(ap, ai, bad, ax, b, b)[2] == 21
    assert _core.sparse_solve(ap, ai, ax, bad, b, b)[2] == 31
    # rank deficient: column 3 a copy of column 2 on a shared pattern
    dense = good.toarray()
    dense[:, 3] = dense[:, 2]
    full = sp.csc_matrix(np.where(np.abs(dense) + np.abs(good.toarray()) > 0, 1.0, 0.0))
    fap, fai, _ = csc_arrays(full)
    vals = np.array([dense[i, j] for j in range(n) for i in fai[fap[j]:fap[j + 1]]])
    assert _core.sparse_solve(fap, fai, vals, vals, b, b)[2] == 21
    nan = ax.copy()
    nan[0] = np.nan
    assert _core.sparse_solve(ap, ai, nan, ax, b, b)[2] == 24


# ------------------------------------------------------------------ through flexmbs.analysis.simulate
STEEL = fx.Material(E=210e9, nu=0.3, rho=7800)


def free_beam_model():
    """A beam with no support under gravity: its stiffness has three rigid-body modes."""
    m = fx.Model()
    m.add_beam("free", (0, 0), (1, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.set_gravity(0, -9.81)
    return m


def two_unjoined_bodies_model():
    """A clamped beam and a second beam at its tip with no joint between them."""
    m = fx.Model()
    a = m.add_beam("held", (0, 0), (1, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.add_beam("loose", (1, 0), (2, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.clamp(a.first)
    m.set_gravity(0, -9.81)
    return m


@pytest.mark.parametrize("build", [free_beam_model, two_unjoined_bodies_model])
@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_unheld_mechanism_static_start_raises(build, solver):
    """A static start of a mechanism that is not held (singular tangent stiffness) raises
    SimulationError at t = 0 instead of crashing or returning garbage."""
    with pytest.raises(SimulationError) as err:
        fx.simulate(build(), 0.01, 1e-3,
                    settings=SimulationSettings(start="static", solver=solver))
    assert err.value.time == 0.0
    assert "static equilibrium" in str(err.value)


def test_unheld_mechanism_static_start_message_says_not_held():
    """The static start of a free beam fails on a singular iteration matrix (the core
    returns info(4) = 11); the message diagnoses why: the beam is not held."""
    with pytest.raises(SimulationError, match="not held"):
        fx.simulate(free_beam_model(), 0.01, 1e-3, settings=SimulationSettings(start="static"))


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_redundant_or_massless_system_raises_singular(solver):
    """A node clamped twice (redundant constraint rows) and a node with neither mass nor
    constraint both make [M Phi_q^T; Phi_q 0] singular at t = 0: SimulationError naming a
    singular matrix."""
    m = fx.Model()
    b = m.add_beam("b", (0, 0), (1, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.clamp(b.first)
    m.clamp(b.first)
    with pytest.raises(SimulationError, match="singular"):
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(solver=solver))
    m = fx.Model()
    m.add_node(2.0, 0.0)
    b = m.add_beam("b", (0, 0), (1, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.clamp(b.first)
    with pytest.raises(SimulationError, match="singular"):
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(solver=solver))


# ------------------------------------------------------------------ no hidden global state
def swinging_beam(diameter, elements):
    """A pinned beam driven by a smooth motor law, with a tip mass, under gravity."""
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.8, 0.3), elements, material=STEEL,
                   section=fx.Tube.with_wall_ratio(diameter, 0.1))
    m.pin(b.first)
    phi0 = np.arctan2(0.3, 0.8)
    m.drive_rotation(b.first, fx.TimeLaw(lambda t: phi0 + 2 * t ** 2, lambda t: 4 * t,
                                         lambda t: 4 + 0 * t, name="swing"))
    m.add_point_mass(b.last, 1.5)
    m.set_gravity(0, -9.81)
    return m


def in_two_threads(work):
    """{k: work(k)} for k = 0, 1, run in two threads at once."""
    results = {}

    def worker(k):
        results[k] = work(k)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    return results


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_two_models_alternately_and_in_threads_match_running_alone(solver):
    """Two different models (different sizes, so a shared factorization or work array
    would be visible) simulated alone, alternately, and from two threads at once give
    bit-identical results: the factorizations live in handles owned by each call.
    (The f2py wrapper keeps the GIL during a call, so the threads' Fortran calls
    interleave rather than overlap; state kept between calls would still show.)"""
    models = [swinging_beam(0.03, 3), swinging_beam(0.05, 5)]

    def run(m):
        return fx.simulate(m, 0.1, 1e-3,
                           settings=SimulationSettings(solver=solver, start="static")).q

    alone = [run(m) for m in models]
    alternate = [run(models[k % 2]) for k in range(4)]
    for k, q in enumerate(alternate):
        assert np.array_equal(q, alone[k % 2])
    results = in_two_threads(lambda k: [run(models[k]) for _ in range(3)])
    for k in range(2):
        for q in results[k]:
            assert np.array_equal(q, alone[k])


# ------------------------------------------------------------------ KLU's analysis once per model
def test_klu_analysis_is_made_once_per_model_and_borrowed_by_every_run(monkeypatch):
    """The KLU symbolic analysis is built once per model: three simulations of one model at three designs make one analysis
    (flexmbs.core.KluAnalysis) and none of their own (stats 'symbolic_analyses' 0); a run
    that analyses the pattern itself (the core's klu_analysis = 0) makes 1 and gives
    bit-identical states (KLU's ordering depends on the pattern only). Each design's states
    match the dense LAPACK path's to 1e-9 m, ten times the Newton tolerance (two different
    factorizations of the same matrices: Newton may stop one iteration apart; measured
    2e-15 m)."""
    from flexmbs.core import KluAnalysis

    simulate_module = importlib.import_module("flexmbs.analysis.simulate")

    m = swinging_beam(0.03, 6)
    runs = []
    for d in (0.03, 0.04, 0.05):
        m.bodies["arm"].section = fx.Tube.with_wall_ratio(d, 0.1)
        r = fx.simulate(m, 0.1, 1e-3, settings=SimulationSettings(solver="klu", start="static"))
        assert r.stats["symbolic_analyses"] == 0
        dense = fx.simulate(m, 0.1, 1e-3,
                            settings=SimulationSettings(solver="dense", start="static"))
        assert np.abs(r.q - dense.q).max() < 1e-9
        runs.append(r)
    analysis = m.pattern("klu")["analysis"]
    assert isinstance(analysis, KluAnalysis) and analysis.analyses == 1
    monkeypatch.setattr(simulate_module, "klu_analysis", lambda model, storage: 0)
    own = fx.simulate(m, 0.1, 1e-3, settings=SimulationSettings(solver="klu", start="static"))
    assert own.stats["symbolic_analyses"] == 1
    assert np.array_equal(own.q, runs[-1].q) and np.array_equal(own.mu, runs[-1].mu)


def test_klu_analysis_of_another_pattern_is_refused(monkeypatch):
    """The core checks that a borrowed analysis is of the run's pattern: another model's
    (different size) makes the simulation and the adjoint's backward pass fail with the
    linear solver's set-up error instead of factoring with a wrong ordering."""
    from flexmbs.core import klu_analysis

    adjoint_module = importlib.import_module("flexmbs.analysis.adjoint")
    simulate_module = importlib.import_module("flexmbs.analysis.simulate")

    m, other = swinging_beam(0.03, 4), swinging_beam(0.03, 6)
    good = fx.simulate(m, 0.05, 1e-3,
                       settings=SimulationSettings(solver="klu", start="static", polish=True),
                       tape=True)
    wrong = klu_analysis(other, "klu")
    monkeypatch.setattr(simulate_module, "klu_analysis", lambda model, storage: wrong)
    with pytest.raises(SimulationError, match="sparse linear solver could not be set up.*"
                                              "another pattern"):
        fx.simulate(m, 0.05, 1e-3, settings=SimulationSettings(solver="klu", start="static"))
    monkeypatch.setattr(adjoint_module, "klu_analysis", lambda model, storage: wrong)
    gq = np.zeros((good.t.size, m.ndof))
    gq[-1, 0] = 1.0
    with pytest.raises(SimulationError, match="backward pass failed"):
        adjoint_module.adjoint_gradient(m, good, np.ones((5, m.compile().nel, 1)), gq[:, :, None])


def test_klu_analysis_is_shared_by_threads_and_remade_by_copies():
    """One model simulated from two threads at once borrows one analysis (KLU only reads it:
    klu.h, "inputs, not modified") and gives bit-identical states; a case's Problem evaluated
    at two designs (the adjoint at the second) makes one analysis; a copy of it (deepcopy;
    pickle takes the same path) makes its own on first use and gives the same responses."""
    from copy import deepcopy

    from flexmbs.problem import Problem

    m = swinging_beam(0.04, 5)
    alone = fx.simulate(m, 0.1, 1e-3, settings=SimulationSettings(solver="klu", start="static")).q
    results = in_two_threads(
        lambda k: [fx.simulate(m, 0.1, 1e-3, SimulationSettings(solver="klu", start="static"))
                   for _ in range(3)])
    for k in range(2):
        for r in results[k]:
            assert r.stats["symbolic_analyses"] == 0
            assert np.array_equal(r.q, alone)
    assert m.pattern("klu")["analysis"].analyses == 1
    case = Problem("robot_2dof_tapered_tubes", {"time.t_end": 0.05, "bodies.arm1.elements": 6,
                                                "bodies.arm2.elements": 6})
    first = case.evaluate(gradient=False)
    case.evaluate(1.1 * case.start, gradient="used", method="adjoint")   # another design
    assert case.mechanism.model.pattern("klu")["analysis"].analyses == 1
    copy = deepcopy(case)
    assert copy.mechanism.model.pattern("klu")["analysis"].analyses == 0
    again = copy.evaluate(gradient=False)
    assert again.stats["solver"] == "klu" and again.stats["symbolic_analyses"] == 0
    assert np.array_equal(again.values["deviation_28"], first.values["deviation_28"])
    assert copy.mechanism.model.pattern("klu")["analysis"].analyses == 1


def test_klu_analysis_of_an_invalid_pattern_raises():
    """A pattern KLU cannot analyse (first column pointer not 0; a row index outside the
    matrix) is a ModelError naming its size, not a crash or a null handle used later."""
    from flexmbs.core import KluAnalysis
    from flexmbs.errors import ModelError

    for ap, ai in (([1, 2], [0]), ([0, 1], [5])):
        bad = KluAnalysis(np.array(ap, np.int32), np.array(ai, np.int32))
        with pytest.raises(ModelError, match=r"rejected the sparsity pattern .*1 unknowns, "
                                             r"1 nonzeros"):
            bad.handle()
        assert bad.analyses == 0
