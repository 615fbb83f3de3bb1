!> Design derivatives of the residual of eq. (1) for the direct differentiation
!! of the discrete generalized-alpha equations (see generalized_alpha.f90).
!!
!! The design enters through the section properties of each element only:
!! dprop(:, e, v) = d[EA, kGA, EI, rhoA, rhoI]_e / dp_v. The internal forces are
!! linear in (EA, kGA, EI) (beam2d: forces per unit stiffness) and the mass
!! matrix is linear in (rhoA, rhoI), so every partial derivative is exact:
!!   dr/dp_v = dM/dp_v (qdd - g_acc) + df_int/dp_v
!! (gravity on the beam's own mass is M g_acc; nodal loads do not depend on p). The beams'
!! Kelvin–Voigt damping forces are proportional to the stiffnesses as well (beam2d.f90):
!! df_int/dp_v holds them, at the state's velocities qd (the material's time eta does not
!! depend on the design).
module sensitivity
    use flexmbs_kinds, only: wp
    use beam2d, only: beam_internal_forces, MAX_EDOF
    use constraints, only: MAX_CDOF
    use model_data, only: mbs_model
    use assembly, only: constraint_values
    implicit none
    private
    public :: mass_design_derivative_times, stiffness_times, add_curvature_times, &
              constraint_curvature, step_design_rhs

