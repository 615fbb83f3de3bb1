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
!!  - CON_PRISMATIC: the component of x_b - x_a along a vector fixed in the
!!    frame of node a (prismatic joint between two bodies), e0 = coef(1:2) the
!!    vector at phi_a = 0:
!!      e   = R(phi_a) e0,   d = x_b - x_a,
!!      Phi = e . d - c0 - lawcoef * law(t),
!!    with dofs (x_a, y_a, x_b, y_b, phi_a). With e' = de/dphi_a = R(pi/2) e,
!!      Phi_q   = (-e, e, e' . d),
!!      Phi_qq  : (phi_a, phi_a) = -e . d,  (x_a, phi_a) = -e',  (x_b, phi_a) = e'.
!!    e0 the axis normal n0 keeps x_b on the axis of body a through x_a; e0
!!    the axis direction t0 with a law drives the relative translation.
module constraints
    use flexmbs_kinds, only: wp
    implicit none
    private
    public :: constraint_row, MAX_CDOF, CON_LINEAR, CON_RIGID_X, CON_RIGID_Y, CON_PRISMATIC

    integer, parameter :: MAX_CDOF = 5      !! coordinates per constraint row at most
    integer, parameter :: CON_LINEAR = 1    !! linear row (constant gradient)
    integer, parameter :: CON_RIGID_X = 2   !! rigid link, x component
    integer, parameter :: CON_RIGID_Y = 3   !! rigid link, y component
    integer, parameter :: CON_PRISMATIC = 4 !! projection on a vector of node a's frame

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
        real(wp) :: c, s, rx, ry, e(2), ep(2), d(2)
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
        case (CON_PRISMATIC)
            c = cos(qv(5))
            s = sin(qv(5))
            e = [c * coef(1) - s * coef(2), s * coef(1) + c * coef(2)]    ! e = R(phi_a) e0
            ep = [-e(2), e(1)]                                            ! de/dphi_a
            d = qv(3:4) - qv(1:2)                                         ! x_b - x_a
            phi = dot_product(e, d) - c0 - drive
            grad = [-e(1), -e(2), e(1), e(2), dot_product(ep, d)]
            hess(5, 5) = -dot_product(e, d)
            hess(1:2, 5) = -ep
            hess(3:4, 5) = ep
            hess(5, 1:4) = hess(1:4, 5)
        case default
            phi = dot_product(coef, qv) - c0 - drive
            grad = coef
        end select
    end subroutine constraint_row

end module constraints
