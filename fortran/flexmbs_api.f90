!> The f2py surface of the flexmbs core (compiled as flexmbs._core).
!!
!! This is the only file f2py reads. Every routine takes plain scalars and
!! arrays: real(c_double), integer(c_int), Fortran-ordered. Status codes are
!! returned, never printed; flexmbs (Python) turns them into exceptions.

!> Solve A X = B with the dense LU path (LAPACK).
subroutine dense_solve(n, nrhs, a, b, x, status)
    use iso_c_binding, only: c_double, c_int
    use linear_solver, only: linear_system, ls_init_dense, ls_factor, ls_solve, ls_free
    implicit none
    integer(c_int), intent(in) :: n                 !! order
    integer(c_int), intent(in) :: nrhs              !! number of right-hand sides
    real(c_double), intent(in) :: a(n, n)           !! matrix
    real(c_double), intent(in) :: b(n, nrhs)        !! right-hand sides
    real(c_double), intent(out) :: x(n, nrhs)       !! solutions
    integer(c_int), intent(out) :: status           !! 0 ok, 1 singular, 3 invalid, 4 non-finite
    type(linear_system) :: ls
    integer :: st
    call ls_init_dense(ls, int(n))
    call ls_factor(ls, reshape(a, [n * n]), st)
    x = b
    if (st == 0) call ls_solve(ls, x, st)
    status = int(st, c_int)
    call ls_free(ls)
end subroutine dense_solve

!> Solve A X = B with KLU, then refactor with new values of the same pattern
!! and solve A2 X2 = B2 (exercises the symbolic-once / numeric-refactor path).
subroutine sparse_solve(n, nnz, nrhs, ap, ai, ax, ax2, b, b2, x, x2, status)
    use iso_c_binding, only: c_double, c_int
    use linear_solver, only: linear_system, ls_init_sparse, ls_factor, ls_solve, ls_free
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
