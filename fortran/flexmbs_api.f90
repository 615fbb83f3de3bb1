!> The f2py surface of the flexmbs core (compiled as flexmbs._core).
!!
!! This is the only file f2py reads. Every routine takes plain scalars and
!! arrays: real(c_double), integer(c_int), Fortran-ordered. Status codes are
!! returned, never printed; flexmbs (Python) turns them into exceptions.

!> Make the BLAS used by the core single-threaded (see klu_shim.c); called once
!! when flexmbs is imported. applied = 1 if the BLAS supports it.
subroutine blas_single_thread(applied)
    use iso_c_binding, only: c_int
    implicit none
    integer(c_int), intent(out) :: applied
    interface
        function fx_blas_single_thread() bind(c, name='fx_blas_single_thread')
            import :: c_int
            integer(c_int) :: fx_blas_single_thread
        end function fx_blas_single_thread
    end interface
    applied = fx_blas_single_thread()
end subroutine blas_single_thread

!> Solve A X = B with the dense LU path (LAPACK).
subroutine dense_solve(n, nrhs, a, b, x, status)
    use iso_c_binding, only: c_double, c_int
    use linear_solver, only: linear_system, ls_init_dense, ls_factor, ls_solve, ls_free
    !f2py threadsafe
    implicit none
    integer(c_int), intent(in) :: n                 !! order
    integer(c_int), intent(in) :: nrhs              !! number of right-hand sides
    real(c_double), intent(in) :: a(n, n)           !! matrix
    real(c_double), intent(in) :: b(n, nrhs)        !! right-hand sides
    real(c_double), intent(out) :: x(n, nrhs)       !! solutions
    integer(c_int), intent(out) :: status           !! 0 ok, 1 singular, 2 out of memory,
                                                    !! 3 invalid, 4 non-finite
    type(linear_system) :: ls
    real(c_double), allocatable :: av(:)
    integer :: st, j, ierr
    x = b
    call ls_init_dense(ls, int(n), st)
    if (st == 0) then
        allocate (av(int(n) * int(n)), stat=ierr)
        if (ierr /= 0) st = 2
    end if
    if (st == 0) then
        do j = 1, n
            av((j - 1) * n + 1:j * n) = a(:, j)
        end do
        call ls_factor(ls, av, st)
    end if
    if (st == 0) call ls_solve(ls, x, st)
    status = int(st, c_int)
    call ls_free(ls)
end subroutine dense_solve

!> Solve A X = B with KLU, then refactor with new values of the same pattern
!! and solve A2 X2 = B2 (exercises the symbolic-once / numeric-refactor path).
subroutine sparse_solve(n, nnz, nrhs, ap, ai, ax, ax2, b, b2, x, x2, status)
    use iso_c_binding, only: c_double, c_int
    use linear_solver, only: linear_system, ls_init_sparse, ls_factor, ls_solve, ls_free
    !f2py threadsafe
    implicit none
    integer(c_int), intent(in) :: n                 !! order
    integer(c_int), intent(in) :: nnz               !! stored values
    integer(c_int), intent(in) :: nrhs              !! number of right-hand sides
    integer(c_int), intent(in) :: ap(n + 1)         !! CSC column pointers, 0-based
    integer(c_int), intent(in) :: ai(nnz)           !! CSC row indices, 0-based
    real(c_double), intent(in) :: ax(nnz)           !! values of the first matrix
    real(c_double), intent(in) :: ax2(nnz)          !! values of the second matrix (same pattern)
    real(c_double), intent(in) :: b(n, nrhs)        !! right-hand sides of the first system
    real(c_double), intent(in) :: b2(n, nrhs)       !! right-hand sides of the second system
    real(c_double), intent(out) :: x(n, nrhs)       !! first solutions
    real(c_double), intent(out) :: x2(n, nrhs)      !! second solutions
    integer(c_int), intent(out) :: status           !! 0 ok; 10*stage + LS code otherwise
    type(linear_system) :: ls
    integer :: st
    x = 0
    x2 = 0
    call ls_init_sparse(ls, int(n), int(ap), int(ai), st)
    if (st /= 0) then
        status = int(10 + st, c_int)
        return
    end if
    call ls_factor(ls, ax, st)
    x = b
    if (st == 0) call ls_solve(ls, x, st)
    if (st /= 0) then
        status = int(20 + st, c_int)
        call ls_free(ls)
        return
    end if
    call ls_factor(ls, ax2, st)
    x2 = b2
    if (st == 0) call ls_solve(ls, x2, st)
    status = 0
    if (st /= 0) status = int(30 + st, c_int)
    call ls_free(ls)
