!> Working precision of the flexmbs core: one real kind everywhere.
!! At the f2py boundary the same kind is spelled real(c_double).
module flexmbs_kinds
    use iso_fortran_env, only: real64
    implicit none
    private
    public :: wp

    !> Working precision (IEEE double, identical to c_double)
    integer, parameter :: wp = real64
end module flexmbs_kinds
