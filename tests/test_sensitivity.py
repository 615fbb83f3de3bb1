"""Design sensitivities: direct differentiation of generalized-alpha against finite differences.

The reference is a central finite difference of the same discrete simulation. Its own
accuracy is measured by a step study (two steps a decade apart): the comparison with the
direct derivatives is asserted at 1e-5 relative only where the two finite differences
agree with each other to better than that, i.e. where FD itself is that accurate (issue 5).
The Newton tolerance (1e-10 relative increment) limits both to about 1e-7.
"""
import numpy as np
import pytest

from flexmbs.cases import load_case
from flexmbs.sensitivity import case_gradients, check_sensitivity

# (case, design in mm): published optima of Tables 1, 2 and 3, where the deviation is active
CASES = [
    ("robot_2dof", [39.29, 28.33, 34.94, 25.19]),            # Table 1 weakly, formulation (28)
    ("robot_2dof_tracking", [47.87, 34.51, 42.11, 30.08]),   # Table 2 weakly, formulation (30)
    ("fourbar", [69.85, 87.61, 37.22]),                      # Table 3 weakly, formulation (33)
]


def _central(case, p, d, s, t_end):
    gp = case_gradients(case, p + s * d, method="direct", t_end=t_end)
    gm = case_gradients(case, p - s * d, method="direct", t_end=t_end)
    return (gp.deviation - gm.deviation) / (2 * s)