end subroutine sparse_solve

!> KLU's symbolic analysis of a CSC pattern (0-based), made once per model and handed to
!! its simulations (`simulate`, `simulate_adjoint`: klu_analysis) so that they do not
!! analyse the pattern again. handle: an opaque address (0 on failure), released by
!! klu_analysis_free; status 0 ok, 2 out of memory, 3 invalid pattern.
subroutine klu_analyze(n, nnz, ap, ai, handle, status)
    use iso_c_binding, only: c_int, c_ptr
    !f2py threadsafe
    implicit none
    integer(c_int), intent(in) :: n                 !! order
    integer(c_int), intent(in) :: nnz               !! stored values
    integer(c_int), intent(in) :: ap(n + 1)         !! CSC column pointers, 0-based
    integer(c_int), intent(in) :: ai(nnz)           !! CSC row indices, 0-based
    integer(8), intent(out) :: handle
    integer(c_int), intent(out) :: status
    interface
        function fx_klu_analyze(n, nnz, ap, ai, status) bind(c, name='fx_klu_analyze')
            import :: c_ptr, c_int
            integer(c_int), value :: n, nnz
            integer(c_int), intent(in) :: ap(*), ai(*)
            integer(c_int), intent(out) :: status
            type(c_ptr) :: fx_klu_analyze
        end function fx_klu_analyze
    end interface
    type(c_ptr) :: p
    handle = 0
    status = 3
    if (n < 1 .or. nnz < 1 .or. ap(1) /= 0 .or. ap(n + 1) /= nnz) return
    p = fx_klu_analyze(n, nnz, ap, ai, status)
    if (status == 0) handle = transfer(p, handle)
end subroutine klu_analyze

!> Release an analysis made by klu_analyze (no simulation may be using it). 0 is ignored.
subroutine klu_analysis_free(handle)
    use iso_c_binding, only: c_ptr
    !f2py threadsafe
    implicit none
    integer(8), intent(in) :: handle
    interface
        subroutine fx_klu_analysis_free(a) bind(c, name='fx_klu_analysis_free')
            import :: c_ptr
            type(c_ptr), value :: a
        end subroutine fx_klu_analysis_free
    end interface
    type(c_ptr) :: p
    if (handle == 0) return
    p = transfer(handle, p)
    call fx_klu_analysis_free(p)
end subroutine klu_analysis_free