contains

    !> Right-hand sides of the direct differentiation of one step, in one pass over the
    !! elements: rhs(:, v) = -(df_int/dp_v + dM/dp_v acc) + betap M qhat(:, v), with
    !! acc = qdd - g_acc and f_int at (q, qd) (see sens_step in generalized_alpha.f90).
    subroutine step_design_rhs(m, dprop, q, qd, acc, betap, qhat, rhs)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: dprop(:, :, :)     !! (5, nel, nv)
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), acc(m%ndof), betap
        real(wp), intent(in) :: qhat(:, :)         !! (ndof, nv)
        real(wp), intent(out) :: rhs(:, :)         !! (ndof, nv) (rows of the coordinates only)
        real(wp) :: fe(MAX_EDOF), parts(MAX_EDOF, 3), qe(MAX_EDOF), qr(MAX_EDOF), acce(MAX_EDOF)
        real(wp) :: ya(MAX_EDOF), yi(MAX_EDOF), qh(MAX_EDOF), mq(MAX_EDOF), ve(MAX_EDOF)
        integer :: e, ne, a, b, v, d, nv
        logical :: has_stiff, has_mass
        nv = size(dprop, 3)
        do v = 1, nv
            rhs(:, v) = betap * m%lumped * qhat(:, v)
        end do
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            has_stiff = any(dprop(1:3, e, :) /= 0)
            has_mass = any(dprop(4:5, e, :) /= 0)
            do a = 1, ne
                d = m%el_dofs(a, e)
                qe(a) = q(d)
                qr(a) = m%qref(d)
                acce(a) = acc(d)
                ve(a) = qd(d)
            end do
            if (has_stiff) call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), &
                qr(1:ne), qe(1:ne), fe(1:ne), parts=parts(1:ne, :), eref=m%el_eref(:, :, e), &
                eta=m%el_eta(e), qde=ve(1:ne))
            if (has_mass) then
                ya(1:ne) = matmul(m%el_mass_a(1:ne, 1:ne, e), acce(1:ne))
                yi(1:ne) = matmul(m%el_mass_i(1:ne, 1:ne, e), acce(1:ne))
            end if
            do v = 1, nv
                do a = 1, ne
                    qh(a) = betap * qhat(m%el_dofs(a, e), v)
                end do
                ! betap M_e qhat_e (explicit loops: no temporary of the array sections)
                mq(1:ne) = 0
                do b = 1, ne
                    do a = 1, ne
                        mq(a) = mq(a) + m%el_mass(a, b, e) * qh(b)
                    end do
                end do
                if (has_stiff) then
                    do a = 1, ne
                        mq(a) = mq(a) - dot_product(dprop(1:3, e, v), parts(a, :))
                    end do
                end if
                if (has_mass) mq(1:ne) = mq(1:ne) - dprop(4, e, v) * ya(1:ne) - dprop(5, e, v) * yi(1:ne)
                do a = 1, ne
                    d = m%el_dofs(a, e)
                    rhs(d, v) = rhs(d, v) + mq(a)
                end do
            end do
        end do
    end subroutine step_design_rhs

    !> y(:, v) = dM/dp_v x for every design variable.
    subroutine mass_design_derivative_times(m, dprop, x, y)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: dprop(:, :, :)     !! (5, nel, nv)
        real(wp), intent(in) :: x(m%ndof)
        real(wp), intent(out) :: y(:, :)           !! (ndof, nv)
        real(wp) :: xe(MAX_EDOF), ya(MAX_EDOF), yi(MAX_EDOF)
        integer :: e, ne, a, v, d
        y = 0
        do e = 1, m%nel
            if (all(dprop(4:5, e, :) == 0)) cycle
            ne = 3 * m%el_nen(e)
            do a = 1, ne
                xe(a) = x(m%el_dofs(a, e))
            end do
            ya(1:ne) = matmul(m%el_mass_a(1:ne, 1:ne, e), xe(1:ne))
            yi(1:ne) = matmul(m%el_mass_i(1:ne, 1:ne, e), xe(1:ne))
            do v = 1, size(dprop, 3)
                do a = 1, ne
                    d = m%el_dofs(a, e)
                    y(d, v) = y(d, v) + dprop(4, e, v) * ya(a) + dprop(5, e, v) * yi(a)
                end do
            end do
        end do
    end subroutine mass_design_derivative_times

    !> y = (K_t(q, qd) + sum_r mu_r Phi_r,qq) x, matrix-free (element by element; K_t of the
    !! beams, with their damping forces at the velocities qd); with transposed = .true., the
    !! transpose of that matrix times x (the adjoint).
    subroutine stiffness_times(m, q, qd, mu, x, y, transposed)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), mu(m%nc), x(m%ndof)
        real(wp), intent(out) :: y(m%ndof)
        logical, intent(in), optional :: transposed
        real(wp) :: fe(MAX_EDOF), ke(MAX_EDOF, MAX_EDOF), qe(MAX_EDOF), qr(MAX_EDOF), xe(MAX_EDOF)
        real(wp) :: ve(MAX_EDOF)
        integer :: e, ne, a, d
        logical :: tr
        tr = .false.
        if (present(transposed)) tr = transposed
        y = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            do a = 1, ne
                d = m%el_dofs(a, e)
                qe(a) = q(d)
                qr(a) = m%qref(d)
                xe(a) = x(d)
                ve(a) = qd(d)
            end do
            call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), qr(1:ne), &
                                      qe(1:ne), fe(1:ne), ke(1:ne, 1:ne), eref=m%el_eref(:, :, e), &
                                      eta=m%el_eta(e), qde=ve(1:ne))
            if (tr) then
                fe(1:ne) = matmul(xe(1:ne), ke(1:ne, 1:ne))
            else
                fe(1:ne) = matmul(ke(1:ne, 1:ne), xe(1:ne))
            end if
            do a = 1, ne
                y(m%el_dofs(a, e)) = y(m%el_dofs(a, e)) + fe(a)
            end do
        end do
        call add_curvature_times(m, q, mu, x, y)
    end subroutine stiffness_times

    !> y = y + sum_r c(r) Phi_r,qq(q) x (the constraint Hessians are symmetric, so this is
    !! also the transposed product).
    subroutine add_curvature_times(m, q, c, x, y)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), c(m%nc), x(m%ndof)
        real(wp), intent(inout) :: y(m%ndof)
        real(wp) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF)
        integer :: a, b, r
        if (m%linear_constraints) return
        do r = 1, m%nc
            call constraint_values(m, r, q, 0.0_wp, phi, grad, hess)
            do a = 1, MAX_CDOF
                if (m%c_dofs(a, r) <= 0) cycle
                do b = 1, MAX_CDOF
                    if (m%c_dofs(b, r) <= 0) cycle
                    y(m%c_dofs(a, r)) = y(m%c_dofs(a, r)) + c(r) * hess(a, b) * x(m%c_dofs(b, r))
                end do
            end do
        end do
    end subroutine add_curvature_times

    !> c(r) = u^T Phi_r,qq w for every constraint row (0 for linear rows).
    subroutine constraint_curvature(m, q, u, w, c)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), u(m%ndof), w(m%ndof)
        real(wp), intent(out) :: c(m%nc)
        real(wp) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF)
        integer :: a, b, r
        c = 0
        if (m%linear_constraints) return
        do r = 1, m%nc
            call constraint_values(m, r, q, 0.0_wp, phi, grad, hess)
            do a = 1, MAX_CDOF
                if (m%c_dofs(a, r) <= 0) cycle
                do b = 1, MAX_CDOF
                    if (m%c_dofs(b, r) <= 0) cycle
                    c(r) = c(r) + u(m%c_dofs(a, r)) * hess(a, b) * w(m%c_dofs(b, r))
                end do
            end do
        end do
    end subroutine constraint_curvature

end module sensitivity
