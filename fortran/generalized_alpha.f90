!> Generalized-alpha time integration of the index-3 DAE (1) with
!! Newton–Raphson on eq. (7), after Chung & Hulbert (1993) and the form of
!! Arnold & Brüls (2007) used by Géradin & Cardona: eqs. (3)–(6) of the paper.
!!
!! Also: the static equilibrium that starts a simulation under its loads at
!! the initial drive positions, the consistent initial velocities and
!! accelerations (never assumed zero), step cuts on Newton failure, and three
!! Newton strategies (ga_settings%newton): full Newton, modified Newton with the
!! legacy refresh rule, and the automatic strategy (the default from Python): the
!! iteration matrix is kept across iterations and steps while the contraction
!! rate is good and refreshed when it is not, with the same stopping tolerance.
!! Everything a call needs lives in its own variables: no module state.
module generalized_alpha
    use iso_c_binding, only: c_int, c_ptr, c_null_ptr, c_associated, c_f_pointer
    use flexmbs_kinds, only: wp
    use constraints, only: MAX_CDOF
    use model_data, only: mbs_model, law_rate, law_accel0
    use assembly, only: residual, iteration_matrix, mass_times, internal_forces, &
                        external_forces, constraint_values, spring_forces, spring_times, &
                        damping_times
    use sensitivity, only: mass_design_derivative_times, stiffness_times, &
                           constraint_curvature, step_design_rhs
    use linear_solver, only: linear_system, ls_init_dense, ls_init_sparse, ls_factor, &
                             ls_solve, ls_free, dense_bytes, SOLVER_DENSE, SOLVER_KLU, LS_OK, &
                             LS_NO_MEMORY
    implicit none
    private
    public :: ga_settings, ga_stats, ga_simulate, ga_coefficients, ga_set_grid
    ! for the adjoint (adjoint.f90): the static start and the scalings, recomputed exactly
    public :: ga_state, static_equilibrium, mass_scale, diagonal_scale, grid_time, ga_cancelled
    ! checkpoints of a run (the adjoint's segments, flexmbs/adjoint.py)
    public :: ckpt_rows
    public :: NEWTON_FULL, NEWTON_REUSE, NEWTON_AUTO
    public :: GA_OK, GA_NEWTON_FAILED, GA_SINGULAR, GA_STATIC_FAILED, GA_INITIAL_SINGULAR, &
              GA_INCONSISTENT_INITIAL, GA_NONFINITE, GA_BAD_INPUT, GA_LINEAR_SOLVER, GA_NO_MEMORY, &
              GA_TAPE_FULL, GA_INTERRUPTED
    public :: MEM_MATRIX, MEM_DENSE_LU, MEM_SPARSE_LU, MEM_STATE, MEM_SENSITIVITY, MEM_MODEL

    integer, parameter :: GA_OK = 0                   !! simulation completed
    integer, parameter :: GA_NEWTON_FAILED = 1        !! Newton failed after all step cuts
    integer, parameter :: GA_SINGULAR = 2             !! singular iteration matrix after all cuts
    integer, parameter :: GA_STATIC_FAILED = 3        !! static equilibrium not found
    integer, parameter :: GA_INITIAL_SINGULAR = 4     !! [M Phi_q^T; Phi_q 0] singular at t = 0
    integer, parameter :: GA_INCONSISTENT_INITIAL = 5 !! q0 violates a constraint (rest start)
    integer, parameter :: GA_NONFINITE = 6            !! NaN/Inf in a law, residual or solution
    integer, parameter :: GA_BAD_INPUT = 7            !! settings out of range
    integer, parameter :: GA_LINEAR_SOLVER = 8        !! linear solver set-up failed
    !> an allocation failed; info = [time, bytes asked for (-1: unknown), 0, MEM_* what]
    integer, parameter :: GA_NO_MEMORY = 9
    !> the tape of every (sub-)step (for the adjoint) has no room left: info = [time, columns, 0, 0]
    integer, parameter :: GA_TAPE_FULL = 10
    !> the caller's cancel flag (ga_settings%cancel) was set: info = [time reached, 0, 0, 0]
    integer, parameter :: GA_INTERRUPTED = 11

    ! Newton strategies (ga_settings%newton)
    integer, parameter :: NEWTON_FULL = 0   !! iteration matrix assembled and factored every iteration
    !> modified Newton: the factorization is kept while the scaled increment shrinks by
    !! at least 4x per iteration (the rule of the former reuse_jacobian=True)
    integer, parameter :: NEWTON_REUSE = 1
    !> automatic: modified Newton whose factorization is refreshed when the contraction
    !! rate exceeds auto_rate, when a step needs auto_iter iterations, when the observed rate
    !! would need more further iterations than a refresh costs (auto_refresh_cost), and at
    !! the start of the step after one that needed auto_stale or renewed its held matrix;
    !! an increment <= tol (full Newton's test)
    !! is accepted only when the contraction bounds the remaining error by what full
    !! Newton's quadratic convergence leaves (auto_floor)
    integer, parameter :: NEWTON_AUTO = 2
    real(wp), parameter :: reuse_rate = 0.25_wp   !! refresh threshold of NEWTON_REUSE
    real(wp), parameter :: auto_rate = 0.3_wp     !! refresh threshold of NEWTON_AUTO
    integer, parameter :: auto_iter = 4           !! iterations to tol after which a step refreshes
    !> automatic: a step that needed this many iterations (to tol and below) makes the next
    !! step start with a fresh matrix: the contraction of an aged matrix had become slow
    integer, parameter :: auto_stale = 3
    !> automatic: the cost of a refresh (assembling and factoring the matrix) in Newton
    !! iterations (a residual and a solve): a held matrix is refreshed within a step when its
    !! observed contraction would need more than 2 + auto_refresh_cost further iterations to
    !! reach acceptance (a fresh matrix converges in about 2). Measured on the robot: 1.8
    !! (2 elements per arm) to 3.5 (32 and 128) iterations per refresh; the lower bound is taken
    real(wp), parameter :: auto_refresh_cost = 2.0_wp
    !> automatic: an increment below tol is accepted when the estimated remaining error,
    !! rate / (1 - rate) times the increment, is below max(tol^2, auto_floor): what full
    !! Newton's quadratic convergence leaves, or the rounding level of the scaled
    !! coordinates. Modified Newton's remaining error has the same sign step after step and
    !! the velocities (gamma' e, gamma' = gamma / (beta h), 3750/s at h = 5e-4) integrate
    !! it: on the robot of the paper (1300 steps) accepting at rate * increment <= tol left
    !! 5e-8 m = 250 tol qscale between auto and full Newton, and responses not smooth in
    !! the design at the 1e-11 level (Taylor tests fail); at the rounding level the errors
    !! are random, as full Newton's, and the difference is 1e-11 m
    real(wp), parameter :: auto_floor = 1.0e-16_wp
    !> scaled increment at the rounding level of the coordinates (~45 epsilon): accepted
    !! whatever the contraction, whose estimate is noise there
    real(wp), parameter :: round_floor = 1.0e-14_wp

    ! what was being allocated when GA_NO_MEMORY is returned (info(4))
    integer, parameter :: MEM_MATRIX = 1       !! iteration matrix values (nnz) and load vector
    integer, parameter :: MEM_DENSE_LU = 2     !! dense LU factors (n x n)
    integer, parameter :: MEM_SPARSE_LU = 3    !! KLU analysis or factorization
    integer, parameter :: MEM_STATE = 4        !! integration state vectors
    integer, parameter :: MEM_SENSITIVITY = 5  !! design-derivative work arrays (n x nv)
    integer, parameter :: MEM_MODEL = 6        !! the model's arrays

    !> Settings of one simulation (documented defaults are set in Python).
    type :: ga_settings
        real(wp) :: h = 5.0e-4_wp        !! time step
        real(wp) :: rho_inf = 0.5_wp     !! spectral radius at infinite frequency
        real(wp) :: tol = 1.0e-10_wp     !! Newton tolerance on the scaled increment
        integer :: nsteps = 0            !! steps (output grid has nsteps + 1 points)
        integer :: max_iter = 20         !! Newton iterations per step
        integer :: max_cuts = 6          !! step halvings before giving up
        integer :: solver = SOLVER_DENSE !! SOLVER_DENSE or SOLVER_KLU
        integer :: newton = NEWTON_FULL  !! NEWTON_FULL, NEWTON_REUSE or NEWTON_AUTO
        logical :: static_start = .false.!! start from static equilibrium at t = 0
        real(wp) :: kscale = 0           !! scaling k of eq. (1); <= 0: automatic
        real(wp) :: penalty = 0          !! penalty p of eq. (1); <= 0: automatic (= k)
        !> modified Newton's states converged as full Newton's are (the discrete adjoint
        !! linearizes about them: adjoint.f90). 'auto': a step is accepted when its increment
        !! is at the rounding level (round_floor) *and* the contraction bounds the remaining
        !! error by auto_floor, where unpolished 'auto' accepts on either; the held matrices
        !! are kept. Modified Newton's remaining error keeps its sign from step to step: at
        !! auto's acceptance it left the robot's KS gradient 2e-6 off (states 8e-12 m, the
        !! accelerations 3e-8 relative), polished 8e-10 (against full Newton at tol 1e-12),
        !! with 0.47 factorizations per step (610 on the robot's 1300 steps) and 2.66 solves
        !! (unpolished: 0.35 and 2.51). With 'reuse' the run takes 'auto''s refresh rules
        !! (its held matrices, at contraction rates up to reuse_rate, left the gradient 2e-8
        !! off; full Newton steps from each step's second iteration instead, with a first held
        !! increment below tol accepted, left it 5e-6 off)
        logical :: polish = .false.
        !> KLU's symbolic analysis of the pattern, made once per model (klu_shim.c
        !! fx_klu_analyze, owned by Python: flexmbs.core.KluAnalysis); null: each run
        !! analyses the pattern itself
        type(c_ptr) :: klu_analysis = c_null_ptr
        !> a non-uniform grid: the times t_0 = 0 < t_1 < ... of the grid points (tgrid(j + 1)
        !! = t_j, j counted from the whole run's start, at least j_start + nsteps + 1 of
        !! them); unallocated: the uniform grid t_j = j h (h then only sets the scaling k of
        !! eq. (1) through the automatic kscale)
        real(wp), allocatable :: tgrid(:)
        !> the address of the caller's cancel flag, an integer(c_int) it owns and may set
        !! from another thread during the run (flexmbs.core: one flag per run): read once per
        !! step and per static iteration (ga_cancelled), the run returns GA_INTERRUPTED when
        !! it is non-zero; null: no flag
        type(c_ptr) :: cancel = c_null_ptr
    end type ga_settings

    !> Work counters returned with the result.
    type :: ga_stats
        integer :: newton_iterations = 0     !! linear solves in the time loop
        integer :: factorizations = 0        !! numeric factorizations (all phases)
        integer :: residual_evaluations = 0  !! residual evaluations (all phases)
        integer :: step_cuts = 0             !! steps that needed cutting
        integer :: static_iterations = 0     !! Newton iterations of the static start
        integer :: steps = 0                 !! grid steps completed
        !> of the factorizations, those made for the sensitivities (modified Newton: the
        !! tangent of a step's last iteration, then kept for the next step's iterations)
        integer :: sensitivity_factorizations = 0
        integer :: symbolic_analyses = 0     !! KLU symbolic analyses run (0: borrowed)
    end type ga_stats

    !> Integration state at one instant, with its design derivatives when asked:
    !! dq(:, v) = dq/dp_v etc. (direct differentiation, nv design variables).
    type :: ga_state
        real(wp), allocatable :: q(:), qd(:), qdd(:), a(:), mu(:)
        real(wp), allocatable :: qdd_prev(:)     !! qdd of the previous step (predictor)
        real(wp) :: h_prev = 0                   !! its step (0: none yet)
        real(wp), allocatable :: dq(:, :), dqd(:, :), dqdd(:, :), da(:, :), dmu(:, :)
    end type ga_state

contains

    !> Time of grid point j (counted from the run's start): s%tgrid(j + 1) on a non-uniform
    !! grid, else j h.
    pure function grid_time(s, j) result(t)
        type(ga_settings), intent(in) :: s
        integer, intent(in) :: j
        real(wp) :: t
        if (allocated(s%tgrid)) then
            t = s%tgrid(j + 1)
        else
            t = j * s%h
        end if
    end function grid_time

    !> The non-uniform grid of a run, ga_settings%tgrid: the times tg of its grid points (one
    !! time: the uniform grid j h, nothing to set). status GA_OK, or GA_NO_MEMORY with info as
    !! ga_simulate's (the bytes asked for, MEM_MODEL) when the allocation fails.
    pure subroutine ga_set_grid(s, tg, status, info)
        type(ga_settings), intent(inout) :: s
        real(wp), intent(in) :: tg(:)
        integer, intent(out) :: status
        real(wp), intent(inout) :: info(4)
        integer :: ierr
        status = GA_OK
        if (size(tg) <= 1) return
        allocate (s%tgrid(size(tg)), stat=ierr)
        if (ierr /= 0) then
            status = GA_NO_MEMORY
            info = [0.0_wp, 8.0_wp * size(tg), 0.0_wp, real(MEM_MODEL, wp)]
            return
        end if
        s%tgrid(:) = tg
    end subroutine ga_set_grid

    !> Whether the caller's cancel flag (s%cancel) is set. The flag is volatile: another
    !! thread sets it while the run reads it, so it is read from memory at every call.
    function ga_cancelled(s) result(cancelled)
        type(ga_settings), intent(in) :: s
        logical :: cancelled
        integer(c_int), pointer, volatile :: flag
        cancelled = .false.
        if (.not. c_associated(s%cancel)) return
        call c_f_pointer(s%cancel, flag)
        cancelled = flag /= 0
    end function ga_cancelled

    !> Numbers of one checkpoint of ga_simulate (ckpt, x_start): q, qd, qdd, a, qdd_prev
    !! (ndof each), mu (nc), then h_prev and the run's scalings k and p of eq. (1).
    pure function ckpt_rows(ndof, nc) result(nr)
        integer, intent(in) :: ndof, nc
        integer :: nr
        nr = 5 * ndof + nc + 3
    end function ckpt_rows

    !> Coefficients of eq. (6) from the spectral radius rho_inf.
    pure subroutine ga_coefficients(rho_inf, alpha_m, alpha_f, gamma, beta)
        real(wp), intent(in) :: rho_inf
        real(wp), intent(out) :: alpha_m, alpha_f, gamma, beta
        alpha_m = (2 * rho_inf - 1) / (rho_inf + 1)
        alpha_f = rho_inf / (rho_inf + 1)
        gamma = 0.5_wp - alpha_m + alpha_f
        beta = 0.25_wp * (gamma + 0.5_wp)**2
    end subroutine ga_coefficients

    !> Mean diagonal of the mass matrix: the scaling k of the initial systems.
    pure function mass_scale(m) result(sc)
        type(mbs_model), intent(in) :: m
        real(wp) :: sc
        integer :: e, a, cnt
        sc = 0
        cnt = 0
        do e = 1, m%nel
            do a = 1, 3 * m%el_nen(e)
                sc = sc + m%el_mass(a, a, e)
                cnt = cnt + 1
            end do
        end do
        do a = 1, m%ndof
            if (m%lumped(a) > 0) then
                sc = sc + m%lumped(a)
                cnt = cnt + 1
            end if
        end do
        if (cnt > 0) sc = sc / cnt
        if (.not. (sc > 0)) sc = 1.0_wp
    end function mass_scale

    !> Mean diagonal of cm M + K_t at q: the automatic k and p of eq. (1).
    !! vals: work array of the matrix values (overwritten).
    function diagonal_scale(m, q, cm, vals) result(sc)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), cm
        real(wp), intent(inout) :: vals(:)
        real(wp) :: sc, fint(m%ndof), qzero(m%ndof)
        integer :: e, ne, a, cnt
        vals = 0
        qzero = 0
        call internal_forces(m, q, qzero, fint, vals, 1.0_wp)
        sc = 0
        cnt = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            do a = 1, ne
                sc = sc + abs(vals(m%map_el(a, a, e))) + cm * m%el_mass(a, a, e)
                cnt = cnt + 1
            end do
        end do
        do a = 1, m%ndof
            if (m%lumped(a) > 0) then
                sc = sc + cm * m%lumped(a)
                cnt = cnt + 1
            end if
        end do
        if (cnt > 0) sc = sc / cnt
        if (.not. (sc > 0)) sc = 1.0_wp
    end function diagonal_scale

    !> Run a whole simulation: initial state, then nsteps generalized-alpha steps.
    !!
    !! Outputs on the grid t_j = j h, j = 0..nsteps (column j+1): the coordinates
    !! `out_dofs` of q, qd, qdd, and all physical multipliers mu = k lambda.
    !! info(1:4) on failure: time, scaled residual or increment, iterations, row/extra.
    !!
    !! With `dprop` (5, nel, nv) = d[EA, kGA, EI, rhoA, rhoI]/dp, the design
    !! derivatives of the discrete equations are carried forward (direct
    !! differentiation, see sens_step) and dq/dp of the coordinates `sens_dofs` is
    !! returned in dq_out(:, v, j+1); with `dmu_out`, d(mu)/dp of every constraint row
    !! (the multipliers' part of the same solve) in dmu_out(:, v, j+1).
    !!
    !! Tape (for the discrete adjoint, adjoint.f90): when tape_h holds at least nsteps + 1
    !! columns, every converged state, of every sub-step of a cut step too, in order:
    !! tape_q, tape_qd, tape_qdd (ndof, :), tape_mu (>= nc, :), tape_h (the step that led
    !! to the column; for the first state the step before it: 0 at the run's start, h_prev
    !! of x_start on a restart), tape_grid(j+1) = column of grid point j,
    !! ntape = columns used. GA_TAPE_FULL when the sub-steps need more columns.
    !!
    !! Checkpoints (the adjoint's segments, flexmbs/adjoint.py): with ckpt_every = K > 0,
    !! the full integration state at the grid points j = 0, K, 2K, ... (counted from the
    !! run's start, j_start included) in ckpt(:, j / K + 1) (layout: ckpt_rows); with
    !! x_start (such a column) and j_start, the run starts from that state at t = j_start h
    !! instead of its initial state (no static start, no initial rates; the grid and the
    !! outputs are the segment's, nsteps steps), with the scalings k, p of the column:
    !! the step after a checkpoint starts with a fresh iteration matrix in both runs, so
    !! the re-run repeats the first run's iterations (its states agree to rounding; the
    !! sparse LU's pivots may be chosen afresh). Not with design derivatives (GA_BAD_INPUT).
    subroutine ga_simulate(m, s, ap, ai, q0, qd0, out_dofs, q_out, qd_out, qdd_out, mu_out, &
                           stats, status, info, dprop, sens_dofs, dq_out, dmu_out, &
                           tape_q, tape_qd, tape_qdd, tape_mu, tape_h, tape_grid, ntape, &
                           ckpt_every, ckpt, x_start, j_start)
        type(mbs_model), intent(in) :: m
        type(ga_settings), intent(in) :: s
        integer, intent(in) :: ap(:), ai(:)           !! CSC pattern (0-based), KLU only
        real(wp), intent(in) :: q0(m%ndof), qd0(m%ndof)
        integer, intent(in) :: out_dofs(:)
        real(wp), intent(out) :: q_out(:, :), qd_out(:, :), qdd_out(:, :), mu_out(:, :)
        type(ga_stats), intent(out) :: stats
        integer, intent(out) :: status
        real(wp), intent(out) :: info(4)
        real(wp), intent(in), optional :: dprop(:, :, :)     !! (5, nel, nv) section derivatives
        integer, intent(in), optional :: sens_dofs(:)        !! coordinates whose derivatives are returned
        real(wp), intent(out), optional :: dq_out(:, :, :)   !! (nsens, nv, nsteps + 1)
        !> (nc, nv, nsteps + 1): d(mu)/dp of every constraint row, mu = k lambda (only when present)
        real(wp), intent(out), optional :: dmu_out(:, :, :)
        real(wp), intent(inout), optional :: tape_q(:, :), tape_qd(:, :), tape_qdd(:, :)
        real(wp), intent(inout), optional :: tape_mu(:, :), tape_h(:)
        integer, intent(inout), optional :: tape_grid(:)
        integer, intent(out), optional :: ntape
        integer, intent(in), optional :: ckpt_every          !! checkpoint every this many grid points
        real(wp), intent(inout), optional :: ckpt(:, :)     !! (ckpt_rows, nsteps / ckpt_every + 1)
        real(wp), intent(in), optional :: x_start(:)        !! (ckpt_rows): start from this state
        integer, intent(in), optional :: j_start            !! ... at grid point j_start
        logical :: taping, restart
        integer :: ptr, ptr0, kck, j0
        type(linear_system) :: ls
        type(ga_state) :: x, xsave
        real(wp), allocatable :: fgrav(:), vals(:)
        ! work arrays of the direct differentiation, (ndof or n, nv), allocated once
        real(wp), allocatable :: ap_(:, :), qhat(:, :), vhat(:, :), rhs(:, :)
        real(wp) :: alpha_m, alpha_f, gamma, beta, kdyn, pdyn, t, hs, fact_h, ks, ps, hgrid
        integer :: j, nsub, icut, isub, st, nv, ierr
        !> fact_valid: a factorization of the step's iteration matrix is held (for step fact_h);
        !! fact_exact: it was taken in the last Newton iteration of the step just converged,
        !! i.e. within the Newton tolerance of the converged state, as full Newton's is;
        !! vals_exact: `vals` holds the iteration matrix of that last iteration
        logical :: fact_valid, fact_exact, vals_exact, modified, stale
        !> full_step: the step is done with full Newton (always in NEWTON_FULL; in
        !! NEWTON_AUTO, the retry of a step that modified Newton did not converge)
        logical :: full_step


        status = GA_OK
        info = 0
        q_out = 0; qd_out = 0; qdd_out = 0; mu_out = 0
        taping = present(tape_h)
        if (taping) taping = size(tape_h) >= s%nsteps + 1
        ptr = 0
        if (present(ntape)) ntape = 0
        if (.not. (s%h > 0) .or. s%rho_inf < 0 .or. s%rho_inf > 1 .or. s%nsteps < 0 .or. &
            s%newton < NEWTON_FULL .or. s%newton > NEWTON_AUTO) then
            status = GA_BAD_INPUT
            return
        end if
        restart = present(x_start) .and. present(j_start)
        j0 = 0
        if (restart) j0 = j_start
        kck = 0
        if (present(ckpt_every) .and. present(ckpt)) kck = max(ckpt_every, 0)
        if (restart) then
            if (size(x_start) < ckpt_rows(m%ndof, m%nc) .or. j0 < 0 .or. present(dprop)) then
                status = GA_BAD_INPUT
                return
            end if
        end if
        if (allocated(s%tgrid)) then
            ! a non-uniform grid: every grid point of the run, strictly increasing
            if (size(s%tgrid) < j0 + s%nsteps + 1) then
                status = GA_BAD_INPUT
                return
            end if
            if (s%nsteps > 0) then
                if (.not. all(s%tgrid(j0 + 2:j0 + s%nsteps + 1) > s%tgrid(j0 + 1:j0 + s%nsteps))) then
                    status = GA_BAD_INPUT
                    return
                end if
            end if
        end if
        if (kck > 0) then
            if (size(ckpt, 1) < ckpt_rows(m%ndof, m%nc) .or. &
                size(ckpt, 2) < (j0 + s%nsteps) / kck + 1) then
                status = GA_BAD_INPUT
                return
            end if
        end if
        call ga_coefficients(s%rho_inf, alpha_m, alpha_f, gamma, beta)

        ! every allocation is checked: on failure GA_NO_MEMORY with the bytes asked
        ! for and what they were for; the local arrays are released on return
        nv = 0
        if (present(dprop)) nv = size(dprop, 3)
        if (s%solver == SOLVER_KLU) then
            call ls_init_sparse(ls, m%n, ap, ai, st, s%klu_analysis)
            if (st == LS_NO_MEMORY) then
                call no_memory(-1.0_wp, MEM_SPARSE_LU)
                return
            else if (st /= LS_OK) then
                status = GA_LINEAR_SOLVER
                info(4) = st
                return
            end if
        else
            call ls_init_dense(ls, m%n, st)
            if (st /= LS_OK) then
                call no_memory(dense_bytes(m%n), MEM_DENSE_LU)
                return
            end if
        end if
        allocate (vals(m%nnz), fgrav(m%ndof), stat=ierr)
        if (ierr /= 0) then
            call no_memory(8.0_wp * (real(m%nnz, wp) + m%ndof), MEM_MATRIX)
            goto 900
        end if
        call allocate_state(x, ierr)
        if (ierr == 0) call allocate_state(xsave, ierr)
        if (ierr /= 0) then
            call no_memory(2 * 8.0_wp * ((5.0_wp + 5 * nv) * m%ndof + (1.0_wp + nv) * m%nc), MEM_STATE)
            goto 900
        end if
        x%qdd_prev = 0
        x%h_prev = 0
        if (nv > 0) then
            x%dq = 0; x%dqd = 0; x%dqdd = 0; x%da = 0; x%dmu = 0
            allocate (ap_(m%ndof, nv), qhat(m%ndof, nv), vhat(m%ndof, nv), rhs(m%n, nv), stat=ierr)
            if (ierr /= 0) then
                call no_memory(8.0_wp * nv * (3.0_wp * m%ndof + m%n), MEM_SENSITIVITY)
                goto 900
            end if
            dq_out = 0
            if (present(dmu_out)) dmu_out = 0
        end if
        x%q = q0
        x%qd = qd0
        x%qdd = 0
        x%mu = 0
        call mass_times(m, m%gacc, fgrav)

        ! --- initial state -----------------------------------------------------
        if (restart) then     ! a segment of a checkpointed run: its checkpoint's state
            call unpack_start()
            goto 100
        end if
        if (s%static_start) then
            call static_equilibrium(m, s, ls, vals, fgrav, x, stats, status, info, ks, ps)
            if (status /= GA_OK) goto 900
            if (nv > 0) then
                call sens_static(m, dprop, ls, vals, ks, ps, x, status)
                if (status == GA_NO_MEMORY) call no_memory(8.0_wp * nv * (m%n + m%ndof), MEM_SENSITIVITY)
                if (status /= GA_OK) goto 900
            end if
        else
            call check_initial(m, x%q, status, info)
            if (status /= GA_OK) goto 900
        end if
        call initial_rates(m, ls, vals, fgrav, x, stats, status, info)
        if (status /= GA_OK) goto 900
        if (nv > 0) then
            call sens_initial(m, dprop, ls, qd0, x, status)
            if (status == GA_NO_MEMORY) call no_memory(8.0_wp * nv * (m%n + 2.0_wp * m%ndof), MEM_SENSITIVITY)
            if (status /= GA_OK) goto 900
            x%da = x%dqdd
        end if
        x%a = x%qdd
100     continue
        call store(0)
        if (taping) then
            ! the step before the first state (0 at the run's start): the adjoint's
            ! transpose of the step-change rescaling of a (ga_step) needs it
            call tape_store(x%h_prev, st)
            tape_grid(1) = ptr
        end if

        ! --- time loop ---------------------------------------------------------
        if (restart) then
            kdyn = x_start(ckpt_rows(m%ndof, m%nc) - 1)
            pdyn = x_start(ckpt_rows(m%ndof, m%nc))
        else
            kdyn = s%kscale
            if (.not. (kdyn > 0)) kdyn = diagonal_scale(m, x%q, (1 - alpha_m) / (beta * s%h**2 * (1 - alpha_f)), vals)
            pdyn = s%penalty
            if (.not. (pdyn > 0)) pdyn = kdyn
        end if
        if (.not. (kdyn > 0 .and. pdyn > 0)) then
            status = GA_BAD_INPUT
            goto 900
        end if
        if (kck > 0 .and. mod(j0, kck) == 0) call ckpt_store(j0)
        modified = s%newton /= NEWTON_FULL
        full_step = .not. modified
        stale = .false.
        fact_valid = .false.
        fact_exact = .false.
        vals_exact = .false.
        fact_h = 0
        call copy_state(x, xsave)
        do j = 1, s%nsteps
            ! the step of grid interval j: s%h, or t_j - t_{j-1} on a non-uniform grid
            if (allocated(s%tgrid)) then
                t = s%tgrid(j0 + j)
                hgrid = s%tgrid(j0 + j + 1) - t
            else
                t = (j0 + j - 1) * s%h
                hgrid = s%h
            end if
            if (ga_cancelled(s)) then
                status = GA_INTERRUPTED
                info = [t, 0.0_wp, 0.0_wp, 0.0_wp]
                goto 900
            end if
            nsub = 1
            icut = 0
            full_step = .not. modified
            ptr0 = ptr
            do
                hs = hgrid / nsub
                do isub = 1, nsub
                    call ga_step(t + (isub - 1) * hs, hs, st)
                    if (st /= GA_OK) exit
                    if (taping) call tape_store(hs, st)
                    if (st /= GA_OK) exit
                end do
                if (st == GA_OK .or. st == GA_NO_MEMORY .or. st == GA_TAPE_FULL) exit
                ! failure: restore the state at t_j; automatic: retry the step with full
                ! Newton (its predictor and path) before cutting it; then cut the step
                call copy_state(xsave, x)
                ptr = ptr0
                fact_valid = .false.
                if (.not. full_step .and. s%newton == NEWTON_AUTO) then
                    full_step = .true.
                    cycle
                end if
                if (icut >= s%max_cuts) exit
                icut = icut + 1
                stats%step_cuts = stats%step_cuts + 1
                nsub = 2 * nsub
            end do
            full_step = .not. modified
            if (st /= GA_OK) then
                status = st
                goto 900
            end if
            stats%steps = j
            call store(j)
            if (taping) tape_grid(j + 1) = ptr
            if (kck > 0 .and. mod(j0 + j, kck) == 0) call ckpt_store(j0 + j)
            call copy_state(x, xsave)
        end do

900     continue
        stats%factorizations = stats%factorizations + ls%factorizations
        stats%symbolic_analyses = ls%analyses
        call ls_free(ls)
        if (present(ntape)) ntape = ptr

    contains

        !> The full state at grid point jj (and the scalings) into checkpoint jj / kck + 1.
        subroutine ckpt_store(jj)
            integer, intent(in) :: jj
            integer :: c, nd
            nd = m%ndof
            c = jj / kck + 1
            ckpt(1:nd, c) = x%q
            ckpt(nd + 1:2 * nd, c) = x%qd
            ckpt(2 * nd + 1:3 * nd, c) = x%qdd
            ckpt(3 * nd + 1:4 * nd, c) = x%a
            ckpt(4 * nd + 1:5 * nd, c) = x%qdd_prev
            if (m%nc > 0) ckpt(5 * nd + 1:5 * nd + m%nc, c) = x%mu
            ckpt(5 * nd + m%nc + 1, c) = x%h_prev
            ckpt(5 * nd + m%nc + 2, c) = kdyn
            ckpt(5 * nd + m%nc + 3, c) = pdyn
            ! the next step starts with a fresh iteration matrix, as a segment re-run from
            ! this checkpoint does: the re-run then repeats this run's iterations exactly
            fact_valid = .false.
            stale = .false.
        end subroutine ckpt_store

        !> The state of x_start (a checkpoint column) into x.
        subroutine unpack_start()
            integer :: nd
            nd = m%ndof
            x%q = x_start(1:nd)
            x%qd = x_start(nd + 1:2 * nd)
            x%qdd = x_start(2 * nd + 1:3 * nd)
            x%a = x_start(3 * nd + 1:4 * nd)
            x%qdd_prev = x_start(4 * nd + 1:5 * nd)
            if (m%nc > 0) x%mu = x_start(5 * nd + 1:5 * nd + m%nc)
            x%h_prev = x_start(5 * nd + m%nc + 1)
        end subroutine unpack_start

        !> Append the converged state (reached with step hh) to the tape.
        subroutine tape_store(hh, stat)
            real(wp), intent(in) :: hh
            integer, intent(out) :: stat
            stat = GA_OK
            if (ptr >= size(tape_h) .or. ptr >= size(tape_q, 2)) then
                stat = GA_TAPE_FULL
                info = [t, real(size(tape_h), wp), 0.0_wp, 0.0_wp]
                return
            end if
            ptr = ptr + 1
            tape_q(:, ptr) = x%q
            tape_qd(:, ptr) = x%qd
            tape_qdd(:, ptr) = x%qdd
            if (m%nc > 0) tape_mu(1:m%nc, ptr) = x%mu
            tape_h(ptr) = hh
        end subroutine tape_store

        !> Report a failed allocation: info = [0, bytes (-1: unknown), 0, what].
        subroutine no_memory(nbytes, what)
            real(wp), intent(in) :: nbytes
            integer, intent(in) :: what
            status = GA_NO_MEMORY
            info = [0.0_wp, nbytes, 0.0_wp, real(what, wp)]
            call ls_free(ls)
        end subroutine no_memory

        !> Allocate the vectors of a state (and its derivatives when nv > 0).
        subroutine allocate_state(y, ierr)
            type(ga_state), intent(inout) :: y
            integer, intent(out) :: ierr
            allocate (y%q(m%ndof), y%qd(m%ndof), y%qdd(m%ndof), y%a(m%ndof), y%mu(m%nc), &
                      y%qdd_prev(m%ndof), stat=ierr)
            if (ierr /= 0 .or. nv == 0) return
            allocate (y%dq(m%ndof, nv), y%dqd(m%ndof, nv), y%dqdd(m%ndof, nv), &
                      y%da(m%ndof, nv), y%dmu(m%nc, nv), stat=ierr)
        end subroutine allocate_state

        subroutine store(jj)
            integer, intent(in) :: jj
            q_out(:, jj + 1) = x%q(out_dofs)
            qd_out(:, jj + 1) = x%qd(out_dofs)
            qdd_out(:, jj + 1) = x%qdd(out_dofs)
            if (m%nc > 0) mu_out(:, jj + 1) = x%mu
            if (nv > 0) dq_out(:, :, jj + 1) = x%dq(sens_dofs, :)
            if (nv > 0 .and. m%nc > 0 .and. present(dmu_out)) dmu_out(1:m%nc, :, jj + 1) = x%dmu
        end subroutine store

        !> One generalized-alpha step from tn to tn + hh (eqs. 3–5), Newton on eq. (7).
        subroutine ga_step(tn, hh, stat)
            real(wp), intent(in) :: tn, hh
            integer, intent(out) :: stat
            real(wp) :: betap, gammap, r(m%n), z(m%n, 1), err, err_prev, rate, phimax, tnew
            real(wp) :: a_new, a_part, qdd_pred, hratio
            integer :: it, lst, i
            logical :: extrapolate, finite
            logical :: refresh, fresh, assemble, mod_step, auto_step, reuse_step
            !> held_start: the step began with a held matrix; renewed: and refreshed it later
            logical :: held_start, renewed, polished, est_ok
            real(wp) :: k_held, est_floor
            ! this step's strategy: modified Newton (reuse or automatic) unless full_step
            mod_step = .not. full_step
            ! polish: the automatic strategy's refresh rules whatever s%newton ('reuse''s held
            ! matrices, contracting at up to reuse_rate, left the robot's KS gradient 2e-8
            ! off, against 8e-10 with 'auto''s), and its acceptance tightened (polished)
            auto_step = mod_step .and. (s%newton == NEWTON_AUTO .or. s%polish)
            reuse_step = mod_step .and. s%newton == NEWTON_REUSE .and. .not. s%polish
            polished = s%polish .and. auto_step .and. nv == 0
            betap = (1 - alpha_m) / (beta * hh**2 * (1 - alpha_f))
            gammap = gamma / (beta * hh)
            tnew = tn + hh
            ! variable steps: a_n approximates qdd(t_n + (alpha_m - alpha_f) h) to second order
            ! (Arnold & Bruls 2007, Multibody Syst Dyn 18:185-202; from eq. (3) with qdd smooth:
            ! a_n - qdd_n = (alpha_m - alpha_f) h qddd + O(h^2)), h the step that ended at t_n.
            ! When this step's length hh differs from that one's (h_prev), a_n is moved to the
            ! point the step of length hh needs: a_n <- qdd_n + (hh / h_prev) (a_n - qdd_n),
            ! the same linear map on the design derivatives (da, dqdd). Nothing at the run's
            ! first step (h_prev = 0) or on an unchanged step; a cut step's sub-steps are
            ! steps of their own (the first one rescales by 1/2^k, the next grid step back).
            if (x%h_prev > 0 .and. hh /= x%h_prev) then
                hratio = hh / x%h_prev
                x%a = x%qdd + hratio * (x%a - x%qdd)
                if (nv > 0) x%da = x%dqdd + hratio * (x%da - x%dqdd)
            end if
            ! predictor, eqs. (3)-(5), with qdd_{n+1} = qdd_n; in modified Newton,
            ! qdd_{n+1} extrapolated linearly from the last two steps instead: a
            ! closer start for the slower (linear) convergence of a reused Jacobian
            ! (-25 % iterations on the robot; full Newton gains nothing from it)
            ! (one pass over the coordinates; per coordinate the operations of the
            ! array expressions: a_part, qdd_pred, a_new = a_part + (1 - alpha_f) /
            ! (1 - alpha_m) qdd_pred, then q, qd and, kept for eq. (3), a = a_part)
            extrapolate = mod_step .and. x%h_prev > 0
            hratio = 0
            if (extrapolate) hratio = hh / x%h_prev
            do i = 1, m%ndof
                a_part = (alpha_f * x%qdd(i) - alpha_m * x%a(i)) / (1 - alpha_m)
                qdd_pred = x%qdd(i)
                if (extrapolate) qdd_pred = x%qdd(i) + hratio * (x%qdd(i) - x%qdd_prev(i))
                a_new = a_part + (1 - alpha_f) / (1 - alpha_m) * qdd_pred
                x%qdd_prev(i) = x%qdd(i)
                x%q(i) = x%q(i) + hh * x%qd(i) + hh**2 * ((0.5_wp - beta) * x%a(i) + beta * a_new)
                x%qd(i) = x%qd(i) + hh * ((1 - gamma) * x%a(i) + gamma * a_new)
                x%qdd(i) = qdd_pred
                x%a(i) = a_part
            end do
            x%h_prev = hh
            refresh = .not. mod_step .or. stale
            stale = .false.
            fact_exact = .false.
            vals_exact = .false.
            err_prev = huge(1.0_wp)
            stat = GA_NEWTON_FAILED
            do it = 1, s%max_iter
                ! modified Newton with sensitivities: from the second iteration on, a fresh
                ! matrix (full Newton steps): the derivative solve needs the factored
                ! tangent within the tolerance of the converged state anyway (sens_step),
                ! and the step then converges like full Newton, in one factorization
                if (nv > 0 .and. mod_step .and. it >= 2) refresh = .true.
                fresh = refresh .or. .not. fact_valid .or. fact_h /= hh
                if (it == 1) then
                    held_start = .not. fresh
                    renewed = .false.
                else if (fresh .and. held_start .and. nv == 0) then
                    ! (with design derivatives, a step's iterations from the second
                    ! on are fresh anyway, and its last factorization serves the next step)
                    renewed = .true.
                end if
                ! the iteration matrix is assembled with the residual, in one pass over the
                ! elements, whenever it is factored
                assemble = fresh
                if (assemble) then
                    call residual(m, x%q, x%qd, x%qdd, x%mu, tnew, fgrav, 1.0_wp, kdyn, pdyn, r, &
                                  phimax, vals=vals, cmat=betap, cc=gammap)
                else
                    call residual(m, x%q, x%qd, x%qdd, x%mu, tnew, fgrav, 1.0_wp, kdyn, pdyn, r, phimax)
                end if
                stats%residual_evaluations = stats%residual_evaluations + 1
                ! the right-hand side -r and the finiteness of r in one pass
                finite = .true.
                do i = 1, m%n
                    z(i, 1) = -r(i)
                    finite = finite .and. abs(r(i)) <= huge(1.0_wp)
                end do
                if (.not. finite) then
                    stat = GA_NONFINITE
                    info = [tnew, huge(1.0_wp), real(it, wp), 0.0_wp]
                    return
                end if
                if (fresh) then
                    call ls_factor(ls, vals, lst)
                    if (lst == LS_NO_MEMORY) then
                        fact_valid = .false.
                        stat = GA_NO_MEMORY
                        info = [tnew, -1.0_wp, real(it, wp), real(MEM_SPARSE_LU, wp)]
                        return
                    else if (lst /= LS_OK) then
                        fact_valid = .false.
                        stat = GA_SINGULAR
                        info = [tnew, maxval(abs(r)), real(it, wp), real(lst, wp)]
                        return
                    end if
                    fact_valid = .true.
                    fact_h = hh
                end if
                refresh = .not. mod_step
                call ls_solve(ls, z, lst)
                stats%newton_iterations = stats%newton_iterations + 1
                if (lst /= LS_OK) then
                    stat = GA_NONFINITE
                    info = [tnew, maxval(abs(r)), real(it, wp), real(lst, wp)]
                    return
                end if
                ! the update and its size in one pass (z is finite: ls_solve checked it)
                err = 0
                do i = 1, m%ndof
                    x%q(i) = x%q(i) + z(i, 1)
                    x%qd(i) = x%qd(i) + gammap * z(i, 1)
                    x%qdd(i) = x%qdd(i) + betap * z(i, 1)
                    err = max(err, abs(z(i, 1)))
                end do
                if (m%nc > 0) x%mu = x%mu + kdyn * z(m%ndof + 1:, 1)
                err = err / m%qscale
                info = [tnew, err, real(it, wp), phimax]
                ! observed contraction rate of the iteration (0 on the first one)
                rate = err / err_prev
                if (auto_step .and. .not. fresh .and. rate > 1) then
                    ! automatic: a held matrix that makes the increment grow is not kept,
                    ! nor its increment: back to the previous iterate, with a fresh matrix
                    ! (the path of full Newton from there)
                    x%q = x%q - z(1:m%ndof, 1)
                    x%qd = x%qd - gammap * z(1:m%ndof, 1)
                    x%qdd = x%qdd - betap * z(1:m%ndof, 1)
                    if (m%nc > 0) x%mu = x%mu - kdyn * z(m%ndof + 1:, 1)
                    refresh = .true.
                    cycle
                end if
                if (err <= s%tol) then
                    ! full and reuse: converged. Automatic: the remaining error of a modified
                    ! Newton iterate is about rate / (1 - rate) times the increment (rate
                    ! observed from the previous iteration; none on the first one, unless its
                    ! matrix was fresh: a full Newton step); accepted when that is at most
                    ! what full Newton's quadratic convergence leaves, tol^2, or the rounding
                    ! level; else one more iteration with the same factorization (cheap)
                    ! the estimate within the floor: tol^2 or the rounding level; polished,
                    ! the rounding level whatever tol
                    est_floor = max(s%tol**2, auto_floor)
                    if (polished) est_floor = auto_floor
                    est_ok = .false.
                    if (it == 1) then
                        est_ok = fresh
                    else if (fresh) then
                        ! a full Newton step: quadratic, remaining error ~ rate^2 increment
                        est_ok = rate**2 * err <= est_floor
                    else if (rate < 1) then
                        est_ok = rate / (1 - rate) * err <= est_floor
                    end if
                    if (polished) then
                        ! polish (the adjoint's forward run): both tests, and not either
                        if (err <= round_floor .and. est_ok) stat = GA_OK
                        ! increments that stopped shrinking below tol with a fresh matrix (full
                        ! Newton's test is met), or at the rounding level: noise
                        if (it >= 3 .and. rate >= 0.5_wp .and. (fresh .or. err <= 1.0e2_wp * round_floor)) &
                            stat = GA_OK
                    else if (.not. auto_step .or. err <= round_floor .or. est_ok) then
                        stat = GA_OK
                    end if
                    if (stat == GA_OK) then
                        fact_exact = fresh
                        vals_exact = assemble
                        ! the next step starts with a fresh matrix after one that needed
                        ! auto_stale iterations with a held one, or that had to renew it
                        stale = auto_step .and. ((it >= auto_stale .and. .not. fresh) .or. renewed)
                        exit
                    end if
                end if
                ! modified Newton: refactor when the contraction is poor; automatic: also
                ! when a step needs auto_iter iterations to reach tol, and while polishing
                ! below tol only when the increment stops shrinking (rate > 1/2)
                if (reuse_step .and. rate > reuse_rate) refresh = .true.
                if (auto_step) then
                    if (err > s%tol .and. (rate > auto_rate .or. it + 1 >= auto_iter)) refresh = .true.
                    if (err <= s%tol .and. rate > 0.5_wp .and. .not. polished) refresh = .true.
                    ! cost model: further held iterations to reach acceptance at the observed
                    ! contraction, against a refresh and the ~2 iterations of a fresh matrix
                    if (.not. fresh .and. it >= 2 .and. rate > 0 .and. rate < 1 .and. err > 0) then
                        k_held = log(max(s%tol**2, auto_floor) * (1 - rate) / (rate * err)) / log(rate)
                        if (k_held > 2 + auto_refresh_cost) refresh = .true.
                    end if
                end if
                if (err > 1.0e6_wp .or. .not. (err == err)) exit
                err_prev = err
            end do
            if (stat == GA_OK) then
                x%a = x%a + (1 - alpha_f) / (1 - alpha_m) * x%qdd
                info = 0
                if (nv > 0) call sens_step(hh, tnew, betap, gammap, stat)
            end if
        end subroutine ga_step

        !> Direct differentiation of one converged step (eqs. 1, 3-5 differentiated
        !! with respect to p). With qdd'_{n+1} = beta' (q'_{n+1} - Qhat) and
        !! qd'_{n+1} = Vhat + gamma' (q'_{n+1} - Qhat), where Qhat and Vhat collect the
        !! known derivatives of step n, the derivative of the residual gives
        !!   S [q'; lambda'] = [ -dr/dp + beta' M Qhat + C_t (gamma' Qhat - Vhat) ; 0 ],
        !! mu' = k lambda' (k: the scaling of the iteration matrix S, constant over the run),
        !! with S the iteration matrix of eq. (7) at the converged state, as exact as full
        !! Newton's: taken in the step's last Newton iteration (within the Newton tolerance
        !! of the converged state).
        !!
        !! Full Newton, and modified Newton with sensitivities, whose iterations from the
        !! second on are full Newton steps (ga_step): the factorization of the last
        !! iteration, one multi-right-hand-side solve; in modified Newton it then serves the
        !! next step's first iteration too. A step that converged in its first, modified,
        !! iteration: S assembled and factored here, and kept for the next step.
        !! Iterative refinement of the solve with an older factorization was measured
        !! slower than one factorization (robot with 2 and 32 elements per arm:
        !! each sweep costs a product with S and a solve, each about a triangular solve,
        !! and the derivatives, unlike Newton's corrections, start from O(1): 3 sweeps did
        !! not reach 1e-10 on most steps).
        subroutine sens_step(hh, tnew, betap, gammap, stat)
            real(wp), intent(in) :: hh, tnew, betap, gammap
            integer, intent(out) :: stat
            integer :: lst, v
            real(wp) :: cv(m%ndof, 2)
            stat = GA_OK
            if (modified .and. .not. fact_exact) then
                if (.not. vals_exact) call iteration_matrix(m, x%q, x%qd, x%mu, tnew, betap, 1.0_wp, &
                                                            gammap, kdyn, pdyn, vals)
                call ls_factor(ls, vals, lst)
                stats%sensitivity_factorizations = stats%sensitivity_factorizations + 1
                if (lst == LS_NO_MEMORY) then
                    fact_valid = .false.
                    stat = GA_NO_MEMORY
                    info = [tnew, -1.0_wp, 0.0_wp, real(MEM_SPARSE_LU, wp)]
                    return
                else if (lst /= LS_OK) then
                    fact_valid = .false.
                    stat = GA_SINGULAR
                    info = [tnew, 0.0_wp, 0.0_wp, real(lst, wp)]
                    return
                end if
                fact_valid = .true.
                fact_h = hh
                stale = .false.
            end if
            ap_ = (alpha_f * x%dqdd - alpha_m * x%da) / (1 - alpha_m)
            qhat = x%dq + hh * x%dqd + hh**2 * ((0.5_wp - beta) * x%da + beta * ap_)
            vhat = x%dqd + hh * ((1 - gamma) * x%da + gamma * ap_)
            call step_design_rhs(m, dprop, x%q, x%qd, x%qdd - m%gacc, betap, qhat, rhs(1:m%ndof, :))
            if (m%nsd > 0 .or. m%damped) then
                ! velocity-dependent forces: C_t qd' = gamma' C_t q' + C_t (vhat - gamma' qhat)
                do v = 1, nv
                    cv(:, 1) = gammap * qhat(:, v) - vhat(:, v)
                    call damping_times(m, x%q, x%qd, cv(:, 1:1), cv(:, 2:2))
                    rhs(1:m%ndof, v) = rhs(1:m%ndof, v) + cv(:, 2)
                end do
            end if
            rhs(m%ndof + 1:, :) = 0
            call ls_solve(ls, rhs, lst)
            if (lst /= LS_OK) then
                stat = GA_NONFINITE
                info = [tnew, 0.0_wp, 0.0_wp, real(lst, wp)]
                return
            end if
            x%dq = rhs(1:m%ndof, :)
            if (m%nc > 0) x%dmu = kdyn * rhs(m%ndof + 1:, :)
            x%dqdd = betap * (x%dq - qhat)
            x%dqd = vhat + gammap * (x%dq - qhat)
            x%da = ap_ + (1 - alpha_f) / (1 - alpha_m) * x%dqdd
        end subroutine sens_step

    end subroutine ga_simulate

    !> dst = src for two allocated states of the same shapes, in place (no allocation).
    subroutine copy_state(src, dst)
        type(ga_state), intent(in) :: src
        type(ga_state), intent(inout) :: dst
        dst%q = src%q
        dst%qd = src%qd
        dst%qdd = src%qdd
        dst%a = src%a
        dst%mu = src%mu
        dst%qdd_prev = src%qdd_prev
        dst%h_prev = src%h_prev
        if (allocated(src%dq)) then
            dst%dq = src%dq
            dst%dqd = src%dqd
            dst%dqdd = src%dqdd
            dst%da = src%da
            dst%dmu = src%dmu
        end if
    end subroutine copy_state

    !> Rest start: the initial configuration must satisfy the constraints.
    subroutine check_initial(m, q, status, info)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof)
        integer, intent(out) :: status
        real(wp), intent(out) :: info(4)
        real(wp) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF)
        integer :: i
        status = GA_OK
        do i = 1, m%nc
            call constraint_values(m, i, q, 0.0_wp, phi, grad, hess)
            if (.not. (abs(phi) <= 1.0e-8_wp * m%qscale)) then
                status = GA_INCONSISTENT_INITIAL
                info = [0.0_wp, phi, 0.0_wp, real(i, wp)]
                return
            end if
        end do
    end subroutine check_initial

    !> Static equilibrium at t = 0: f_int(q) - f_ext(0) + Phi_q^T mu = 0, Phi(q, 0) = 0.
    !! Full load first; on failure, load stepping in 4, then 16 increments.
    subroutine static_equilibrium(m, s, ls, vals, fgrav, x, stats, status, info, ks, ps)
        type(mbs_model), intent(in) :: m
        type(ga_settings), intent(in) :: s
        type(linear_system), intent(inout) :: ls
        real(wp), intent(inout) :: vals(:)
        real(wp), intent(in) :: fgrav(m%ndof)
        type(ga_state), intent(inout) :: x
        type(ga_stats), intent(inout) :: stats
        integer, intent(out) :: status
        real(wp), intent(out) :: info(4)
        real(wp), intent(out) :: ks, ps          !! k and p used (for the sensitivities)
        real(wp) :: q_start(m%ndof), r(m%n), z(m%n, 1), err, phimax, lf
        real(wp) :: qzero(m%ndof)                !! velocities of the static state
        integer :: nincr, inc, it, lst, attempt
        logical :: ok
        ks = s%kscale
        if (.not. (ks > 0)) ks = diagonal_scale(m, x%q, 0.0_wp, vals)
        ps = s%penalty
        if (.not. (ps > 0)) ps = ks
        q_start = x%q
        qzero = 0
        nincr = 1
        do attempt = 1, 3
            x%q = q_start
            x%mu = 0
            ok = .true.
            do inc = 1, nincr
                lf = real(inc, wp) / nincr
                ok = .false.
                do it = 1, 4 * s%max_iter
                    if (ga_cancelled(s)) then
                        status = GA_INTERRUPTED
                        info = 0
                        return
                    end if
                    call residual(m, x%q, qzero, x%qdd, x%mu, 0.0_wp, fgrav, 0.0_wp, ks, ps, r, &
                                  phimax, lf)
                    stats%residual_evaluations = stats%residual_evaluations + 1
                    if (.not. all(abs(r) <= huge(1.0_wp))) exit
                    call iteration_matrix(m, x%q, qzero, x%mu, 0.0_wp, 0.0_wp, 1.0_wp, 0.0_wp, ks, &
                                          ps, vals)
                    call ls_factor(ls, vals, lst)
                    if (lst == LS_NO_MEMORY) then
                        status = GA_NO_MEMORY
                        info = [0.0_wp, -1.0_wp, real(it, wp), real(MEM_SPARSE_LU, wp)]
                        return
                    else if (lst /= LS_OK) then
                        status = GA_STATIC_FAILED
                        info = [0.0_wp, maxval(abs(r)), real(it, wp), real(10 + lst, wp)]
                        return
                    end if
                    z(:, 1) = -r
                    call ls_solve(ls, z, lst)
                    stats%static_iterations = stats%static_iterations + 1
                    if (lst /= LS_OK) exit
                    x%q = x%q + z(1:m%ndof, 1)
                    if (m%nc > 0) x%mu = x%mu + ks * z(m%ndof + 1:, 1)
                    err = maxval(abs(z(1:m%ndof, 1))) / m%qscale
                    info = [0.0_wp, err, real(it, wp), phimax]
                    if (err <= s%tol) then
                        ok = .true.
                        exit
                    end if
                    if (.not. (err < 1.0e3_wp)) exit
                end do
                if (.not. ok) exit
            end do
            if (ok) exit
            nincr = 4 * nincr
        end do
        if (ok) then
            status = GA_OK
            info = 0
        else
            status = GA_STATIC_FAILED
        end if
    end subroutine static_equilibrium

    !> Consistent initial velocities and accelerations (and multipliers) at t = 0:
    !!   [M  k Phi_q^T; k Phi_q  0] [qd; .]   = [M qd0; -k Phi_t]
    !!   [M  k Phi_q^T; k Phi_q  0] [qdd; lam] = [f_ext - f_int(q, qd) - f_sd(q, qd);
    !!                                             -k (Phi_tt + qd^T Phi_qq qd)]
    !! with mu = k lam. The velocity step is a mass-weighted projection of qd0.
    subroutine initial_rates(m, ls, vals, fgrav, x, stats, status, info)
        type(mbs_model), intent(in) :: m
        type(linear_system), intent(inout) :: ls
        real(wp), intent(inout) :: vals(:)
        real(wp), intent(in) :: fgrav(m%ndof)
        type(ga_state), intent(inout) :: x
        type(ga_stats), intent(inout) :: stats
        integer, intent(out) :: status
        real(wp), intent(out) :: info(4)
        real(wp) :: z(m%n, 2), fint(m%ndof), fext(m%ndof), k0, phi, grad(MAX_CDOF)
        real(wp) :: hess(MAX_CDOF, MAX_CDOF), qv(MAX_CDOF), rate, acc
        real(wp) :: mu0(m%nc)
        integer :: i, a, b, lst
        status = GA_OK
        info = 0
        k0 = mass_scale(m)
        mu0 = 0
        call iteration_matrix(m, x%q, x%qd, mu0, 0.0_wp, 1.0_wp, 0.0_wp, 0.0_wp, k0, 0.0_wp, vals)
        call ls_factor(ls, vals, lst)
        if (lst == LS_NO_MEMORY) then
            status = GA_NO_MEMORY
            info = [0.0_wp, -1.0_wp, 0.0_wp, real(MEM_SPARSE_LU, wp)]
            return
        else if (lst /= LS_OK) then
            status = GA_INITIAL_SINGULAR
            info(4) = lst
            return
        end if
        ! velocities
        call mass_times(m, x%qd, z(1:m%ndof, 1))
        do i = 1, m%nc
            rate = 0
            if (m%c_law(i) > 0) rate = m%c_lawcoef(i) * law_rate(m, m%c_law(i))
            z(m%ndof + i, 1) = k0 * rate          ! -k Phi_t, Phi_t = -lawcoef law'
        end do
        call ls_solve(ls, z(:, 1:1), lst)
        if (lst /= LS_OK) then
            status = GA_NONFINITE
            return
        end if
        x%qd = z(1:m%ndof, 1)
        ! accelerations and multipliers
        call internal_forces(m, x%q, x%qd, fint)
        call external_forces(m, fgrav, 0.0_wp, fext)
        stats%residual_evaluations = stats%residual_evaluations + 1
        if (m%nsd > 0) call spring_forces(m, x%q, x%qd, fint)
        z(1:m%ndof, 2) = fext - fint
        do i = 1, m%nc
            call constraint_values(m, i, x%q, 0.0_wp, phi, grad, hess)
            do a = 1, MAX_CDOF
                qv(a) = 0
                if (m%c_dofs(a, i) > 0) qv(a) = x%qd(m%c_dofs(a, i))
            end do
            acc = 0
            if (m%c_law(i) > 0) acc = m%c_lawcoef(i) * law_accel0(m, m%c_law(i))
            ! Phi_tt = -acc
            z(m%ndof + i, 2) = -k0 * (-acc)
            do a = 1, MAX_CDOF
                do b = 1, MAX_CDOF
                    z(m%ndof + i, 2) = z(m%ndof + i, 2) - k0 * hess(a, b) * qv(a) * qv(b)
                end do
            end do
        end do
        call ls_solve(ls, z(:, 2:2), lst)
        if (lst /= LS_OK) then
            status = GA_NONFINITE
            return
        end if
        x%qdd = z(1:m%ndof, 2)
        if (m%nc > 0) x%mu = k0 * z(m%ndof + 1:, 2)
    end subroutine initial_rates

    !> Design derivative of the static equilibrium at t = 0:
    !!   [K_t + p Phi_q^T Phi_q + mu Phi_qq   k Phi_q^T; k Phi_q  0] [q0'; lambda0'] = [-(df_int/dp - dM/dp g); 0]
    subroutine sens_static(m, dprop, ls, vals, ks, ps, x, status)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: dprop(:, :, :)
        type(linear_system), intent(inout) :: ls
        real(wp), intent(inout) :: vals(:)
        real(wp), intent(in) :: ks, ps
        type(ga_state), intent(inout) :: x
        integer, intent(out) :: status
        real(wp), allocatable :: rhs(:, :), zero(:, :)
        real(wp) :: qzero(m%ndof)
        integer :: lst, ierr
        status = GA_OK
        qzero = 0
        allocate (rhs(m%n, size(dprop, 3)), zero(m%ndof, size(dprop, 3)), stat=ierr)
        if (ierr /= 0) then
            status = GA_NO_MEMORY
            return
        end if
        zero = 0
        call iteration_matrix(m, x%q, qzero, x%mu, 0.0_wp, 0.0_wp, 1.0_wp, 0.0_wp, ks, ps, vals)
        call ls_factor(ls, vals, lst)
        if (lst /= LS_OK) then
            status = GA_STATIC_FAILED
            return
        end if
        ! -(df_int/dp - dM/dp g): the step right-hand side with beta' = 0 and qdd = 0
        call step_design_rhs(m, dprop, x%q, qzero, -m%gacc, 0.0_wp, zero, rhs(1:m%ndof, :))
        rhs(m%ndof + 1:, :) = 0
        call ls_solve(ls, rhs, lst)
        if (lst /= LS_OK) then
            status = GA_NONFINITE
            return
        end if
        x%dq = rhs(1:m%ndof, :)
        if (m%nc > 0) x%dmu = ks * rhs(m%ndof + 1:, :)
    end subroutine sens_static

    !> Design derivatives of the consistent initial velocities and accelerations,
    !! with the factorization of [M k Phi_q^T; k Phi_q 0] left by initial_rates:
    !!   M qd'  + k Phi_q^T nu'  = dM/dp (qd0 - qd)           Phi_q qd'  = -(Phi_qq q0') qd
    !!   M qdd' + k Phi_q^T lam' = dM/dp (g - qdd) - df_int/dp - (K_t + mu Phi_qq) q0' - C_t qd'
    !!                                    Phi_q qdd' = -(Phi_qq q0') qdd - 2 qd^T Phi_qq qd'
    !! (exact for linear constraints, and for rigid links started at rest; the
    !! third derivative of a rigid link times qd^2 is neglected).
    subroutine sens_initial(m, dprop, ls, qd0, x, status)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: dprop(:, :, :)
        type(linear_system), intent(inout) :: ls
        real(wp), intent(in) :: qd0(m%ndof)
        type(ga_state), intent(inout) :: x
        integer, intent(out) :: status
        integer :: nv, v, lst, ierr
        real(wp) :: k0, kq(m%ndof), kq2(m%ndof, 1), c1(m%nc), c2(m%nc)
        real(wp), allocatable :: rhs(:, :), md(:, :), zero(:, :)
        status = GA_OK
        nv = size(dprop, 3)
        allocate (rhs(m%n, nv), md(m%ndof, nv), zero(m%ndof, nv), stat=ierr)
        if (ierr /= 0) then
            status = GA_NO_MEMORY
            return
        end if
        zero = 0
        k0 = mass_scale(m)
        ! velocities
        call mass_design_derivative_times(m, dprop, qd0 - x%qd, md)
        rhs(1:m%ndof, :) = md
        do v = 1, nv
            call constraint_curvature(m, x%q, x%dq(:, v), x%qd, c1)
            rhs(m%ndof + 1:, v) = -k0 * c1
        end do
        call ls_solve(ls, rhs, lst)
        if (lst /= LS_OK) then
            status = GA_NONFINITE
            return
        end if
        x%dqd = rhs(1:m%ndof, :)
        ! accelerations and multipliers
        ! dM/dp (g - qdd) - df_int/dp: the step right-hand side with beta' = 0
        call step_design_rhs(m, dprop, x%q, x%qd, x%qdd - m%gacc, 0.0_wp, zero, rhs(1:m%ndof, :))
        do v = 1, nv
            call stiffness_times(m, x%q, x%qd, x%mu, x%dq(:, v), kq)
            rhs(1:m%ndof, v) = rhs(1:m%ndof, v) - kq
            if (m%nsd > 0) then
                ! spring-dampers: - K_sd q0'
                call spring_times(m, x%q, x%qd, x%dq(:, v), 1.0_wp, 0.0_wp, kq)
                rhs(1:m%ndof, v) = rhs(1:m%ndof, v) - kq
            end if
            if (m%nsd > 0 .or. m%damped) then
                ! velocity-dependent forces: - C_t qd'
                call damping_times(m, x%q, x%qd, x%dqd(:, v:v), kq2)
                rhs(1:m%ndof, v) = rhs(1:m%ndof, v) - kq2(:, 1)
            end if
            call constraint_curvature(m, x%q, x%dq(:, v), x%qdd, c1)
            call constraint_curvature(m, x%q, x%qd, x%dqd(:, v), c2)
            rhs(m%ndof + 1:, v) = -k0 * (c1 + 2 * c2)
        end do
        call ls_solve(ls, rhs, lst)
        if (lst /= LS_OK) then
            status = GA_NONFINITE
            return
        end if
        x%dqdd = rhs(1:m%ndof, :)
        if (m%nc > 0) x%dmu = k0 * rhs(m%ndof + 1:, :)
    end subroutine sens_initial

end module generalized_alpha
