!> Assembly of the residual of eq. (1) and of the iteration matrix of eq. (7).
!!
!! Unknowns of a Newton correction: z = [dq (ndof); dlambda (nc)]. The
!! physical multipliers are mu = k lambda, with k the scaling factor of eq. (1);
!! p is the penalty of the augmented Lagrangian. Residual:
!!   r_q = M qdd + f_int(q, qd) + f_sd(q, qd) - f_ext(t) + Phi_q^T (mu + p Phi)
!!   r_c = k Phi(q, t)
!! (f_int: the beams, with their Kelvin–Voigt damping, beam2d.f90; f_sd: the
!! spring-dampers, force_elements.f90). Iteration matrix (eq. 7, with dqdd = beta' dq,
!! dqd = gamma' dq):
!!   [ cm M + cc C_t + ck (K_t + p Phi_q^T Phi_q + sum_r (mu_r + p Phi_r) Phi_r,qq)   k Phi_q^T ]
!!   [ k Phi_q                                                                       0         ]
!! with K_t = d(f_int + f_sd)/dq and C_t = d(f_int + f_sd)/dqd.
!! Values go to the positions given by the model's maps, so the same code fills
!! a dense column-major matrix or the CSC values of the KLU pattern.
module assembly
    use flexmbs_kinds, only: wp
    use beam2d, only: beam_internal_forces, beam_forces, MAX_EDOF
    use constraints, only: constraint_row, MAX_CDOF
    use force_elements, only: spring_damper
    use model_data, only: mbs_model, law_value
    implicit none
    private
    public :: internal_forces, mass_times, external_forces, constraint_values
    public :: residual, iteration_matrix, spring_forces, spring_times, damping_times

contains

    !> Internal forces f_int(q, qd) (qd: the beams' Kelvin–Voigt damping, beam2d.f90); with
    !! `vals`, adds ck * K_t + cc * C_t of the beams at the element positions; with `parts`
    !! (and `vals`), also every element's forces per unit stiffness (beam_internal_forces'
    !! parts: the adjoint's design contraction, from the same pass as the tangent).
    subroutine internal_forces(m, q, qd, fint, vals, ck, parts, cc)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof)
        real(wp), intent(out) :: fint(m%ndof)
        real(wp), intent(inout), optional :: vals(:)
        real(wp), intent(in), optional :: ck
        real(wp), intent(out), optional :: parts(:, :, :)     !! (MAX_EDOF, 3, nel)
        real(wp), intent(in), optional :: cc                  !! coefficient of C_t (0 if absent)
        real(wp) :: fe(MAX_EDOF), ke(MAX_EDOF, MAX_EDOF), ce(MAX_EDOF, MAX_EDOF)
        real(wp) :: qe(MAX_EDOF), qr(MAX_EDOF), ve(MAX_EDOF), ccv, eta
        integer :: e, ne, a, b, d
        fint = 0
        ccv = 0
        if (present(cc)) ccv = cc
        ve = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            eta = m%el_eta(e)
            do a = 1, ne
                d = m%el_dofs(a, e)
                qe(a) = q(d)
                qr(a) = m%qref(d)
                if (eta /= 0) ve(a) = qd(d)
            end do
            if (present(vals)) then
                if (present(parts)) then
                    call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), &
                                              qr(1:ne), qe(1:ne), fe(1:ne), ke(1:ne, 1:ne), &
                                              parts=parts(1:ne, :, e), eref=m%el_eref(:, :, e), &
                                              eta=eta, qde=ve(1:ne), ce=ce(1:ne, 1:ne))
                else if (eta /= 0) then
                    call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), &
                                              qr(1:ne), qe(1:ne), fe(1:ne), ke(1:ne, 1:ne), &
                                              eref=m%el_eref(:, :, e), eta=eta, qde=ve(1:ne), &
                                              ce=ce(1:ne, 1:ne))
                else
                    ! an undamped element: no C_t (nothing to form or add)
                    call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), &
                                              qr(1:ne), qe(1:ne), fe(1:ne), ke(1:ne, 1:ne), &
                                              eref=m%el_eref(:, :, e))
                end if
                if (eta /= 0 .or. present(parts)) then
                    ! (ce = 0 for an undamped element)
                    do b = 1, ne
                        do a = 1, ne
                            vals(m%map_el(a, b, e)) = vals(m%map_el(a, b, e)) + ck * ke(a, b) &
                                                      + ccv * ce(a, b)
                        end do
                    end do
                else
                    do b = 1, ne
                        do a = 1, ne
                            vals(m%map_el(a, b, e)) = vals(m%map_el(a, b, e)) + ck * ke(a, b)
                        end do
                    end do
                end if
            else
                call beam_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), m%el_eref(:, :, e), &
                                 qe(1:ne), fe(1:ne), eta, ve(1:ne))
            end if
            do a = 1, ne
                d = m%el_dofs(a, e)
                fint(d) = fint(d) + fe(a)
            end do
        end do
    end subroutine internal_forces

    !> y = C_t x: the damping matrix d f / d qd of every velocity-dependent force (the
    !! spring-dampers' and the beams' Kelvin–Voigt damping) at (q, qd) times every column of
    !! x (ndof, nr), matrix-free (each element's matrix formed once for all columns); with
    !! transposed = .true., y = C_t^T x (the adjoint; the beams' part is symmetric).
    subroutine damping_times(m, q, qd, x, y, transposed)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), x(:, :)
        real(wp), intent(out) :: y(:, :)
        logical, intent(in), optional :: transposed
        real(wp) :: fe(MAX_EDOF), ce(MAX_EDOF, MAX_EDOF)
        integer :: e, ne, r
        do r = 1, size(x, 2)
            if (m%nsd > 0) then
                call spring_times(m, q, qd, x(:, r), 0.0_wp, 1.0_wp, y(:, r), transposed)
            else
                y(:, r) = 0
            end if
        end do
        if (.not. m%damped) return
        do e = 1, m%nel
            if (m%el_eta(e) == 0) cycle
            ne = 3 * m%el_nen(e)
            call beam_internal_forces(m%el_nen(e), m%el_len(e), m%el_prop(1:3, e), &
                                      m%qref(m%el_dofs(1:ne, e)), q(m%el_dofs(1:ne, e)), fe(1:ne), &
                                      eref=m%el_eref(:, :, e), eta=m%el_eta(e), ce=ce(1:ne, 1:ne))
            ! (an element's coordinates are distinct: the vector subscript scatters safely)
            do r = 1, size(x, 2)
                y(m%el_dofs(1:ne, e), r) = y(m%el_dofs(1:ne, e), r) &
                                           + matmul(ce(1:ne, 1:ne), x(m%el_dofs(1:ne, e), r))
            end do
        end do
    end subroutine damping_times

    !> y = M x with the constant mass matrix (element blocks + lumped diagonal).
    !! A beam's consistent mass (beam2d's beam_mass) couples only like coordinates (x with
    !! x, y with y, phi with phi) of its nodes: the other entries, zero, are skipped.
    pure subroutine mass_times(m, x, y)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: x(m%ndof)
        real(wp), intent(out) :: y(m%ndof)
        integer :: e, ne, a, b
        real(wp) :: s, xe(MAX_EDOF)
        y = m%lumped * x
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            do a = 1, ne
                xe(a) = x(m%el_dofs(a, e))
            end do
            do a = 1, ne
                s = 0
                do b = mod(a - 1, 3) + 1, ne, 3
                    s = s + m%el_mass(a, b, e) * xe(b)
                end do
                y(m%el_dofs(a, e)) = y(m%el_dofs(a, e)) + s
            end do
        end do
    end subroutine mass_times

    !> f = f_int(q, qd) + cm M qdd, in one pass over the elements: the residual's element
    !! part when no matrix is assembled (mass coupling as in mass_times).
    subroutine element_forces(m, q, qd, qdd, cm, f)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), qdd(m%ndof), cm
        real(wp), intent(out) :: f(m%ndof)
        real(wp) :: fe(MAX_EDOF), qe(MAX_EDOF), ae(MAX_EDOF), ve(MAX_EDOF), s
        integer :: e, nen, ne, a, d, i, j, k
        f = cm * m%lumped * qdd
        ve = 0
        do e = 1, m%nel
            nen = m%el_nen(e)
            ne = 3 * nen
            do a = 1, ne
                d = m%el_dofs(a, e)
                qe(a) = q(d)
                ae(a) = qdd(d)
            end do
            if (m%el_eta(e) /= 0) then
                do a = 1, ne
                    ve(a) = qd(m%el_dofs(a, e))
                end do
            end if
            call beam_forces(nen, m%el_len(e), m%el_prop(1:3, e), m%el_eref(:, :, e), &
                             qe(1:ne), fe(1:ne), m%el_eta(e), ve(1:ne))
            ! row a = coordinate k of node i couples with coordinate k of every node j
            do i = 1, nen
                do k = 1, 3
                    a = 3 * (i - 1) + k
                    s = 0
                    do j = 1, nen
                        s = s + m%el_mass(a, 3 * (j - 1) + k, e) * ae(3 * (j - 1) + k)
                    end do
                    d = m%el_dofs(a, e)
                    f(d) = f(d) + (fe(a) + cm * s)
                end do
            end do
        end do
    end subroutine element_forces

    !> External forces at time t: gravity M g_acc plus the nodal loads.
    pure subroutine external_forces(m, fgrav, t, fext)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: fgrav(m%ndof)   !! M g_acc, computed once
        real(wp), intent(in) :: t
        real(wp), intent(out) :: fext(m%ndof)
        integer :: i
        fext = fgrav
        do i = 1, m%nload
            if (m%ld_law(i) > 0) then
                fext(m%ld_dof(i)) = fext(m%ld_dof(i)) + m%ld_amp(i) * law_value(m, m%ld_law(i), t)
            else
                fext(m%ld_dof(i)) = fext(m%ld_dof(i)) + m%ld_amp(i)
            end if
        end do
    end subroutine external_forces

    !> Value, gradient and Hessian of constraint row r at (q, t).
    pure subroutine constraint_values(m, r, q, t, phi, grad, hess)
        type(mbs_model), intent(in) :: m
        integer, intent(in) :: r
        real(wp), intent(in) :: q(m%ndof), t
        real(wp), intent(out) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF)
        real(wp) :: qv(MAX_CDOF), drive
        integer :: a
        do a = 1, MAX_CDOF
            if (m%c_dofs(a, r) > 0) then
                qv(a) = q(m%c_dofs(a, r))
            else
                qv(a) = 0
            end if
        end do
        drive = 0
        if (m%c_law(r) > 0) drive = m%c_lawcoef(r) * law_value(m, m%c_law(r), t)
        call constraint_row(m%c_kind(r), m%c_coef(:, r), m%c_c0(r), drive, qv, phi, grad, hess)
    end subroutine constraint_values

    !> Residual of eq. (1): r_q = cm M qdd + f_int + f_sd - f_ext + Phi_q^T (mu + p Phi),
    !! r_c = k Phi. `cm` = 0 and qd = 0 give the static residual. Returns also max |Phi|.
    !! With `vals` (and `cmat`, `cc`), the iteration matrix of eq. (7) at the same state
    !! (iteration_matrix with cm = cmat, ck = 1) is assembled in the same pass over the elements.
    subroutine residual(m, q, qd, qdd, mu, t, fgrav, cm, kscale, pen, r, phimax, lf, vals, cmat, cc)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), qdd(m%ndof), mu(m%nc), t, fgrav(m%ndof)
        real(wp), intent(in) :: cm, kscale, pen
        real(wp), intent(in), optional :: lf    !! load factor on f_ext (static load stepping)
        real(wp), intent(out) :: r(m%n)
        real(wp), intent(out) :: phimax
        real(wp), intent(out), optional :: vals(:)   !! iteration matrix values
        real(wp), intent(in), optional :: cmat, cc   !! coefficients of M and C_t in the matrix
        real(wp) :: fext(m%ndof), mq(m%ndof)
        real(wp) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF)
        integer :: i, a
        logical :: inertia
        inertia = cm /= 0
        ! f_int (with cm M qdd when no matrix is assembled) straight into r, then - f_ext
        if (present(vals)) then
            call iteration_matrix(m, q, qd, mu, t, cmat, 1.0_wp, cc, kscale, pen, vals, r(1:m%ndof))
        else if (inertia) then
            call element_forces(m, q, qd, qdd, cm, r(1:m%ndof))     ! f_int + cm M qdd in one pass
            inertia = .false.
        else
            call internal_forces(m, q, qd, r(1:m%ndof))
        end if
        if (m%nload == 0 .and. .not. present(lf)) then
            r(1:m%ndof) = r(1:m%ndof) - fgrav              ! f_ext = M g_acc alone
        else
            call external_forces(m, fgrav, t, fext)
            if (present(lf)) fext = lf * fext
            r(1:m%ndof) = r(1:m%ndof) - fext
        end if
        if (m%nsd > 0) call spring_forces(m, q, qd, r(1:m%ndof))
        if (inertia) then
            call mass_times(m, qdd, mq)
            r(1:m%ndof) = r(1:m%ndof) + cm * mq
        end if
        phimax = 0
        do i = 1, m%nc
            call constraint_values(m, i, q, t, phi, grad, hess)
            phimax = max(phimax, abs(phi))
            do a = 1, MAX_CDOF
                if (m%c_dofs(a, i) > 0) r(m%c_dofs(a, i)) = r(m%c_dofs(a, i)) + grad(a) * (mu(i) + pen * phi)
            end do
            r(m%ndof + i) = kscale * phi
        end do
    end subroutine residual

    !> Iteration matrix of eq. (7) (see the module header) into `vals`.
    !! With `fint_out` (and ck = 1): also the internal forces f_int(q) of the same pass; with
    !! `parts` (ck /= 0): every element's forces per unit stiffness (internal_forces).
    subroutine iteration_matrix(m, q, qd, mu, t, cm, ck, cc, kscale, pen, vals, fint_out, parts)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), mu(m%nc), t
        real(wp), intent(in) :: cm      !! coefficient of M (beta' in dynamics, 0 in statics)
        real(wp), intent(in) :: ck      !! coefficient of the stiffness terms (1, or 0 for the
                                        !! initial-acceleration system)
        real(wp), intent(in) :: cc      !! coefficient of C_t (gamma' in dynamics, 0 in statics)
        real(wp), intent(in) :: kscale, pen
        real(wp), intent(out) :: vals(:)
        real(wp), intent(out), optional :: fint_out(m%ndof)
        real(wp), intent(out), optional :: parts(:, :, :)
        real(wp) :: fint(m%ndof)
        real(wp) :: phi, grad(MAX_CDOF), hess(MAX_CDOF, MAX_CDOF), w
        integer :: e, ne, a, b, i
        vals = 0
        if (ck /= 0 .or. (cc /= 0 .and. m%damped)) call internal_forces(m, q, qd, fint, vals, ck, parts, cc)
        if (present(fint_out)) fint_out = fint
        if (m%nsd > 0 .and. (ck /= 0 .or. cc /= 0)) then
            fint = 0
            call spring_forces(m, q, qd, fint, vals, ck, cc)
        end if
        if (cm /= 0) then
            ! the consistent mass couples only like coordinates (mass_times): the zero
            ! entries, which would add nothing, are skipped
            do e = 1, m%nel
                ne = 3 * m%el_nen(e)
                do b = 1, ne
                    do a = mod(b - 1, 3) + 1, ne, 3
                        vals(m%map_el(a, b, e)) = vals(m%map_el(a, b, e)) + cm * m%el_mass(a, b, e)
                    end do
                end do
            end do
            do a = 1, m%ndof
                vals(m%map_diag(a)) = vals(m%map_diag(a)) + cm * m%lumped(a)
            end do
        end if
        do i = 1, m%nc
            call constraint_values(m, i, q, t, phi, grad, hess)
            w = ck * (mu(i) + pen * phi)
            do a = 1, MAX_CDOF
                if (m%c_dofs(a, i) <= 0) cycle
                vals(m%map_qc(a, i)) = vals(m%map_qc(a, i)) + kscale * grad(a)
                vals(m%map_cq(a, i)) = vals(m%map_cq(a, i)) + kscale * grad(a)
                do b = 1, MAX_CDOF
                    if (m%c_dofs(b, i) <= 0) cycle
                    vals(m%map_qq(a, b, i)) = vals(m%map_qq(a, b, i)) &
                        + ck * pen * grad(a) * grad(b) + w * hess(a, b)
                end do
            end do
        end do
    end subroutine iteration_matrix

    !> Adds the spring-damper forces f_sd(q, qd) to f; with `vals`, adds ck K + cc C
    !! of every spring-damper at its positions (force_elements.f90).
    subroutine spring_forces(m, q, qd, f, vals, ck, cc)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof)
        real(wp), intent(inout) :: f(m%ndof)
        real(wp), intent(inout), optional :: vals(:)
        real(wp), intent(in), optional :: ck, cc
        real(wp) :: fe(4), ke(4, 4), ce(4, 4)
        integer :: i, a, b
        do i = 1, m%nsd
            if (present(vals)) then
                call spring_damper(m%sd_prop(:, i), q(m%sd_dofs(:, i)), qd(m%sd_dofs(:, i)), fe, ke, ce)
                do b = 1, 4
                    do a = 1, 4
                        vals(m%map_sd(a, b, i)) = vals(m%map_sd(a, b, i)) + ck * ke(a, b) + cc * ce(a, b)
                    end do
                end do
            else
                call spring_damper(m%sd_prop(:, i), q(m%sd_dofs(:, i)), qd(m%sd_dofs(:, i)), fe)
            end if
            do a = 1, 4
                f(m%sd_dofs(a, i)) = f(m%sd_dofs(a, i)) + fe(a)
            end do
        end do
    end subroutine spring_forces

    !> y = (ck K_sd + cc C_sd) x: the spring-damper tangents at (q, qd) times x, matrix-free;
    !! with transposed = .true., y = (ck K_sd + cc C_sd)^T x (the adjoint).
    subroutine spring_times(m, q, qd, x, ck, cc, y, transposed)
        type(mbs_model), intent(in) :: m
        real(wp), intent(in) :: q(m%ndof), qd(m%ndof), x(m%ndof), ck, cc
        real(wp), intent(out) :: y(m%ndof)
        logical, intent(in), optional :: transposed
        real(wp) :: fe(4), ke(4, 4), ce(4, 4), ye(4)
        integer :: i, a
        logical :: tr
        tr = .false.
        if (present(transposed)) tr = transposed
        y = 0
        do i = 1, m%nsd
            call spring_damper(m%sd_prop(:, i), q(m%sd_dofs(:, i)), qd(m%sd_dofs(:, i)), fe, ke, ce)
            if (tr) then
                ye = matmul(transpose(ck * ke + cc * ce), x(m%sd_dofs(:, i)))
            else
                ye = matmul(ck * ke + cc * ce, x(m%sd_dofs(:, i)))
            end if
            do a = 1, 4
                y(m%sd_dofs(a, i)) = y(m%sd_dofs(a, i)) + ye(a)
            end do
        end do
    end subroutine spring_times

end module assembly