!> The model of a mechanism (see flexmbs.model for the meaning of every array), built once
!! and held by Python behind an opaque address (flexmbs.core.CoreModel): the arrays that do
!! not depend on the design or the time grid, with the per-element mass matrices per unit
!! rhoA and rhoI and the reference strains. `simulate`, `simulate_adjoint` and
!! `system_matrices` take the handle and only read its model (runs in parallel threads may
!! share it). handle: 0 on failure; released by model_destroy. status 0 ok, 1 out of
!! memory (nbytes: the size asked for).
subroutine model_create(ndof, nc, nel, nload, nlaw, nnz, nela, nca, nlda, &
                        qref, lumped, gacc, el_nen, el_dofs, el_len, el_eta, &
                        ld_dof, ld_law, ld_amp, c_kind, c_dofs, c_coef, c_c0, c_law, c_lawcoef, &
                        map_el, map_diag, map_cq, map_qc, map_qq, &
                        nsd, nsda, sd_dofs, sd_prop, map_sd, handle, status, nbytes)
    use iso_c_binding, only: c_double, c_int, c_int64_t
    use model_data, only: mbs_model, model_from_arrays, model_address
    !f2py threadsafe
    implicit none
    integer(c_int), intent(in) :: ndof, nc, nel, nload, nlaw, nnz   !! true counts
    integer(c_int), intent(in) :: nela, nca, nlda                   !! array extents (>= 1)
    real(c_double), intent(in) :: qref(ndof), lumped(ndof), gacc(ndof)
    integer(c_int), intent(in) :: el_nen(nela), el_dofs(9, nela)
    real(c_double), intent(in) :: el_len(nela)
    real(c_double), intent(in) :: el_eta(nela)          !! Kelvin-Voigt time per element (s)
    integer(c_int), intent(in) :: ld_dof(nlda), ld_law(nlda)
    real(c_double), intent(in) :: ld_amp(nlda)
    integer(c_int), intent(in) :: c_kind(nca), c_dofs(5, nca), c_law(nca)
    real(c_double), intent(in) :: c_coef(5, nca), c_c0(nca), c_lawcoef(nca)
    integer(c_int), intent(in) :: map_el(81, nela), map_diag(ndof)
    integer(c_int), intent(in) :: map_cq(5, nca), map_qc(5, nca), map_qq(25, nca)
    integer(c_int), intent(in) :: nsd, nsda                 !! spring-dampers, extent (>= 1)
    integer(c_int), intent(in) :: sd_dofs(4, nsda)          !! x_a, y_a, x_b, y_b (1-based)
    real(c_double), intent(in) :: sd_prop(4, nsda)          !! k, c, l0, f0
    integer(c_int), intent(in) :: map_sd(16, nsda)          !! value positions of the 4 x 4 blocks
    integer(c_int64_t), intent(out) :: handle
    integer(c_int), intent(out) :: status
    real(c_double), intent(out) :: nbytes
    type(mbs_model), pointer :: p
    real(c_double), allocatable :: no_prop(:, :)
    real(c_double) :: no_law(1, 2), no_dd0(1)
    integer :: stat
    handle = 0
    status = 1
    nbytes = 0
    ! the design's properties and the grid's law tables come with each run (model_of_run)
    allocate (no_prop(5, nela), stat=stat)
    if (stat /= 0) then
        nbytes = 8.0_c_double * 5 * nela
        return
    end if
    allocate (p, stat=stat)
    if (stat /= 0) then
        nbytes = -1
        return
    end if
    no_prop = 0
    no_law = 0
    no_dd0 = 0
    call model_from_arrays(p, int(ndof), int(nc), int(nel), int(nload), int(nlaw), int(nnz), &
                           qref, lumped, gacc, el_nen, el_dofs, el_len, no_prop, &
                           ld_dof, ld_law, ld_amp, c_kind, c_dofs, c_coef, &
                           c_c0, c_law, c_lawcoef, 1.0_c_double, no_law, no_law, no_dd0, &
                           map_el, map_diag, map_cq, map_qc, map_qq, stat, nbytes, &
                           int(nsd), int(sd_dofs), sd_prop, int(map_sd), el_eta)
    if (stat /= 0) then
        deallocate (p)
        return
    end if
    status = 0
    handle = model_address(p)
end subroutine model_create

!> Release a model made by model_create (no run may be using it). 0 is ignored.
subroutine model_destroy(handle)
    use iso_c_binding, only: c_int64_t
    use model_data, only: mbs_model, model_at, model_free
    !f2py threadsafe
    implicit none
    integer(c_int64_t), intent(in) :: handle
    type(mbs_model), pointer :: p
    p => model_at(handle)
    if (.not. associated(p)) return
    call model_free(p)
    deallocate (p)
end subroutine model_destroy

!> The counts of the model at a handle from model_create: ndof, nc, nel, nload, nlaw, nnz,
!! nsd and n = ndof + nc (all 0 for the null handle).
subroutine model_counts(handle, counts)
    use iso_c_binding, only: c_int, c_int64_t
    use model_data, only: mbs_model, model_at
    !f2py threadsafe
    implicit none
    integer(c_int64_t), intent(in) :: handle
    integer(c_int), intent(out) :: counts(8)
    type(mbs_model), pointer :: p
    counts = 0
    p => model_at(handle)
    if (.not. associated(p)) return
    counts = int([p%ndof, p%nc, p%nel, p%nload, p%nlaw, p%nnz, p%nsd, p%n], c_int)
end subroutine model_counts

