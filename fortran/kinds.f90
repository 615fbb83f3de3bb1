!> Working precision of the flexmbs core: one real kind everywhere.
!! At the f2py boundary the same kind is spelled real(c_double).
module flexmbs_kinds
    use iso_fortran_env, only: real64
    use iso_c_binding, only: c_double
    implicit none
    private
    public :: wp

    !> Working precision (IEEE double, identical to c_double)
    integer, parameter :: wp = real64

    ! The f2py API spells the kind c_double; both must agree.
    logical, parameter, private :: same_kind = (wp == c_double)
    integer, parameter, private :: check_kind(merge(1, -1, same_kind)) = 1
end module flexmbs_kinds
