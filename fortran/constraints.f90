!> Kinematic constraints Phi(q, t) = 0 of eq. (1), one scalar row at a time.
!!
!! Row kinds (each row touches at most MAX_CDOF coordinates):
!!  - CON_LINEAR: Phi = sum_k coef_k q(dof_k) - c0 - lawcoef * law(t).
!!    Clamps, hinges (pins), prescribed positions, and absolute or relative
!!    rotation drives (motors) are all of this kind: their gradient is constant.
!!  - CON_RIGID_X / CON_RIGID_Y: rigid link between node i and node j, with
!!    the offset d = (dx, dy) of j in the frame of node i (coef(1:2)):
!!      Phi_x = x_j - x_i - (cos(phi_i) dx - sin(phi_i) dy)
!!      Phi_y = y_j - y_i - (sin(phi_i) dx + cos(phi_i) dy)
!!    with dofs (x_i, x_j, phi_i) and (y_i, y_j, phi_i) respectively.
module constraints
    use flexmbs_kinds, only: wp
    implicit none
    private
    public :: constraint_row, MAX_CDOF, CON_LINEAR, CON_RIGID_X, CON_RIGID_Y

    integer, parameter :: MAX_CDOF = 4      !! coordinates per constraint row at most
    integer, parameter :: CON_LINEAR = 1    !! linear row (constant gradient)
    integer, parameter :: CON_RIGID_X = 2   !! rigid link, x component
    integer, parameter :: CON_RIGID_Y = 3   !! rigid link, y component

contains

    !> Value, gradient and Hessian of one constraint row at q.
    !! `qv` holds the row's coordinates q(dofs(1:MAX_CDOF)) (0 where unused),
    !! `drive` the value lawcoef * law(t) of its time law (0 if none).
    pure subroutine constraint_row(kind, coef, c0, drive, qv, phi, grad, hess)
        integer, intent(in) :: kind                        !! CON_* kind
        real(wp), intent(in) :: coef(MAX_CDOF)             !! coefficients / rigid offsets
        real(wp), intent(in) :: c0                         !! constant term
        real(wp), intent(in) :: drive                      !! prescribed part lawcoef*law(t)
        real(wp), intent(in) :: qv(MAX_CDOF)               !! coordinates of the row
        real(wp), intent(out) :: phi                       !! Phi
        real(wp), intent(out) :: grad(MAX_CDOF)            !! dPhi/dqv
        real(wp), intent(out) :: hess(MAX_CDOF, MAX_CDOF)  !! d2Phi/dqv2
        real(wp) :: c, s, rx, ry
        hess = 0
        grad = 0
        select case (kind)
        case (CON_RIGID_X)
            c = cos(qv(3))
            s = sin(qv(3))
            rx = c * coef(1) - s * coef(2)
            ry = s * coef(1) + c * coef(2)
            phi = qv(2) - qv(1) - rx - c0 - drive
            grad(1:3) = [-1.0_wp, 1.0_wp, ry]
            hess(3, 3) = rx
        case (CON_RIGID_Y)
            c = cos(qv(3))
            s = sin(qv(3))
            rx = c * coef(1) - s * coef(2)
            ry = s * coef(1) + c * coef(2)
            phi = qv(2) - qv(1) - ry - c0 - drive
            grad(1:3) = [-1.0_wp, 1.0_wp, -rx]
            hess(3, 3) = ry
        case default
            phi = dot_product(coef, qv) - c0 - drive
            grad = coef
        end select
    end subroutine constraint_row

end module constraints
