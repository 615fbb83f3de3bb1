!> Linear solvers behind one interface: dense LU (LAPACK dgetrf/dgetrs) for
!! small systems, SuiteSparse KLU (through klu_shim.c) for large sparse ones.
!!
!! A `linear_system` owns its factorization: the caller declares it as a
!! local variable, so two simulations in one process never share state.
!! Matrix values are passed as a flat array: column-major n*n storage for the
!! dense kind, CSC values of the pattern given at initialisation for KLU.
module linear_solver
    use iso_c_binding, only: c_ptr, c_null_ptr, c_int, c_double, c_associated
    use iso_fortran_env, only: int64
    use flexmbs_kinds, only: wp
    implicit none
    private
    public :: linear_system, ls_init_dense, ls_init_sparse, ls_factor, ls_solve, ls_free, dense_bytes
    public :: SOLVER_DENSE, SOLVER_KLU
    public :: LS_OK, LS_SINGULAR, LS_NO_MEMORY, LS_INVALID, LS_NONFINITE

    integer, parameter :: SOLVER_DENSE = 1  !! LAPACK LU with partial pivoting
    integer, parameter :: SOLVER_KLU = 2    !! SuiteSparse KLU

    integer, parameter :: LS_OK = 0         !! success
    integer, parameter :: LS_SINGULAR = 1   !! zero or negligible pivot
    integer, parameter :: LS_NO_MEMORY = 2  !! allocation failed
    integer, parameter :: LS_INVALID = 3    !! bad pattern or call order
    integer, parameter :: LS_NONFINITE = 4  !! NaN or Inf among the values

    !> Pivot ratio min|u_ii|/max|u_ii| below which a matrix counts as singular
    real(wp), parameter :: pivot_ratio_min = 1.0e-14_wp

    type :: linear_system
        integer :: kind = 0                  !! SOLVER_DENSE or SOLVER_KLU
        integer :: n = 0                     !! order of the matrix
        integer :: nnz = 0                   !! stored values (n*n when dense)
        integer :: factorizations = 0        !! numeric factorizations done
        integer :: analyses = 0              !! KLU symbolic analyses run (0 when borrowed)
        logical :: factored = .false.        !! a valid factorization is held
        real(wp), allocatable :: lu(:, :)    !! dense LU factors
        integer, allocatable :: ipiv(:)      !! dense pivots
        type(c_ptr) :: klu = c_null_ptr      !! KLU handle (klu_shim.c)
    end type linear_system

    interface
        function fx_klu_create(n, nnz, ap, ai, shared, status) bind(c, name='fx_klu_create')
            import :: c_ptr, c_int
            integer(c_int), value :: n, nnz
            integer(c_int), intent(in) :: ap(*), ai(*)
            type(c_ptr), value :: shared
            integer(c_int), intent(out) :: status
            type(c_ptr) :: fx_klu_create
        end function fx_klu_create
        function fx_klu_analysed(h) bind(c, name='fx_klu_analysed')
            import :: c_ptr, c_int
            type(c_ptr), value :: h
            integer(c_int) :: fx_klu_analysed
        end function fx_klu_analysed
        function fx_klu_factor(h, ax) bind(c, name='fx_klu_factor')
            import :: c_ptr, c_int, c_double
            type(c_ptr), value :: h
            real(c_double), intent(in) :: ax(*)
            integer(c_int) :: fx_klu_factor
        end function fx_klu_factor
        function fx_klu_solve(h, b, nrhs) bind(c, name='fx_klu_solve')
            import :: c_ptr, c_int, c_double
            type(c_ptr), value :: h
            real(c_double), intent(inout) :: b(*)
            integer(c_int), value :: nrhs
            integer(c_int) :: fx_klu_solve
        end function fx_klu_solve
        function fx_klu_tsolve(h, b, nrhs) bind(c, name='fx_klu_tsolve')
            import :: c_ptr, c_int, c_double
            type(c_ptr), value :: h
            real(c_double), intent(inout) :: b(*)
            integer(c_int), value :: nrhs
            integer(c_int) :: fx_klu_tsolve
        end function fx_klu_tsolve
        subroutine fx_klu_free(h) bind(c, name='fx_klu_free')
            import :: c_ptr
            type(c_ptr), value :: h
        end subroutine fx_klu_free
    end interface

