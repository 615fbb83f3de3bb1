!> Discrete adjoint of the generalized-alpha scheme (docs/adjoint.md).
!!
!! The transpose of the direct differentiation of generalized_alpha.f90 (sens_step,
!! sens_initial, sens_static), run backwards over the converged states of a forward run:
!! for nf functionals G_f = sum_j gq(:, f, j) . q_j + gmu(:, f, j) . mu_j of the discrete
!! solution (the per-step partials of a response aggregated over the history: KS, p-norm,
!! max, final value, ...), dG_f/dp of nv design variables for the cost of one transposed
!! solve per step (nf right-hand sides), whatever nv: the design enters through a per-element
!! contraction gprop(5, nel, f) = dG_f/d[EA, kGA, EI, rhoA, rhoI]_e, contracted with the
!! section derivatives dprop once at the end.
!!
!! The iteration matrix of every step is assembled and factored again at the stored
!! converged state (the exact tangent: the direct method uses the factorization of the
!! step's last Newton iteration, within the Newton tolerance of it). The states are those of
!! every (sub-)step of the forward run, in order (its tape: a cut step's sub-steps too), with
!! the step that led to each; the partials are given on the output grid. Nothing is printed;
!! every allocation is checked.
module adjoint
    use flexmbs_kinds, only: wp
    use beam2d, only: beam_internal_forces, MAX_EDOF
    use constraints, only: MAX_CDOF
    use model_data, only: mbs_model
    use assembly, only: iteration_matrix, mass_times, constraint_values, spring_times, damping_times
    use sensitivity, only: stiffness_times, add_curvature_times
    use linear_solver, only: linear_system, ls_init_dense, ls_init_sparse, ls_factor, &
                             ls_solve, ls_free, SOLVER_KLU, LS_OK, LS_NO_MEMORY
    use generalized_alpha, only: ga_settings, ga_stats, ga_state, ga_coefficients, &
                                 static_equilibrium, mass_scale, diagonal_scale, grid_time, GA_OK, &
                                 GA_SINGULAR, GA_NONFINITE, GA_BAD_INPUT, GA_LINEAR_SOLVER, &
                                 GA_NO_MEMORY, GA_STATIC_FAILED, GA_INITIAL_SINGULAR, &
                                 GA_INTERRUPTED, ga_cancelled
    implicit none
    private
    public :: ga_adjoint

contains

    !> Backward (adjoint) recursion over a converged forward run.
    !!
    !! qt, qdt, qddt (ndof, ncol) and mut (>= nc, ncol): every coordinate, velocity,
    !! acceleration and physical multiplier of every converged (sub-)step of the forward run
    !! (its tape, ga_simulate), run with the settings s from q0, qd0; th(c): the step that led
    !! to column c (th(1): the step before the first state, 0 at the run's start, a
    !! segment's checkpoint h_prev); grid(j + 1): the column of grid point j. gq (ndof, nf,
    !! nsteps + 1), gmu (>= nc, nf, nsteps + 1): dG_f/dq_j and dG_f/dmu_j on the grid. Out:
    !! grad(v, f) = dG_f/dp_v and gprop(:, e, f) = dG_f/dprop_e. status: GA_* codes; info =
    !! [time, 0, 0, extra] on failure.
    !!
    !! Segments (checkpointing, flexmbs/adjoint.py): with j_start, the tape is that of the
    !! s%nsteps steps from grid point j_start on (a run restarted from a checkpoint,
    !! ga_simulate x_start), grid its columns, and gq, gmu the partials of the whole run
    !! (grid point j in column j + 1); adj_in (ndof, nf, 4) the adjoint state [qb, qdb,
    !! qddb, ab] at the segment's last state from the later segment (absent: the last
    !! segment), adj_out the same at its first state for the earlier one; with accumulate,
    !! gprop holds the later segments' sums and is added to. The initial state's part
    !! (A8)-(A10) runs only in the segment with j_start = 0. s%kscale and s%penalty must be
    !! the run's (its checkpoints') when j_start > 0.
    subroutine ga_adjoint(m, s, ap, ai, q0, qd0, qt, qdt, qddt, mut, th, grid, gq, gmu, dprop, &
                          grad, gprop, status, info, j_start, adj_in, adj_out, accumulate)
        type(mbs_model), intent(in) :: m
        type(ga_settings), intent(in) :: s
        integer, intent(in) :: ap(:), ai(:)
        real(wp), intent(in) :: q0(m%ndof), qd0(m%ndof)
        real(wp), intent(in) :: qt(:, :), qdt(:, :), qddt(:, :), mut(:, :), th(:)
        integer, intent(in) :: grid(:)
        real(wp), intent(in) :: gq(:, :, :), gmu(:, :, :)
        real(wp), intent(in) :: dprop(:, :, :)
        real(wp), intent(out) :: grad(:, :)
        real(wp), intent(inout) :: gprop(:, :, :)
        integer, intent(out) :: status
        real(wp), intent(out) :: info(4)
        integer, intent(in), optional :: j_start
        real(wp), intent(in), optional :: adj_in(:, :, :)
        real(wp), intent(out), optional :: adj_out(:, :, :)
        logical, intent(in), optional :: accumulate
        type(linear_system) :: ls
        real(wp), allocatable :: vals(:), fgrav(:), qb(:, :), qdb(:, :), qddb(:, :), ab(:, :)
        real(wp), allocatable :: apb(:, :), qhb(:, :), vhb(:, :), z(:, :), w(:, :), acc(:)
        !> every element's forces per unit stiffness at the step's state, from the pass that
        !! assembles its tangent (iteration_matrix): the design contraction reuses them
        real(wp), allocatable :: elparts(:, :, :)
        logical, allocatable :: stiff(:), mass(:)
        logical :: state_ok
        integer, allocatable :: gidx(:)
        real(wp) :: alpha_m, alpha_f, gamma, beta, h, betap, gammap, cf, kdyn, pdyn, t, k0
        integer :: nf, nt, nv, j, f, e, v, st, ierr, n, nd, nc, ncol, j0

        status = GA_OK
        info = 0
        grad = 0
        if (present(accumulate)) then
            if (.not. accumulate) gprop = 0
        else
            gprop = 0
        end if
        if (present(adj_out)) adj_out = 0
        j0 = 0
        if (present(j_start)) j0 = j_start
        nd = m%ndof
        nc = m%nc
        n = m%n
        nt = s%nsteps + 1
        nf = size(gq, 2)
        nv = size(dprop, 3)
        ncol = 0
        if (size(grid) >= nt .and. nt >= 1) ncol = grid(nt)
        if (.not. (s%h > 0) .or. s%rho_inf < 0 .or. s%rho_inf > 1 .or. s%nsteps < 0 .or. &
            size(grid) < nt .or. ncol < nt .or. size(qt, 2) < ncol .or. size(th) < ncol .or. &
            size(gq, 3) < j0 + nt .or. size(gmu, 2) /= nf .or. size(gmu, 3) < j0 + nt .or. &
            size(grad, 1) /= nv .or. size(grad, 2) /= nf .or. size(gprop, 3) /= nf .or. &
            j0 < 0 .or. (j0 > 0 .and. .not. (s%kscale > 0 .and. s%penalty > 0))) then
            status = GA_BAD_INPUT
            return
        end if
        if (allocated(s%tgrid)) then       ! a non-uniform grid covers the run's points
            if (size(s%tgrid) < j0 + nt) status = GA_BAD_INPUT
        end if
        if (status == GA_BAD_INPUT) then
            return
        end if
        ! (two statements: Fortran's .and. does not guard an absent argument)
        state_ok = .true.
        if (present(adj_in)) state_ok = adjoint_state_fits(adj_in)
        if (present(adj_out)) state_ok = state_ok .and. adjoint_state_fits(adj_out)
        if (.not. state_ok) then
            status = GA_BAD_INPUT
            return
        end if
        if (grid(1) /= 1 .or. any(grid(2:nt) <= grid(1:nt - 1)) .or. &
            .not. all(th(2:ncol) > 0)) then
            status = GA_BAD_INPUT
            return
        end if
        call ga_coefficients(s%rho_inf, alpha_m, alpha_f, gamma, beta)
        cf = (1 - alpha_f) / (1 - alpha_m)

        if (s%solver == SOLVER_KLU) then
            call ls_init_sparse(ls, n, ap, ai, st, s%klu_analysis)
        else
            call ls_init_dense(ls, n, st)
        end if
        if (st /= LS_OK) then
            status = merge(GA_NO_MEMORY, GA_LINEAR_SOLVER, st == LS_NO_MEMORY)
            info(4) = st
            call ls_free(ls)
            return
        end if
        allocate (vals(m%nnz), fgrav(nd), qb(nd, nf), qdb(nd, nf), qddb(nd, nf), ab(nd, nf), &
                  apb(nd, nf), qhb(nd, nf), vhb(nd, nf), z(n, nf), w(nd, nf), acc(nd), &
                  stiff(max(m%nel, 1)), mass(max(m%nel, 1)), gidx(ncol), &
                  elparts(MAX_EDOF, 3, max(m%nel, 1)), stat=ierr)
        if (ierr /= 0) then
            status = GA_NO_MEMORY
            info = [0.0_wp, 8.0_wp * (m%nnz + nd * (9.0_wp * nf + 2) + n * nf &
                                      + 3.0_wp * MAX_EDOF * m%nel), 0.0_wp, 5.0_wp]
            call ls_free(ls)
            return
        end if
        call mass_times(m, m%gacc, fgrav)
        ! grid index of every column (0: a sub-step of a cut step, no partials)
        gidx = 0
        do j = 1, nt
            gidx(grid(j)) = j
        end do
        do e = 1, m%nel
            stiff(e) = any(dprop(1:3, e, :) /= 0)
            mass(e) = any(dprop(4:5, e, :) /= 0)
        end do
        kdyn = s%kscale
        if (.not. (kdyn > 0)) kdyn = diagonal_scale(m, qt(:, 1), &
            (1 - alpha_m) / (beta * s%h**2 * (1 - alpha_f)), vals)
        pdyn = s%penalty
        if (.not. (pdyn > 0)) pdyn = kdyn

        ! adjoint of the last state: only its own partials (a segment: the later segments')
        if (present(adj_in)) then
            qb = adj_in(:, :, 1)
            qdb = adj_in(:, :, 2)
            qddb = adj_in(:, :, 3)
            ab = adj_in(:, :, 4)
        else
            qb = gq(:, :, j0 + nt)
            qdb = 0
            qddb = 0
            ab = 0
        end if
        t = grid_time(s, j0 + s%nsteps)
        do j = ncol, 2, -1
            ! step from column j - 1 (state n) to column j (state n + 1), eqs. (A3)-(A7)
            if (ga_cancelled(s)) then
                status = GA_INTERRUPTED
                info = [t, 0.0_wp, 0.0_wp, 0.0_wp]
                goto 900
            end if
            h = th(j)
            betap = (1 - alpha_m) / (beta * h**2 * (1 - alpha_f))
            gammap = gamma / (beta * h)
            if (gidx(j) > 0) t = grid_time(s, j0 + gidx(j) - 1)
            ! a_{n+1} = ap + cf qdd_{n+1}
            apb = ab
            qddb = qddb + cf * ab
            ! qd_{n+1} = Vhat + gamma' (q_{n+1} - Qhat), qdd_{n+1} = beta' (q_{n+1} - Qhat)
            vhb = qdb
            qhb = -gammap * qdb - betap * qddb
            z(1:nd, :) = qb + gammap * qdb + betap * qddb
            if (nc > 0) then
                z(nd + 1:, :) = 0
                if (gidx(j) > 0) z(nd + 1:, :) = kdyn * gmu(1:nc, :, j0 + gidx(j))
            end if
            ! transposed solve with the iteration matrix at the converged state n + 1
            call iteration_matrix(m, qt(:, j), qdt(:, j), mut(1:nc, j), t, betap, 1.0_wp, gammap, &
                                  kdyn, pdyn, vals, parts=elparts)
            call factor_solve(t)
            if (status /= GA_OK) goto 900
            ! rhs = -dr/dp + beta' M Qhat + C_t (gamma' Qhat - Vhat)
            acc = qddt(:, j) - m%gacc
            call contract(qt(:, j), qdt(:, j), acc, z(1:nd, :), pe=elparts)
            do f = 1, nf
                call mass_times(m, z(1:nd, f), w(:, f))
                qhb(:, f) = qhb(:, f) + betap * w(:, f)
            end do
            if (m%nsd > 0 .or. m%damped) then
                call damping_times(m, qt(:, j), qdt(:, j), z(1:nd, :), w, transposed=.true.)
                qhb = qhb + gammap * w
                vhb = vhb - w
            end if
            ! Qhat = q_n + h qd_n + h^2 ((1/2 - beta) a_n + beta ap),
            ! Vhat = qd_n + h ((1 - gamma) a_n + gamma ap), ap = (alpha_f qdd_n - alpha_m a_n) / (1 - alpha_m)
            qb = qhb
            if (gidx(j - 1) > 0) qb = qb + gq(:, :, j0 + gidx(j - 1))
            qdb = h * qhb + vhb
            ab = h**2 * (0.5_wp - beta) * qhb + h * (1 - gamma) * vhb
            apb = apb + h**2 * beta * qhb + h * gamma * vhb
            qddb = alpha_f / (1 - alpha_m) * apb
            ab = ab - alpha_m / (1 - alpha_m) * apb
            ! the step-change rescaling of a_n at its start (ga_step): a_n <- qdd_n +
            ! r (a_n - qdd_n), r = h / th(j - 1) when the step before (th(1): the one before
            ! the first state, 0 at the run's start) was another length; its transpose
            if (th(j - 1) > 0 .and. h /= th(j - 1)) then
                qddb = qddb + (1 - h / th(j - 1)) * ab
                ab = (h / th(j - 1)) * ab
            end if
            t = t - h
        end do
        if (present(adj_out)) then
            adj_out(:, :, 1) = qb
            adj_out(:, :, 2) = qdb
            adj_out(:, :, 3) = qddb
            adj_out(:, :, 4) = ab
        end if
        if (j0 > 0) goto 800      ! an earlier segment holds the initial state

        ! --- initial state: a_0 = qdd_0 ------------------------------------------------
        qddb = qddb + ab
        k0 = mass_scale(m)
        call iteration_matrix(m, qt(:, 1), qd0, mut(1:nc, 1) * 0, 0.0_wp, 1.0_wp, 0.0_wp, 0.0_wp, &
                              k0, 0.0_wp, vals)
        ! accelerations: [M k0 Phi_q^T; k0 Phi_q 0] [qdd'; lam'] = [-dr/dp - K q0' - C qd'; -k0 (c1 + 2 c2)]
        z(1:nd, :) = qddb
        if (nc > 0) z(nd + 1:, :) = k0 * gmu(1:nc, :, 1)
        call factor_solve(0.0_wp, GA_INITIAL_SINGULAR)
        if (status /= GA_OK) goto 900
        acc = qddt(:, 1) - m%gacc
        call contract(qt(:, 1), qdt(:, 1), acc, z(1:nd, :))
        if (m%nsd > 0 .or. m%damped) then
            call damping_times(m, qt(:, 1), qdt(:, 1), z(1:nd, :), w, transposed=.true.)
            qdb = qdb - w
        end if
        do f = 1, nf
            if (nc > 0) then
                w(:, f) = 0
                call add_curvature_times(m, qt(:, 1), z(nd + 1:, f), qdt(:, 1), w(:, f))
                qdb(:, f) = qdb(:, f) - 2 * k0 * w(:, f)
            end if
            if (s%static_start) then
                call stiffness_times(m, qt(:, 1), qdt(:, 1), mut(1:nc, 1), z(1:nd, f), w(:, f), &
                                     transposed=.true.)
                qb(:, f) = qb(:, f) - w(:, f)
                if (m%nsd > 0) then
                    call spring_times(m, qt(:, 1), qdt(:, 1), z(1:nd, f), 1.0_wp, 0.0_wp, w(:, f), &
                                      transposed=.true.)
                    qb(:, f) = qb(:, f) - w(:, f)
                end if
                if (nc > 0) then
                    w(:, f) = 0
                    call add_curvature_times(m, qt(:, 1), z(nd + 1:, f), qddt(:, 1), w(:, f))
                    qb(:, f) = qb(:, f) - k0 * w(:, f)
                end if
            end if
        end do
        ! velocities: [M k0 Phi_q^T; k0 Phi_q 0] [qd'; nu'] = [dM/dp (qd0 - qd); -k0 c1(q0', qd)]
        z(1:nd, :) = qdb
        if (nc > 0) z(nd + 1:, :) = 0
        call solve_only(0.0_wp)
        if (status /= GA_OK) goto 900
        acc = qd0 - qdt(:, 1)
        call contract(qt(:, 1), qdt(:, 1), acc, z(1:nd, :), velocity=.true.)
        if (s%static_start .and. nc > 0) then
            do f = 1, nf
                w(:, f) = 0
                call add_curvature_times(m, qt(:, 1), z(nd + 1:, f), qdt(:, 1), w(:, f))
                qb(:, f) = qb(:, f) - k0 * w(:, f)
            end do
        end if
        if (s%static_start) then
            call static_adjoint()
            if (status /= GA_OK) goto 900
        end if

        ! --- contraction with the section derivatives -------------------------------------
800     continue
        do f = 1, nf
            do v = 1, nv
                grad(v, f) = sum(gprop(:, 1:m%nel, f) * dprop(:, 1:m%nel, v))
            end do
        end do

900     continue
        call ls_free(ls)

    contains

        !> An adjoint state array (adj_in, adj_out) has the shape (nd, nf, >= 4).
        pure logical function adjoint_state_fits(a)
            real(wp), intent(in) :: a(:, :, :)
            adjoint_state_fits = size(a, 1) == nd .and. size(a, 2) == nf .and. size(a, 3) >= 4
        end function adjoint_state_fits

        !> Factor `vals` and solve the transpose in place in z.
        subroutine factor_solve(tt, singular)
            real(wp), intent(in) :: tt
            integer, intent(in), optional :: singular
            integer :: lst
            call ls_factor(ls, vals, lst)
            if (lst /= LS_OK) then
                status = GA_SINGULAR
                if (present(singular)) status = singular
                if (lst == LS_NO_MEMORY) status = GA_NO_MEMORY
                info = [tt, 0.0_wp, 0.0_wp, real(lst, wp)]
                return
            end if
            call solve_only(tt)
        end subroutine factor_solve

        subroutine solve_only(tt)
            real(wp), intent(in) :: tt
            integer :: lst
            call ls_solve(ls, z, lst, transposed=.true.)
            if (lst /= LS_OK) then
                status = GA_NONFINITE
                info = [tt, 0.0_wp, 0.0_wp, real(lst, wp)]
            end if
        end subroutine solve_only

        !> gprop(:, e, f) += y_f^T d(rhs)/dprop_e: the right-hand side of the direct method
        !! -(df_int/dp + dM/dp acc) at (q, qv), or with velocity, +dM/dp acc (acc = qd0 - qd).
        subroutine contract(q, qv, accv, y, velocity, pe)
            real(wp), intent(in) :: q(nd), qv(nd), accv(nd), y(:, :)
            logical, intent(in), optional :: velocity
            !> the elements' forces per unit stiffness at q when already computed
            real(wp), intent(in), optional :: pe(:, :, :)
            real(wp) :: fe(MAX_EDOF), parts(MAX_EDOF, 3), qe(MAX_EDOF), qr(MAX_EDOF)
            real(wp) :: ae(MAX_EDOF), ya(MAX_EDOF), yi(MAX_EDOF), ye(MAX_EDOF), ve(MAX_EDOF), sg
            integer :: ee, ne, a, ff, d
            logical :: vel
            vel = .false.
            if (present(velocity)) vel = velocity
            sg = merge(1.0_wp, -1.0_wp, vel)
            do ee = 1, m%nel
                ne = 3 * m%el_nen(ee)
                do a = 1, ne
                    d = m%el_dofs(a, ee)
                    qe(a) = q(d)
                    qr(a) = m%qref(d)
                    ae(a) = accv(d)
                    ve(a) = qv(d)
                end do
                if (stiff(ee) .and. .not. vel) then
                    if (present(pe)) then
                        parts(1:ne, :) = pe(1:ne, :, ee)
                    else
                        call beam_internal_forces(m%el_nen(ee), m%el_len(ee), m%el_prop(1:3, ee), &
                            qr(1:ne), qe(1:ne), fe(1:ne), parts=parts(1:ne, :), eref=m%el_eref(:, :, ee), &
                            eta=m%el_eta(ee), qde=ve(1:ne))
                    end if
                end if
                if (mass(ee)) then
                    ya(1:ne) = matmul(m%el_mass_a(1:ne, 1:ne, ee), ae(1:ne))
                    yi(1:ne) = matmul(m%el_mass_i(1:ne, 1:ne, ee), ae(1:ne))
                end if
                do ff = 1, nf
                    do a = 1, ne
                        ye(a) = y(m%el_dofs(a, ee), ff)
                    end do
                    if (stiff(ee) .and. .not. vel) then
                        do a = 1, 3
                            gprop(a, ee, ff) = gprop(a, ee, ff) - dot_product(ye(1:ne), parts(1:ne, a))
                        end do
                    end if
                    if (mass(ee)) then
                        gprop(4, ee, ff) = gprop(4, ee, ff) + sg * dot_product(ye(1:ne), ya(1:ne))
                        gprop(5, ee, ff) = gprop(5, ee, ff) + sg * dot_product(ye(1:ne), yi(1:ne))
                    end if
                end do
            end do
        end subroutine contract

        !> Transpose of the static start: [K_s k Phi_q^T; k Phi_q 0] [q0'; lam'] = [-(df_int/dp - dM/dp g); 0].
        !! The static state is recomputed (the same deterministic Newton iteration from q0).
        subroutine static_adjoint()
            type(ga_state) :: xs
            type(ga_stats) :: sst
            real(wp) :: ks, ps, qzero(nd), sinfo(4)
            integer :: sstat, ierr2
            allocate (xs%q(nd), xs%qd(nd), xs%qdd(nd), xs%a(nd), xs%mu(nc), xs%qdd_prev(nd), stat=ierr2)
            if (ierr2 /= 0) then
                status = GA_NO_MEMORY
                return
            end if
            xs%q = q0
            xs%qd = 0
            xs%qdd = 0
            xs%mu = 0
            call static_equilibrium(m, s, ls, vals, fgrav, xs, sst, sstat, sinfo, ks, ps)
            if (sstat /= GA_OK) then
                status = merge(GA_INTERRUPTED, GA_STATIC_FAILED, sstat == GA_INTERRUPTED)
                info = sinfo
                return
            end if
            qzero = 0
            call iteration_matrix(m, xs%q, qzero, xs%mu, 0.0_wp, 0.0_wp, 1.0_wp, 0.0_wp, ks, ps, vals)
            z(1:nd, :) = qb
            if (nc > 0) z(nd + 1:, :) = 0
            call factor_solve(0.0_wp, GA_STATIC_FAILED)
            if (status /= GA_OK) return
            acc = -m%gacc
            call contract(xs%q, qzero, acc, z(1:nd, :))
        end subroutine static_adjoint

    end subroutine ga_adjoint

end module adjoint