@pytest.mark.parametrize("name,design", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("nsteps", [100, 500, None], ids=["100 steps", "500 steps", "full"])
def test_direct_matches_central_differences_along_random_direction(name, design, nsteps):
    """d(deviation history)/dp along a random direction: direct vs central FD, 1e-5 relative."""
    case = load_case(name)
    t_end = case.t_end if nsteps is None else nsteps * case.h
    p = np.asarray(design, float)
    d = np.random.default_rng(7).standard_normal(p.size)
    d /= np.linalg.norm(d)
    g = case_gradients(case, p, method="direct", t_end=t_end)
    direct = g.d_deviation @ d
    fd1 = _central(case, p, d, 1e-4, t_end)
    fd2 = _central(case, p, d, 1e-5, t_end)
    scale = np.max(np.abs(fd2[1:]))
    fd_accuracy = np.max(np.abs(fd1 - fd2)) / scale
    assert fd_accuracy < 1e-5, f"finite differences not accurate enough to judge: {fd_accuracy:.2e}"
    err = np.max(np.abs(direct - fd2)) / scale
    assert err < 1e-5, f"direct vs central FD: {err:.2e} relative (FD self-consistency {fd_accuracy:.2e})"
    # and at the last step alone (the horizon's end, where the robot's constraint is active)
    assert abs(direct[-1] - fd2[-1]) <= 1e-5 * max(abs(fd2[-1]), 1e-3 * scale)


def test_direct_matches_central_differences_per_variable_robot():
    """Each column of d(deviation)/dp, robot formulation (28), full 0.65 s: 1e-5 relative."""
    case = load_case("robot_2dof")
    p = np.array([39.29, 28.33, 34.94, 25.19])
    g = case_gradients(case, p, method="direct")
    c = case_gradients(case, p, method="central", fd_step=2e-5)   # 2e-5 relative = ~7e-4 mm
    for i in range(p.size):
        scale = np.max(np.abs(c.d_deviation[:, i]))
        err = np.max(np.abs(g.d_deviation[:, i] - c.d_deviation[:, i])) / scale
        assert err < 1e-5, f"p{i + 1}: {err:.2e}"
    assert c.simulations == 1 + 2 * p.size and g.simulations == 1


def test_mass_gradient_matches_finite_differences():
    """Beam mass m = 229.02 sum p_i^2 (CASES.md) for the robot: gradient 2 * 229.02 p_i * 1e-6 kg/mm."""
    case = load_case("robot_2dof")
    p = np.array([39.29, 28.33, 34.94, 25.19])
    g = case_gradients(case, p, method="direct")
    rho_a_per_p2 = 2700 * 0.36 * np.pi / 4 * 0.3            # kg / m^2 per element of 0.3 m
    np.testing.assert_allclose(g.d_mass, 2 * rho_a_per_p2 * p * 1e-6, rtol=1e-12)
    fd = [(case.mass(p + e * 1e-4) - case.mass(p - e * 1e-4)) / 2e-4 for e in np.eye(4)]
    np.testing.assert_allclose(g.d_mass, fd, rtol=1e-8)


def test_forward_differences_with_the_papers_step_are_the_inaccurate_path():
    """CASES.md: a 1e-3 relative FD step is several per cent wrong at the late, vibrating
    steps of the robot, 1e-6 is accurate. Direct derivatives need no step at all."""
    case = load_case("robot_2dof")
    p = np.array([39.29, 28.33, 34.94, 25.19])
    g = case_gradients(case, p, method="direct")
    coarse = case_gradients(case, p, method="forward", fd_step=1e-3)
    fine = case_gradients(case, p, method="forward", fd_step=1e-6)
    scale = np.max(np.abs(g.d_deviation), axis=0)
    err_coarse = np.max(np.abs(coarse.d_deviation - g.d_deviation) / scale)
    err_fine = np.max(np.abs(fine.d_deviation - g.d_deviation) / scale)
    assert err_fine < 1e-4
    assert err_coarse > 10 * err_fine


@pytest.mark.parametrize("options", [dict(reuse_jacobian=True), dict(solver="klu")],
                         ids=["modified Newton", "KLU"])
def test_derivatives_do_not_depend_on_solver_options(options):
    """The derivatives solve the same discrete equations whatever the linear solver or the
    Jacobian reuse. Modified Newton stops at a different point within the Newton tolerance
    (1e-10 m on q, i.e. 1e-7 of the 1 mm deviation), which moves the derivatives by a few
    1e-7 (measured 6e-7); the bound is the 1e-5 accuracy the optimizers need (issue 5)."""
    case = load_case("robot_2dof")
    p = np.array([39.29, 28.33, 34.94, 25.19])
    ref = case_gradients(case, p, method="direct")
    other = case_gradients(case, p, method="direct", **options)
    scale = np.max(np.abs(ref.d_deviation))
    assert np.max(np.abs(other.d_deviation - ref.d_deviation)) < 1e-5 * scale


def test_check_sensitivity_step_study_has_the_textbook_shape():
    """The step study of check_sensitivity: truncation error falls like s^2 (large s), the
    best error is below 1e-6 (four-bar, Table 3 weakly design, 300 steps)."""
    case = load_case("fourbar")
    p = np.array([69.85, 87.61, 37.22])
    chk = check_sensitivity(case, p, steps=(1e-1, 1e-2, 1e-3, 1e-4), t_end=300 * case.h)
    errs = dict(chk.rows)
    assert chk.best_error < 1e-6
    # truncation regime: a tenfold smaller step gives a ~100-fold smaller error
    assert errs[1e-2] < errs[1e-1] / 30
    assert "FD step" in chk.table()


def test_design_derivative_at_the_maximum_is_consistent():
    """d_max_deviation is the history's derivative at the step of the maximum (issue 5 JSON)."""
    case = load_case("robot_2dof")
    g = case_gradients(case, [39.29, 28.33, 34.94, 25.19])
    k = int(np.argmax(g.deviation))
    assert g.step_at_max == k
    np.testing.assert_array_equal(g.d_max_deviation, g.d_deviation[k])
    # thicker arms deflect less: every derivative of the active deviation is negative
    assert np.all(g.d_max_deviation < 0)


def test_cli_gradient_json_direct_and_fd_agree():
    """`flexmbs simulate CASE --design ... --gradient [direct|fd] --json` (issue 5): the
    derivative of the deviation at its maximum, by direct differentiation and by the paper's
    forward differences (relative step 1e-6), agree to 1e-4 relative (FD truncation/round-off)."""
    import json
    import subprocess
    import sys
    out = {}
    for method in ("direct", "fd"):
        proc = subprocess.run([sys.executable, "-m", "flexmbs", "simulate", "robot_2dof", "--design",
                               "39.29,28.33,34.94,25.19", "--gradient", method, "--json"],
                              capture_output=True, text=True, check=True)
        out[method] = json.loads(proc.stdout)
    d, f = out["direct"], out["fd"]
    assert d["gradient_method"] == "direct" and f["gradient_method"] == "forward"
    assert d["gradient_simulations"] == 1 and f["gradient_simulations"] == 5
    np.testing.assert_allclose(d["d_max_deviation_d_design_m_per_mm"],
                               f["d_max_deviation_d_design_m_per_mm"], rtol=1e-4)
    np.testing.assert_allclose(d["d_mass_d_design_kg_per_mm"], f["d_mass_d_design_kg_per_mm"], rtol=1e-5)
