!> Pure kernels of the force elements between nodes: point-to-point spring-dampers.
!!
!! A spring-damper joins the positions x_a, x_b of two nodes (their rotations are
!! not involved). With d = x_b - x_a, the current length l = |d|, the unit vector
!! e = d / l and the elongation rate ldot = e . (v_b - v_a), the tension is
!!   N = k (l - l0) + c ldot + f0
!! (stiffness k, damping c, free length l0, constant preload f0). Its contribution
!! to the internal forces of eq. (1) is the gradient of l times N:
!!   f = N g,   g = dl/dq = [-e; e]     (q = [x_a, y_a, x_b, y_b])
!! (for c = 0 and f0 = 0, f is the gradient of the energy k (l - l0)^2 / 2).
!! The force depends on the velocities, so the iteration matrix of eq. (7) gets,
!! besides ck K, a damping term gamma' C (see assembly.f90):
!!   K = df/dq  = k g g^T + c g (B w)^T + (N / l) B P B^T
!!   C = df/dqd = c g g^T
!! with P = I - e e^T, w = P (v_b - v_a) / l = d(ldot)/dd, and B = [-I; I] (so
!! B P B^T = [P -P; -P P]). K is not symmetric when c ldot /= 0.
module force_elements
    use flexmbs_kinds, only: wp
    implicit none
    private
    public :: spring_damper, SD_NPROP

    integer, parameter :: SD_NPROP = 4   !! properties per spring-damper: k, c, l0, f0

contains

    !> Forces f (4) of one spring-damper and, when asked, its tangents K and C (4 x 4).
    !! At zero length the direction is undefined: e = 0 there (no force but f0 g = 0).
    pure subroutine spring_damper(prop, xe, ve, fe, ke, ce)
        real(wp), intent(in) :: prop(SD_NPROP)        !! k, c, l0, f0
        real(wp), intent(in) :: xe(4)                 !! x_a, y_a, x_b, y_b
        real(wp), intent(in) :: ve(4)                 !! their velocities
        real(wp), intent(out) :: fe(4)                !! internal forces f = N g
        real(wp), intent(out), optional :: ke(4, 4)   !! df/dq
        real(wp), intent(out), optional :: ce(4, 4)   !! df/dqd
        real(wp) :: d(2), dv(2), e(2), g(4), w(4), p(2, 2), l, ldot, tension
        integer :: a, b
        d = xe(3:4) - xe(1:2)
        dv = ve(3:4) - ve(1:2)
        l = norm2(d)
        if (l > 0) then
            e = d / l
        else
            e = 0
        end if
        ldot = dot_product(e, dv)
        tension = prop(1) * (l - prop(3)) + prop(2) * ldot + prop(4)
        g = [-e, e]
        fe = tension * g
        if (present(ce)) then
            do b = 1, 4
                ce(:, b) = prop(2) * g * g(b)
            end do
        end if
        if (.not. present(ke)) return
        p(:, 1) = [1.0_wp - e(1) * e(1), -e(2) * e(1)]
        p(:, 2) = [-e(1) * e(2), 1.0_wp - e(2) * e(2)]
        if (l > 0) then
            w(3:4) = matmul(p, dv) / l
        else
            w(3:4) = 0
        end if
        w(1:2) = -w(3:4)
        do b = 1, 4
            ke(:, b) = g * (prop(1) * g(b) + prop(2) * w(b))
        end do
        if (l > 0) then
            do b = 1, 2
                do a = 1, 2
                    ke(a, b) = ke(a, b) + tension / l * p(a, b)
                    ke(a + 2, b + 2) = ke(a + 2, b + 2) + tension / l * p(a, b)
                    ke(a, b + 2) = ke(a, b + 2) - tension / l * p(a, b)
                    ke(a + 2, b) = ke(a + 2, b) - tension / l * p(a, b)
                end do
            end do
        end if
    end subroutine spring_damper

end module force_elements