contains

    !> Prepare a dense system of order n. status = LS_NO_MEMORY when the factors
    !! (dense_bytes(n)) cannot be allocated, or n*n exceeds the default-integer
    !! index range of the value array; nothing stays allocated then.
    subroutine ls_init_dense(ls, n, status)
        type(linear_system), intent(inout) :: ls  !! system to initialise
        integer, intent(in) :: n                  !! order
        integer, intent(out) :: status            !! LS_* code
        integer :: ierr
        call ls_free(ls)
        status = LS_OK
        if (int(n, int64)**2 > int(huge(n), int64)) then
            status = LS_NO_MEMORY
            return
        end if
        ls%kind = SOLVER_DENSE
        ls%n = n
        ls%nnz = n * n
        allocate (ls%lu(n, n), ls%ipiv(n), stat=ierr)
        if (ierr /= 0) then
            call ls_free(ls)
            status = LS_NO_MEMORY
        end if
    end subroutine ls_init_dense

    !> Bytes of the dense factors of order n (LU values and pivots).
    pure function dense_bytes(n) result(b)
        integer, intent(in) :: n
        real(wp) :: b
        b = 8.0_wp * real(n, wp)**2 + 4.0_wp * real(n, wp)
    end function dense_bytes

    !> Prepare a sparse system: KLU symbolic analysis of the CSC pattern (0-based), or,
    !! with `shared` (an analysis object of klu_shim.c's fx_klu_analyze, made once per
    !! model), that analysis borrowed: status LS_INVALID if it is of another pattern.
    subroutine ls_init_sparse(ls, n, ap, ai, status, shared)
        type(linear_system), intent(inout) :: ls  !! system to initialise
        integer, intent(in) :: n                  !! order
        integer, intent(in) :: ap(n + 1)          !! column pointers, 0-based
        integer, intent(in) :: ai(:)              !! row indices, 0-based
        integer, intent(out) :: status            !! LS_* code
        type(c_ptr), intent(in), optional :: shared
        type(c_ptr) :: given
        integer(c_int) :: st
        call ls_free(ls)
        ls%kind = SOLVER_KLU
        ls%n = n
        ls%nnz = ap(n + 1)
        given = c_null_ptr
        if (present(shared)) given = shared
        ls%klu = fx_klu_create(int(n, c_int), int(ls%nnz, c_int), int(ap, c_int), int(ai, c_int), &
                               given, st)
        status = int(st)
        if (status == LS_OK) ls%analyses = ls%analyses + int(fx_klu_analysed(ls%klu))
    end subroutine ls_init_sparse

    !> Numeric factorization of the matrix whose values are `vals`.
    subroutine ls_factor(ls, vals, status)
        type(linear_system), intent(inout) :: ls  !! system
        real(wp), intent(in) :: vals(:)           !! values (dense column-major or CSC)
        integer, intent(out) :: status            !! LS_* code
        integer :: info, i, j
        real(wp) :: umax, umin
        ls%factored = .false.
        select case (ls%kind)
        case (SOLVER_DENSE)
            if (.not. all(abs(vals(1:ls%nnz)) <= huge(1.0_wp))) then
                status = LS_NONFINITE
                return
            end if
            ! column by column: no n x n temporary
            do j = 1, ls%n
                ls%lu(:, j) = vals((j - 1) * ls%n + 1:j * ls%n)
            end do
            call dgetrf(ls%n, ls%n, ls%lu, ls%n, ls%ipiv, info)
            ls%factorizations = ls%factorizations + 1
            if (info > 0) then
                status = LS_SINGULAR
                return
            else if (info < 0) then
                status = LS_INVALID
                return
            end if
            umax = 0.0_wp
            umin = huge(1.0_wp)
            do i = 1, ls%n
                umax = max(umax, abs(ls%lu(i, i)))
                umin = min(umin, abs(ls%lu(i, i)))
            end do
            if (.not. (umin > pivot_ratio_min * umax)) then
                status = LS_SINGULAR
                return
            end if
            status = LS_OK
        case (SOLVER_KLU)
            if (.not. c_associated(ls%klu)) then
                status = LS_INVALID
                return
            end if
            status = int(fx_klu_factor(ls%klu, vals))
            ls%factorizations = ls%factorizations + 1
        case default
            status = LS_INVALID
        end select
        ls%factored = (status == LS_OK)
    end subroutine ls_factor

    !> Solve A x = b (or A^T x = b with transposed = .true.: the adjoint's solves) in place
    !! for the columns of b, with the held factorization.
    subroutine ls_solve(ls, b, status, transposed)
        type(linear_system), intent(inout) :: ls  !! factored system
        real(wp), intent(inout) :: b(:, :)        !! right-hand sides in, solutions out
        integer, intent(out) :: status            !! LS_* code
        logical, intent(in), optional :: transposed
        integer :: info
        logical :: tr
        tr = .false.
        if (present(transposed)) tr = transposed
        if (.not. ls%factored) then
            status = LS_INVALID
            return
        end if
        select case (ls%kind)
        case (SOLVER_DENSE)
            call dgetrs(merge('T', 'N', tr), ls%n, size(b, 2), ls%lu, ls%n, ls%ipiv, b, size(b, 1), info)
            status = merge(LS_OK, LS_INVALID, info == 0)
        case (SOLVER_KLU)
            if (tr) then
                status = int(fx_klu_tsolve(ls%klu, b, int(size(b, 2), c_int)))
            else
                status = int(fx_klu_solve(ls%klu, b, int(size(b, 2), c_int)))
            end if
        case default
            status = LS_INVALID
        end select
        if (status == LS_OK) then
            if (.not. all(abs(b) <= huge(1.0_wp))) status = LS_NONFINITE
        end if
    end subroutine ls_solve

    !> Release the factorization and the KLU handle.
    subroutine ls_free(ls)
        type(linear_system), intent(inout) :: ls  !! system to release
        if (allocated(ls%lu)) deallocate (ls%lu)
        if (allocated(ls%ipiv)) deallocate (ls%ipiv)
        if (c_associated(ls%klu)) call fx_klu_free(ls%klu)
        ls%klu = c_null_ptr
        ls%kind = 0
        ls%n = 0
        ls%nnz = 0
        ls%factored = .false.
    end subroutine ls_free

end module linear_solver