!> Simulate a mechanism: the model at a handle from model_create, the design's element
!! properties el_prop and the laws tabulated on the run's grid (flexmbs.core.core_model_args).
!! status: 0 ok, 1 Newton failed after step cuts, 2 singular iteration matrix,
!! 3 static equilibrium failed, 4 singular initial system, 5 inconsistent initial
!! configuration, 6 non-finite values, 7 bad settings, 8 linear solver set-up,
!! 9 an allocation failed (nothing is left allocated), 10 the tape is full, 11 interrupted
!! (the caller's cancel flag was set); 7 also for a null model handle or
!! extents (ndof, nca, nela, law rows) of another model.
!! info: time, scaled increment or residual, iterations, extra (row / code);
!! for status 9: time, bytes asked for (-1: unknown), 0, what (1 iteration matrix,
!! 2 dense LU factors, 3 KLU factorization, 4 state vectors, 5 sensitivity work
!! arrays, 6 model arrays).
!! stats: newton iterations, factorizations, residual evaluations, step cuts,
!! static iterations, steps completed, factorizations made for the sensitivities
!! (included in the factorizations), KLU symbolic analyses run (0 when borrowed).
subroutine simulate(model, ndof, nca, nela, nlawa, npts, nout, nsteps, q0, qd0, el_prop, &
                    law_h, law_val, law_der, law_dd0, nap, nai, ap, ai, &
                    h, rho_inf, tol, max_iter, max_cuts, solver, newton, static_start, &
                    kscale, penalty, out_dofs, q_out, qd_out, qdd_out, mu_out, stats, status, info, &
                    nv, nva, nsens, dprop, sens_dofs, dq_out, want_dmu, ndmu, dmu_out, polish, &
                    ntape, tape_q, tape_qd, tape_qdd, tape_mu, tape_h, tape_grid, ntape_used, &
                    nckr, nck, ckpt_every, ckpt, restart, x_start, j_start, klu_analysis, ntg, tg, &
                    cancel)
    use iso_c_binding, only: c_double, c_int, c_int64_t, c_loc
    use model_data, only: mbs_model, model_of_run
    use generalized_alpha, only: ga_settings, ga_stats, ga_simulate, ga_set_grid, &
                                 GA_NO_MEMORY, MEM_MODEL, &
                                 GA_BAD_INPUT
    !f2py threadsafe
    implicit none
    integer(c_int64_t), intent(in) :: model    !! the model (model_create)
    integer(c_int), intent(in) :: ndof, nca    !! its coordinates and multiplier rows (max(nc, 1))
    integer(c_int), intent(in) :: nela, nlawa, npts     !! extents: elements, laws (>= 1), grid
    real(c_double), intent(in) :: q0(ndof), qd0(ndof)   !! initial state
    real(c_double), intent(in) :: el_prop(5, nela)      !! the design: EA, kGA, EI, rhoA, rhoI
    !> the laws tabulated on the run's grid (step law_h): values, rates, d2/dt2 at t = 0
    real(c_double), intent(in) :: law_h, law_val(nlawa, npts), law_der(nlawa, npts), law_dd0(nlawa)
    integer(c_int), intent(in) :: nout, nsteps
    integer(c_int), intent(in) :: nap, nai
    integer(c_int), intent(in) :: ap(nap), ai(nai)
    real(c_double), intent(in) :: h, rho_inf, tol, kscale, penalty
    integer(c_int), intent(in) :: max_iter, max_cuts, solver, static_start
    integer(c_int), intent(in) :: newton       !! 0 full Newton, 1 modified (reuse), 2 automatic
    integer(c_int), intent(in) :: out_dofs(nout)
    real(c_double), intent(out) :: q_out(nout, nsteps + 1), qd_out(nout, nsteps + 1)
    real(c_double), intent(out) :: qdd_out(nout, nsteps + 1), mu_out(nca, nsteps + 1)
    integer(c_int), intent(out) :: stats(8), status
    real(c_double), intent(out) :: info(4)
    integer(c_int), intent(in) :: nv                        !! design variables (0: no sensitivities)
    integer(c_int), intent(in) :: nva, nsens                !! extents (>= 1)
    real(c_double), intent(in) :: dprop(5, nela, nva)       !! d[EA,kGA,EI,rhoA,rhoI]/dp per element
    integer(c_int), intent(in) :: sens_dofs(nsens)          !! coordinates whose dq/dp is returned
    real(c_double), intent(out) :: dq_out(nsens, nva, nsteps + 1)  !! dq/dp on the grid
    integer(c_int), intent(in) :: want_dmu                  !! 1: return d(mu)/dp (needs nv > 0)
    integer(c_int), intent(in) :: ndmu                      !! extent: nca when want_dmu, else 1
    real(c_double), intent(out) :: dmu_out(ndmu, nva, nsteps + 1)  !! d(mu)/dp on the grid
    !> 1: modified Newton converges every step to the rounding level (states as full
    !! Newton's, for the adjoint: ga_settings%polish), 0: not
    integer(c_int), intent(in) :: polish
    !> tape of every (sub-)step for the adjoint (generalized_alpha.f90): kept when ntape >=
    !! nsteps + 1 (status 10 when the sub-steps need more columns); extent 1 otherwise
    integer(c_int), intent(in) :: ntape
    real(c_double), intent(out) :: tape_q(ndof, ntape), tape_qd(ndof, ntape), tape_qdd(ndof, ntape)
    real(c_double), intent(out) :: tape_mu(nca, ntape), tape_h(ntape)
    integer(c_int), intent(out) :: tape_grid(nsteps + 1)     !! column of every grid point
    integer(c_int), intent(out) :: ntape_used                !! columns used
    !> checkpoints (generalized_alpha.f90 ga_simulate, ckpt_rows = 5 ndof + nc + 3 numbers
    !! each): with ckpt_every > 0 the full state at every ckpt_every-th grid point, in
    !! ckpt(:, j / ckpt_every + 1); with restart = 1 the run starts from the state x_start
    !! at grid point j_start (a segment of a checkpointed run; not with nv > 0)
    integer(c_int), intent(in) :: nckr, nck, ckpt_every, restart, j_start
    real(c_double), intent(out) :: ckpt(nckr, nck)
    real(c_double), intent(in) :: x_start(nckr)
    !> KLU's symbolic analysis of (ap, ai) from klu_analyze (made once per model), or 0:
    !! the run analyses the pattern itself (stats(8) = 1)
    integer(8), intent(in) :: klu_analysis
    !> a non-uniform grid (ga_settings%tgrid): the times of the whole run's grid points,
    !! t_0 = 0 < t_1 < ... (at least j_start + nsteps + 1); ntg = 1: the uniform grid j h
    integer(c_int), intent(in) :: ntg
    real(c_double), intent(in) :: tg(ntg)
    !> the caller's cancel flag, passed by reference and read once per step: set to non-zero
    !! by another thread during the run, it ends the run with status 11 (interrupted; info(1):
    !! the time reached). Each run has its own (flexmbs.core.run_interruptible)
    integer(c_int), intent(inout), target :: cancel(1)
    integer :: tgrid(nsteps + 1), tused
    type(mbs_model) :: m
    type(ga_settings) :: s
    type(ga_stats) :: st
    integer :: stat
    real(c_double) :: nbytes
    q_out = 0; qd_out = 0; qdd_out = 0; mu_out = 0; dq_out = 0; dmu_out = 0; stats = 0; info = 0
    tape_q = 0; tape_qd = 0; tape_qdd = 0; tape_mu = 0; tape_h = 0; tape_grid = 0; ntape_used = 0
    ckpt = 0
    tgrid = 0
    tused = 0
    call model_of_run(m, model, int(ndof), int(nca), el_prop, law_h, law_val, law_der, law_dd0, &
                      stat, nbytes)
    if (stat /= 0) then
        status = int(merge(GA_NO_MEMORY, GA_BAD_INPUT, stat == 1), c_int)
        if (stat == 1) info = [0.0_c_double, nbytes, 0.0_c_double, real(MEM_MODEL, c_double)]
        return
    end if
    s = ga_settings(h=h, rho_inf=rho_inf, tol=tol, nsteps=int(nsteps), max_iter=int(max_iter), &
                    max_cuts=int(max_cuts), solver=int(solver), newton=int(newton), &
                    static_start=static_start /= 0, kscale=kscale, penalty=penalty, &
                    polish=polish /= 0)
    s%klu_analysis = transfer(klu_analysis, s%klu_analysis)
    s%cancel = c_loc(cancel)
    call ga_set_grid(s, tg, stat, info)     ! a non-uniform grid (ntg > 1), or GA_NO_MEMORY
    if (stat /= 0) then
        status = int(stat, c_int)
        return
    end if
    if (nv > 0 .and. want_dmu /= 0 .and. ndmu >= m%nc) then
        call ga_simulate(m, s, int(ap), int(ai), q0, qd0, int(out_dofs), q_out, qd_out, qdd_out, &
                         mu_out, st, stat, info, dprop(:, :, 1:nv), int(sens_dofs), dq_out(:, 1:nv, :), &
                         dmu_out(:, 1:nv, :), tape_q=tape_q, tape_qd=tape_qd, tape_qdd=tape_qdd, &
                         tape_mu=tape_mu, tape_h=tape_h, tape_grid=tgrid, ntape=tused)
    else if (nv > 0) then
        call ga_simulate(m, s, int(ap), int(ai), q0, qd0, int(out_dofs), q_out, qd_out, qdd_out, &
                         mu_out, st, stat, info, dprop(:, :, 1:nv), int(sens_dofs), dq_out(:, 1:nv, :), &
                         tape_q=tape_q, tape_qd=tape_qd, tape_qdd=tape_qdd, tape_mu=tape_mu, &
                         tape_h=tape_h, tape_grid=tgrid, ntape=tused)
    else if (restart /= 0) then
        dq_out = 0
        call ga_simulate(m, s, int(ap), int(ai), q0, qd0, int(out_dofs), q_out, qd_out, qdd_out, &
                         mu_out, st, stat, info, tape_q=tape_q, tape_qd=tape_qd, tape_qdd=tape_qdd, &
                         tape_mu=tape_mu, tape_h=tape_h, tape_grid=tgrid, ntape=tused, &
                         ckpt_every=int(ckpt_every), ckpt=ckpt, x_start=x_start, j_start=int(j_start))
    else
        dq_out = 0
        call ga_simulate(m, s, int(ap), int(ai), q0, qd0, int(out_dofs), q_out, qd_out, qdd_out, &
                         mu_out, st, stat, info, tape_q=tape_q, tape_qd=tape_qd, tape_qdd=tape_qdd, &
                         tape_mu=tape_mu, tape_h=tape_h, tape_grid=tgrid, ntape=tused, &
                         ckpt_every=int(ckpt_every), ckpt=ckpt)
    end if
    if (restart /= 0 .and. nv > 0) stat = GA_BAD_INPUT
    status = int(stat, c_int)
    tape_grid = int(tgrid, c_int)
    ntape_used = int(tused, c_int)
    stats = int([st%newton_iterations, st%factorizations, st%residual_evaluations, &
                 st%step_cuts, st%static_iterations, st%steps, st%sensitivity_factorizations, &
                 st%symbolic_analyses], &
                c_int)
end subroutine simulate

!> Discrete adjoint of a converged simulation (adjoint.f90, docs/adjoint.md): the design
!! gradients grad(v, f) of nf functionals G_f = sum_j gq(:, f, j) . q_j + gmu(:, f, j) . mu_j
!! of the solution, from the tape of a forward run with the same model, settings, q0 and
!! qd0 (qt, qdt, qddt, mut, th, grid: its tape_q, tape_qd, tape_qdd, tape_mu, tape_h,
!! tape_grid; ncol = ntape_used). gprop(:, e, f) = dG_f/d[EA, kGA, EI, rhoA, rhoI]_e.
!! status as `simulate`. Segments of a checkpointed run (adjoint.f90 ga_adjoint): the tape
!! of the nsteps steps from grid point j_start, gq and gmu over the whole run's ntot points,
!! with have_in = 1 the adjoint state adj_in from the later segment, adj_out for the earlier
!! one, gprop_in the later segments' gprop (added to).
subroutine simulate_adjoint(model, ndof, nca, nela, nlawa, npts, nsteps, q0, qd0, el_prop, &
                   law_h, law_val, law_der, law_dd0, nap, nai, ap, ai, &
                   h, rho_inf, tol, max_iter, max_cuts, solver, static_start, kscale, penalty, &
                   ncol, qt, qdt, qddt, mut, th, grid, nf, gq, gmu, nv, dprop, grad, gprop, &
                   status, info, ntot, j_start, have_in, adj_in, adj_out, gprop_in, klu_analysis, &
                   ntg, tg, cancel)
    use iso_c_binding, only: c_double, c_int, c_int64_t, c_loc
    use model_data, only: mbs_model, model_of_run
    use generalized_alpha, only: ga_settings, ga_set_grid, GA_NO_MEMORY, MEM_MODEL, GA_BAD_INPUT
    use adjoint, only: ga_adjoint
    !f2py threadsafe
    implicit none
    integer(c_int64_t), intent(in) :: model             !! as `simulate`'s
    integer(c_int), intent(in) :: ndof, nca, nela, nlawa, npts
    real(c_double), intent(in) :: q0(ndof), qd0(ndof)
    real(c_double), intent(in) :: el_prop(5, nela)
    real(c_double), intent(in) :: law_h, law_val(nlawa, npts), law_der(nlawa, npts), law_dd0(nlawa)
    integer(c_int), intent(in) :: nsteps
    integer(c_int), intent(in) :: nap, nai
    integer(c_int), intent(in) :: ap(nap), ai(nai)
    real(c_double), intent(in) :: h, rho_inf, tol, kscale, penalty
    integer(c_int), intent(in) :: max_iter, max_cuts, solver, static_start
    integer(c_int), intent(in) :: ncol                               !! tape columns
    real(c_double), intent(in) :: qt(ndof, ncol), qdt(ndof, ncol)    !! the forward run's tape
    real(c_double), intent(in) :: qddt(ndof, ncol), mut(nca, ncol)
    real(c_double), intent(in) :: th(ncol)                           !! step leading to a column
    integer(c_int), intent(in) :: grid(nsteps + 1)                   !! column of grid point j
    integer(c_int), intent(in) :: nf                                  !! functionals
    integer(c_int), intent(in) :: ntot                                !! grid points of the run
    real(c_double), intent(in) :: gq(ndof, nf, ntot)                 !! dG_f/dq_j
    real(c_double), intent(in) :: gmu(nca, nf, ntot)                 !! dG_f/dmu_j
    integer(c_int), intent(in) :: nv
    real(c_double), intent(in) :: dprop(5, nela, nv)
    real(c_double), intent(out) :: grad(nv, nf)
    real(c_double), intent(out) :: gprop(5, nela, nf)
    integer(c_int), intent(out) :: status
    real(c_double), intent(out) :: info(4)
    integer(c_int), intent(in) :: j_start, have_in
    real(c_double), intent(in) :: adj_in(ndof, nf, 4)
    real(c_double), intent(out) :: adj_out(ndof, nf, 4)
    real(c_double), intent(in) :: gprop_in(5, nela, nf)
    integer(8), intent(in) :: klu_analysis     !! as `simulate`'s
    integer(c_int), intent(in) :: ntg          !! as `simulate`'s: the grid's times, or 1
    real(c_double), intent(in) :: tg(ntg)
    integer(c_int), intent(inout), target :: cancel(1)     !! as `simulate`'s (read once per step)
    type(mbs_model) :: m
    type(ga_settings) :: s
    integer :: stat
    real(c_double) :: nbytes
    grad = 0; gprop = gprop_in; info = 0; adj_out = 0
    call model_of_run(m, model, int(ndof), int(nca), el_prop, law_h, law_val, law_der, law_dd0, &
                      stat, nbytes)
    if (stat /= 0) then
        status = int(merge(GA_NO_MEMORY, GA_BAD_INPUT, stat == 1), c_int)
        if (stat == 1) info = [0.0_c_double, nbytes, 0.0_c_double, real(MEM_MODEL, c_double)]
        return
    end if
    s = ga_settings(h=h, rho_inf=rho_inf, tol=tol, nsteps=int(nsteps), max_iter=int(max_iter), &
                    max_cuts=int(max_cuts), solver=int(solver), static_start=static_start /= 0, &
                    kscale=kscale, penalty=penalty)
    s%klu_analysis = transfer(klu_analysis, s%klu_analysis)
    s%cancel = c_loc(cancel)
    call ga_set_grid(s, tg, stat, info)     ! a non-uniform grid (ntg > 1), or GA_NO_MEMORY
    if (stat /= 0) then
        status = int(stat, c_int)
        return
    end if
    if (have_in /= 0) then
        call ga_adjoint(m, s, int(ap), int(ai), q0, qd0, qt, qdt, qddt, mut, th, int(grid), gq, gmu, &
                        dprop(:, 1:max(m%nel, 0), :), grad, gprop(:, 1:max(m%nel, 0), :), stat, info, &
                        j_start=int(j_start), adj_in=adj_in, adj_out=adj_out, accumulate=.true.)
    else
        call ga_adjoint(m, s, int(ap), int(ai), q0, qd0, qt, qdt, qddt, mut, th, int(grid), gq, gmu, &
                        dprop(:, 1:max(m%nel, 0), :), grad, gprop(:, 1:max(m%nel, 0), :), stat, info, &
                        j_start=int(j_start), adj_out=adj_out, accumulate=.true.)
    end if
    status = int(stat, c_int)
end subroutine simulate_adjoint

!> Element internal forces and tangents of one beam (for the tangent checker): with the
!! Kelvin-Voigt time eta and the velocities qde, fe includes the damping forces, ke is
!! d fe / d qe at fixed qde and ce = d fe / d qde (beam2d.f90).
subroutine beam_element(nen, elen, stiff, qref, qe, eta, qde, fe, ke, ce)
    use iso_c_binding, only: c_double, c_int
    use beam2d, only: beam_internal_forces
    implicit none
    integer(c_int), intent(in) :: nen                     !! 2 or 3
    real(c_double), intent(in) :: elen                    !! reference length
    real(c_double), intent(in) :: stiff(3)                !! EA, kGA, EI
    real(c_double), intent(in) :: qref(3 * nen), qe(3 * nen)
    real(c_double), intent(in) :: eta                     !! Kelvin-Voigt time (s)
    real(c_double), intent(in) :: qde(3 * nen)            !! velocities
    real(c_double), intent(out) :: fe(3 * nen), ke(3 * nen, 3 * nen), ce(3 * nen, 3 * nen)
    call beam_internal_forces(int(nen), elen, stiff, qref, qe, fe, ke, eta=eta, qde=qde, ce=ce)
end subroutine beam_element

!> Beam element mass matrix.
subroutine beam_element_mass(nen, elen, rho_a, rho_i, me)
    use iso_c_binding, only: c_double, c_int
    use beam2d, only: beam_mass
    implicit none
    integer(c_int), intent(in) :: nen
    real(c_double), intent(in) :: elen, rho_a, rho_i
    real(c_double), intent(out) :: me(3 * nen, 3 * nen)
    call beam_mass(int(nen), elen, rho_a, rho_i, me)
end subroutine beam_element_mass

!> Residual of eq. (1) and iteration matrix of eq. (7) of a model at one state
!! (dense storage: vals is the n x n matrix, column-major). With cm = 0, ck = 1,
!! cc = 0, kscale = 0, pen = 0 and mu = 0 the leading ndof x ndof block is K_t.
subroutine system_matrices(model, ndof, nc, nca, nela, nlawa, npts, nnz, el_prop, &
                           law_h, law_val, law_der, law_dd0, &
                           q, qdd, mu, t, cm, ck, kscale, pen, r, vals, phimax, status, qd, cc)
    use iso_c_binding, only: c_double, c_int, c_int64_t
    use model_data, only: mbs_model, model_of_run
    use assembly, only: residual, iteration_matrix, mass_times
    !f2py threadsafe
    implicit none
    integer(c_int64_t), intent(in) :: model                          !! as `simulate`'s
    integer(c_int), intent(in) :: ndof, nc, nca, nela, nlawa, npts
    integer(c_int), intent(in) :: nnz                                !! the model's stored values
    real(c_double), intent(in) :: el_prop(5, nela)
    real(c_double), intent(in) :: law_h, law_val(nlawa, npts), law_der(nlawa, npts), law_dd0(nlawa)
    real(c_double), intent(in) :: q(ndof), qdd(ndof), mu(nca), t   !! state
    real(c_double), intent(in) :: cm, ck, kscale, pen                !! coefficients (see assembly.f90)
    real(c_double), intent(out) :: r(ndof + nc)                      !! residual
    real(c_double), intent(out) :: vals(nnz)                         !! iteration matrix values
    real(c_double), intent(out) :: phimax                            !! max |Phi|
    integer(c_int), intent(out) :: status          !! 0 ok, 7 extents of another model, 9 out of memory
    real(c_double), intent(in) :: qd(ndof)                           !! velocities (spring-dampers)
    real(c_double), intent(in) :: cc                                 !! coefficient of C_t (gamma')
    type(mbs_model) :: m
    real(c_double) :: fgrav(ndof), nbytes
    integer :: stat
    r = 0; vals = 0; phimax = 0
    call model_of_run(m, model, int(ndof), int(nca), el_prop, law_h, law_val, law_der, law_dd0, &
                      stat, nbytes)
    if (stat == 0 .and. (nc /= m%nc .or. nnz /= m%nnz)) stat = 2
    status = int(merge(9, 7, stat == 1), c_int)
    if (stat /= 0) return
    status = 0
    call mass_times(m, m%gacc, fgrav)
    call residual(m, q, qd, qdd, mu(1:max(nc, 0)), t, fgrav, cm, kscale, pen, r, phimax)
    call iteration_matrix(m, q, qd, mu(1:max(nc, 0)), t, cm, ck, cc, kscale, pen, vals)
end subroutine system_matrices
