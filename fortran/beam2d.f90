!> Pure kernels of the planar geometrically exact (Simo–Reissner) beam with
!! absolute nodal coordinates (x, y, phi) per node, after Géradin & Cardona,
!! "Flexible Multibody Dynamics: A Finite Element Approach" (2001), ch. 6–7.
!!
!! Element nodes are ordered along the beam: 2-node (linear) or 3-node
!! (quadratic, middle node second) Lagrange interpolation of x, y and phi on
!! xi in [-1, 1], arc length s = (xi + 1) L / 2.
!!
!! Strains (rotation R(phi) of the cross section, x' = dx/ds):
!!   Gamma_1 = cos(phi) x' + sin(phi) y' - 1      (axial)
!!   Gamma_2 = -sin(phi) x' + cos(phi) y'         (shear)
!!   kappa   = phi'                               (curvature)
!! measured from the strains of the reference configuration, so any initial
!! (straight or not) element is stress free there. Stress resultants
!! N = EA Gamma_1, Q = kGA Gamma_2, M = EI kappa. Internal forces and the exact
!! tangent use reduced Gauss integration (1 point for 2 nodes, 2 points for 3
!! nodes: no shear locking, no spurious zero-energy mode); the consistent mass
!! with rotary inertia is integrated exactly. In the planar case the mass
!! matrix is constant (no complementary inertia forces in g of eq. (1)).
!!
!! Kelvin–Voigt material damping (docs/case-format.md, materials): with the retardation
!! time eta (s) of the material, every resultant gets a viscous part proportional to the
!! rate of its strain, [N Q M] = D (Gamma + eta Gamma_dot), D = diag(EA, kGA, EI). The
!! strain rates are Gamma_dot = B(q) qd (B = dGamma/dq), so the forces are
!!   f = int B^T D (Gamma + eta B qd) ds
!! and their tangents
!!   df/dq  = int B^T D B + (N d2Gamma_1 + Q d2Gamma_2)                  (total N, Q)
!!            + eta B^T D (d2Gamma qd)                     (not symmetric)
!!   df/dqd = eta int B^T D B                              (C_t of eq. (7))
!! with d2Gamma_j the Hessians of the strains (kappa is linear in q). A rigid motion
!! leaves the strains unchanged, so it is not damped; qd = 0 (statics) has no viscous
!! force.
module beam2d
    use flexmbs_kinds, only: wp
    implicit none
    private
    public :: beam_internal_forces, beam_forces, beam_mass, beam_reference_strains, MAX_EDOF, MAX_GAUSS

    integer, parameter :: MAX_NEN = 3            !! nodes per element at most
    integer, parameter :: MAX_EDOF = 3 * MAX_NEN !! element dofs at most
    integer, parameter :: MAX_GAUSS = 2          !! Gauss points of the stiffness at most

contains

    !> Shape functions and their xi-derivatives at xi.
    pure subroutine shape(nen, xi, n, dn)
        integer, intent(in) :: nen       !! 2 or 3 nodes
        real(wp), intent(in) :: xi       !! natural coordinate
        real(wp), intent(out) :: n(MAX_NEN)  !! shape functions (1:nen)
        real(wp), intent(out) :: dn(MAX_NEN) !! dN/dxi (1:nen)
        ! (fixed-size arrays throughout the kernels: no automatic arrays, so the compiler
        ! inlines and unrolls the small helpers; the operations are those of nen-sized ones)
        n = 0
        dn = 0
        if (nen == 2) then
            n(1:2) = [0.5_wp * (1.0_wp - xi), 0.5_wp * (1.0_wp + xi)]
            dn(1:2) = [-0.5_wp, 0.5_wp]
        else
            n = [0.5_wp * xi * (xi - 1.0_wp), 1.0_wp - xi * xi, 0.5_wp * xi * (xi + 1.0_wp)]
            dn = [xi - 0.5_wp, -2.0_wp * xi, xi + 0.5_wp]
        end if
    end subroutine shape

    !> Interpolated x', y', phi' (dns: shape-function derivatives d/ds) and phi of nodal
    !! values v = (x, y, phi per node), or of their rates when v are velocities.
    pure subroutine along(nen, v, dns, n, dx, dy, dphi, phi)
        integer, intent(in) :: nen
        real(wp), intent(in) :: v(3 * nen), dns(MAX_NEN), n(MAX_NEN)
        real(wp), intent(out) :: dx, dy, dphi, phi
        integer :: a
        dx = 0; dy = 0; dphi = 0; phi = 0
        do a = 1, nen
            dx = dx + dns(a) * v(3 * a - 2)
            dy = dy + dns(a) * v(3 * a - 1)
            dphi = dphi + dns(a) * v(3 * a)
            phi = phi + n(a) * v(3 * a)
        end do
    end subroutine along

    !> Raw strain measures e1 = c x' + s y', e2 = -s x' + c y', kappa = phi', with
    !! c = cos(phi), s = sin(phi) of the interpolated rotation (returned for reuse).
    pure subroutine raw_strains(nen, qe, dns, n, e1, e2, kap, c, s)
        integer, intent(in) :: nen
        real(wp), intent(in) :: qe(3 * nen), dns(MAX_NEN), n(MAX_NEN)
        real(wp), intent(out) :: e1, e2, kap, c, s
        real(wp) :: phi, dx, dy
        call along(nen, qe, dns, n, dx, dy, kap, phi)
        c = cos(phi)
        s = sin(phi)
        e1 = c * dx + s * dy
        e2 = -s * dx + c * dy
    end subroutine raw_strains

    !> Gauss points and weights of the reduced integration of the stiffness.
    pure subroutine stiffness_gauss(nen, ng, xg, wg)
        integer, intent(in) :: nen
        integer, intent(out) :: ng
        real(wp), intent(out) :: xg(MAX_GAUSS), wg(MAX_GAUSS)
        if (nen == 2) then
            ng = 1
            xg = 0.0_wp
            wg = [2.0_wp, 0.0_wp]
        else
            ng = 2
            xg = [-1.0_wp / sqrt(3.0_wp), 1.0_wp / sqrt(3.0_wp)]
            wg = [1.0_wp, 1.0_wp]
        end if
    end subroutine stiffness_gauss

    !> Strains (e1, e2, kappa) of the reference configuration at the Gauss points,
    !! computed once per model (the stress-free state of beam_internal_forces).
    pure subroutine beam_reference_strains(nen, elen, qref, eref)
        integer, intent(in) :: nen                     !! nodes of the element (2 or 3)
        real(wp), intent(in) :: elen                   !! reference length L
        real(wp), intent(in) :: qref(3 * nen)          !! reference coordinates
        real(wp), intent(out) :: eref(3, MAX_GAUSS)    !! reference raw strains per Gauss point
        real(wp) :: xg(MAX_GAUSS), wg(MAX_GAUSS), n(MAX_NEN), dn(MAX_NEN), c, s
        integer :: ig, ng
        call stiffness_gauss(nen, ng, xg, wg)
        eref = 0
        do ig = 1, ng
            call shape(nen, xg(ig), n, dn)
            call raw_strains(nen, qref, dn / (0.5_wp * elen), n, eref(1, ig), eref(2, ig), &
                             eref(3, ig), c, s)
        end do
    end subroutine beam_reference_strains

    !> Internal force vector (and its exact tangent) of one beam element.
    !!
    !! With `parts` present, the forces are returned per unit stiffness as well:
    !! parts(:, 1) for EA = 1, parts(:, 2) for kGA = 1, parts(:, 3) for EI = 1,
    !! so that fe = EA parts(:,1) + kGA parts(:,2) + EI parts(:,3) (the forces
    !! are linear in the section stiffnesses, their viscous part too; used by the
    !! design sensitivities).
    !!
    !! With `eta` (Kelvin–Voigt time, s) and the velocities `qde`, the viscous forces
    !! (module header) are included in fe, ke and parts; `ce` = d fe / d qde needs `eta`
    !! only (it does not depend on the velocities).
    pure subroutine beam_internal_forces(nen, elen, stiff, qref, qe, fe, ke, parts, eref, eta, &
                                         qde, ce)
        integer, intent(in) :: nen                   !! nodes of the element (2 or 3)
        real(wp), intent(in) :: elen                 !! reference length L
        real(wp), intent(in) :: stiff(3)             !! EA, kGA, EI
        real(wp), intent(in) :: qref(3 * nen)        !! reference (stress-free) coordinates
        real(wp), intent(in) :: qe(3 * nen)          !! current coordinates
        real(wp), intent(out) :: fe(3 * nen)         !! internal forces
        real(wp), intent(out), optional :: ke(3 * nen, 3 * nen)    !! tangent d fe / d qe
        real(wp), intent(out), optional :: parts(3 * nen, 3)       !! forces per unit stiffness
        real(wp), intent(in), optional :: eref(3, MAX_GAUSS)       !! reference strains (else from qref)
        real(wp), intent(in), optional :: eta                      !! Kelvin–Voigt time (s)
        real(wp), intent(in), optional :: qde(3 * nen)             !! current velocities
        real(wp), intent(out), optional :: ce(3 * nen, 3 * nen)    !! damping d fe / d qde
        real(wp) :: xg(MAX_GAUSS), wg(MAX_GAUSS), n(MAX_NEN), dn(MAX_NEN), dns(MAX_NEN), jac, w
        real(wp) :: e1, e2, kap, r1, r2, rk
        real(wp) :: g1, g2, gk, nf, qf, mf, c, s, ev
        real(wp) :: gd(3), xd, yd, phd, hq(2, MAX_EDOF)
        real(wp) :: b(3, MAX_EDOF), db(3, MAX_EDOF)
        integer :: ig, ng, a, bb, ia, ib, j, ne
        logical :: visc
        ev = 0
        if (present(eta)) ev = eta
        visc = ev /= 0 .and. present(qde)
        ne = 3 * nen
        call stiffness_gauss(nen, ng, xg, wg)
        jac = 0.5_wp * elen
        fe = 0
        gd = 0
        if (present(ke)) ke = 0
        if (present(parts)) parts = 0
        if (present(ce)) ce = 0
        do ig = 1, ng
            call shape(nen, xg(ig), n, dn)
            dns = dn / jac
            w = wg(ig) * jac
            if (present(eref)) then
                r1 = eref(1, ig)
                r2 = eref(2, ig)
                rk = eref(3, ig)
            else
                call raw_strains(nen, qref, dns, n, r1, r2, rk, c, s)
            end if
            call raw_strains(nen, qe, dns, n, e1, e2, kap, c, s)
            ! strains measured from the reference configuration
            g1 = e1 - r1
            g2 = e2 - r2
            gk = kap - rk
            if (visc) then
                ! strain rates Gamma_dot = B qd from x'_dot, y'_dot, kappa_dot, phi_dot
                call along(nen, qde, dns, n, xd, yd, gd(3), phd)
                gd(1) = c * xd + s * yd + e2 * phd
                gd(2) = -s * xd + c * yd - e1 * phd
            end if
            ! total (elastic + viscous) stress resultants
            nf = stiff(1) * (g1 + ev * gd(1))
            qf = stiff(2) * (g2 + ev * gd(2))
            mf = stiff(3) * (gk + ev * gd(3))
            ! B = d(Gamma_1, Gamma_2, kappa)/d qe
            do a = 1, nen
                ia = 3 * (a - 1)
                b(1, ia + 1:ia + 3) = [dns(a) * c, dns(a) * s, n(a) * e2]
                b(2, ia + 1:ia + 3) = [-dns(a) * s, dns(a) * c, -n(a) * e1]
                b(3, ia + 1:ia + 3) = [0.0_wp, 0.0_wp, dns(a)]
            end do
            fe = fe + w * (nf * b(1, 1:ne) + qf * b(2, 1:ne) + mf * b(3, 1:ne))
            if (present(parts)) then
                parts(:, 1) = parts(:, 1) + w * (g1 + ev * gd(1)) * b(1, 1:ne)
                parts(:, 2) = parts(:, 2) + w * (g2 + ev * gd(2)) * b(2, 1:ne)
                parts(:, 3) = parts(:, 3) + w * (gk + ev * gd(3)) * b(3, 1:ne)
            end if
            if (present(ke) .or. present(ce)) then
                ! (explicit loops: matmul(transpose(b), db) made a temporary per Gauss point)
                do j = 1, 3
                    db(j, 1:ne) = w * stiff(j) * b(j, 1:ne)
                end do
            end if
            if (present(ce) .and. ev /= 0) then
                ! damping eta B^T D B
                do ib = 1, 3 * nen
                    do ia = 1, 3 * nen
                        ce(ia, ib) = ce(ia, ib) + ev * (b(1, ia) * db(1, ib) + b(2, ia) * db(2, ib) &
                                                        + b(3, ia) * db(3, ib))
                    end do
                end do
            end if
            if (present(ke)) then
                ! material part B^T D B; the curvature row of B is zero in the x and y
                ! columns, so its term is added to the (phi, phi) entries alone (after the
                ! other two, as in the full sum: the other entries would add exact zeros)
                do ib = 1, 3 * nen
                    do ia = 1, 3 * nen
                        ke(ia, ib) = ke(ia, ib) + b(1, ia) * db(1, ib) + b(2, ia) * db(2, ib)
                    end do
                end do
                do ib = 3, 3 * nen, 3
                    do ia = 3, 3 * nen, 3
                        ke(ia, ib) = ke(ia, ib) + b(3, ia) * db(3, ib)
                    end do
                end do
                ! geometric part N d2Gamma_1 + Q d2Gamma_2
                do a = 1, nen
                    ia = 3 * (a - 1)
                    do bb = 1, nen
                        ib = 3 * (bb - 1)
                        ! (phi_a, x_b) and (phi_a, y_b), with their symmetric terms
                        ke(ia + 3, ib + 1) = ke(ia + 3, ib + 1) + w * n(a) * dns(bb) * (-nf * s - qf * c)
                        ke(ia + 3, ib + 2) = ke(ia + 3, ib + 2) + w * n(a) * dns(bb) * (nf * c - qf * s)
                        ke(ib + 1, ia + 3) = ke(ib + 1, ia + 3) + w * n(a) * dns(bb) * (-nf * s - qf * c)
                        ke(ib + 2, ia + 3) = ke(ib + 2, ia + 3) + w * n(a) * dns(bb) * (nf * c - qf * s)
                        ! (phi_a, phi_b)
                        ke(ia + 3, ib + 3) = ke(ia + 3, ib + 3) - w * n(a) * n(bb) * (nf * e1 + qf * e2)
                    end do
                end do
                if (visc) then
                    ! viscous part eta B^T D (d2Gamma qd): hq(j, :) = d(Gamma_dot_j)/dq at fixed qd
                    do a = 1, nen
                        ia = 3 * (a - 1)
                        hq(1, ia + 1:ia + 3) = [-dns(a) * s * phd, dns(a) * c * phd, &
                                                n(a) * (-s * xd + c * yd - e1 * phd)]
                        hq(2, ia + 1:ia + 3) = [-dns(a) * c * phd, -dns(a) * s * phd, &
                                                n(a) * (-c * xd - s * yd - e2 * phd)]
                    end do
                    do ib = 1, 3 * nen
                        do ia = 1, 3 * nen
                            ke(ia, ib) = ke(ia, ib) + ev * (db(1, ia) * hq(1, ib) + db(2, ia) * hq(2, ib))
                        end do
                    end do
                end if
            end if
        end do
    end subroutine beam_internal_forces

    !> Internal force vector of one element alone (no tangent): the fe of
    !! beam_internal_forces with reference strains `eref`, Kelvin–Voigt time `eta` and
    !! velocities `qde` (eta = 0: elastic, qde not read), in fewer operations (B never
    !! formed, no optional arguments). The residual-only path of modified Newton. The
    !! strains come from the same `shape` and `raw_strains` as the reference strains:
    !! exactly zero in the reference configuration (stress free).
    pure subroutine beam_forces(nen, elen, stiff, eref, qe, fe, eta, qde)
        integer, intent(in) :: nen                   !! nodes of the element (2 or 3)
        real(wp), intent(in) :: elen                 !! reference length L
        real(wp), intent(in) :: stiff(3)             !! EA, kGA, EI
        real(wp), intent(in) :: eref(3, MAX_GAUSS)   !! reference strains (beam_reference_strains)
        real(wp), intent(in) :: qe(3 * nen)          !! current coordinates
        real(wp), intent(out) :: fe(3 * nen)         !! internal forces
        real(wp), intent(in) :: eta                  !! Kelvin–Voigt time (s)
        real(wp), intent(in) :: qde(3 * nen)         !! current velocities (read when eta /= 0)
        real(wp) :: xg(MAX_GAUSS), wg(MAX_GAUSS), n(MAX_NEN), dn(MAX_NEN), dns(MAX_NEN), jac, w
        real(wp) :: e1, e2, kap, c, s, nf, qf, mf, fx, fy, fp, xd, yd, kd, phd, dx, dy, phi
        integer :: ig, ng, a
        call stiffness_gauss(nen, ng, xg, wg)
        jac = 0.5_wp * elen
        fe = 0
        do ig = 1, ng
            call shape(nen, xg(ig), n, dn)
            dns = dn / jac
            w = wg(ig) * jac
            ! raw_strains' operations, with `along` (inlined; a call of raw_strains per
            ! Gauss point was ~4 % of a simulation's samples at 128 elements per arm)
            call along(nen, qe, dns, n, dx, dy, kap, phi)
            c = cos(phi)
            s = sin(phi)
            e1 = c * dx + s * dy
            e2 = -s * dx + c * dy
            nf = e1 - eref(1, ig)
            qf = e2 - eref(2, ig)
            mf = kap - eref(3, ig)
            if (eta /= 0) then
                ! strains plus eta times their rates B qd (beam_internal_forces)
                call along(nen, qde, dns, n, xd, yd, kd, phd)
                nf = nf + eta * (c * xd + s * yd + e2 * phd)
                qf = qf + eta * (-s * xd + c * yd - e1 * phd)
                mf = mf + eta * kd
            end if
            nf = w * stiff(1) * nf
            qf = w * stiff(2) * qf
            mf = w * stiff(3) * mf
            ! w B^T [N Q M]: B rows (d Gamma_1, d Gamma_2, d kappa)/d qe as in beam_internal_forces
            fx = nf * c - qf * s
            fy = nf * s + qf * c
            fp = nf * e2 - qf * e1
            do a = 1, nen
                fe(3 * a - 2) = fe(3 * a - 2) + dns(a) * fx
                fe(3 * a - 1) = fe(3 * a - 1) + dns(a) * fy
                fe(3 * a) = fe(3 * a) + n(a) * fp + dns(a) * mf
            end do
        end do
    end subroutine beam_forces

    !> Consistent mass matrix with rotary inertia, exact Gauss integration.
    pure subroutine beam_mass(nen, elen, rho_a, rho_i, me)
        integer, intent(in) :: nen                      !! nodes of the element (2 or 3)
        real(wp), intent(in) :: elen                    !! reference length L
        real(wp), intent(in) :: rho_a                   !! mass per unit length
        real(wp), intent(in) :: rho_i                   !! rotary inertia per unit length
        real(wp), intent(out) :: me(3 * nen, 3 * nen)   !! mass matrix
        real(wp) :: xg(3), wg(3), n(MAX_NEN), dn(MAX_NEN), w
        integer :: ig, a, bb
        xg = [-sqrt(0.6_wp), 0.0_wp, sqrt(0.6_wp)]
        wg = [5.0_wp / 9.0_wp, 8.0_wp / 9.0_wp, 5.0_wp / 9.0_wp]
        me = 0
        do ig = 1, 3
            call shape(nen, xg(ig), n, dn)
            w = wg(ig) * 0.5_wp * elen
            do a = 1, nen
                do bb = 1, nen
                    me(3 * a - 2, 3 * bb - 2) = me(3 * a - 2, 3 * bb - 2) + w * rho_a * n(a) * n(bb)
                    me(3 * a - 1, 3 * bb - 1) = me(3 * a - 1, 3 * bb - 1) + w * rho_a * n(a) * n(bb)
                    me(3 * a, 3 * bb) = me(3 * a, 3 * bb) + w * rho_i * n(a) * n(bb)
                end do
            end do
        end do
    end subroutine beam_mass

end module beam2d
