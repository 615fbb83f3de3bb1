!> The mechanism as the core sees it: flat arrays built once per design by
!! flexmbs.model (Python), copied into one `mbs_model` value that the caller
!! owns. No module-level state: two models can be simulated side by side.
module model_data
    use flexmbs_kinds, only: wp
    use beam2d, only: beam_mass, beam_reference_strains, MAX_EDOF, MAX_GAUSS
    use constraints, only: MAX_CDOF, CON_LINEAR
    implicit none
    private
    public :: mbs_model, law_value, law_rate, law_accel0

    type :: mbs_model
        integer :: ndof = 0                      !! coordinates (3 per node)
        integer :: nc = 0                        !! constraint rows (multipliers)
        integer :: n = 0                         !! unknowns of the iteration matrix: ndof + nc
        integer :: nel = 0                       !! beam elements
        integer :: nload = 0                     !! time-dependent nodal loads
        integer :: nlaw = 0                      !! tabulated time laws
        integer :: nnz = 0                       !! stored values of the iteration matrix
        real(wp), allocatable :: qref(:)         !! reference (stress-free) configuration
        real(wp), allocatable :: lumped(:)       !! lumped diagonal masses (point masses, inertias)
        real(wp), allocatable :: gacc(:)         !! gravity acceleration per coordinate
        integer, allocatable :: el_nen(:)        !! nodes per element
        integer, allocatable :: el_dofs(:, :)    !! (MAX_EDOF, nel) global coordinate indices
        real(wp), allocatable :: el_len(:)       !! reference lengths
        real(wp), allocatable :: el_prop(:, :)   !! (5, nel): EA, kGA, EI, rhoA, rhoI
        real(wp), allocatable :: el_mass(:, :, :)!! (MAX_EDOF, MAX_EDOF, nel) element mass matrices
        real(wp), allocatable :: el_mass_a(:, :, :) !! element mass matrices per unit rhoA (rhoI = 0)
        real(wp), allocatable :: el_mass_i(:, :, :) !! element mass matrices per unit rhoI (rhoA = 0)
        real(wp), allocatable :: el_eref(:, :, :)   !! (3, MAX_GAUSS, nel) reference strains
        integer, allocatable :: ld_dof(:)        !! loaded coordinate
        integer, allocatable :: ld_law(:)        !! law of the load (0: constant)
        real(wp), allocatable :: ld_amp(:)       !! amplitude of the load
        integer, allocatable :: c_kind(:)        !! CON_* kind of each row
        integer, allocatable :: c_dofs(:, :)     !! (MAX_CDOF, nc) coordinates (0: unused)
        real(wp), allocatable :: c_coef(:, :)    !! (MAX_CDOF, nc) coefficients / offsets
        real(wp), allocatable :: c_c0(:)         !! constant terms
        integer, allocatable :: c_law(:)         !! law of the row (0: none)
        real(wp), allocatable :: c_lawcoef(:)    !! multiplier of the law
        logical :: linear_constraints = .true.   !! all rows CON_LINEAR (constant gradient)
        real(wp) :: law_h = 1.0_wp               !! grid step of the tabulated laws
        real(wp), allocatable :: law_val(:, :)   !! (nlaw, npts) values on the grid
        real(wp), allocatable :: law_der(:, :)   !! (nlaw, npts) first derivatives on the grid
        real(wp), allocatable :: law_dd0(:)      !! second derivatives at t = 0
        integer, allocatable :: map_el(:, :, :)  !! (MAX_EDOF, MAX_EDOF, nel) value positions
        integer, allocatable :: map_diag(:)      !! (ndof) positions of the diagonal
        integer, allocatable :: map_cq(:, :)     !! (MAX_CDOF, nc) positions of (ndof+r, dof)
        integer, allocatable :: map_qc(:, :)     !! (MAX_CDOF, nc) positions of (dof, ndof+r)
        integer, allocatable :: map_qq(:, :, :)  !! (MAX_CDOF, MAX_CDOF, nc) positions of (dof, dof)
        real(wp) :: qscale = 1.0_wp              !! length scale of the convergence test
    end type mbs_model

    public :: model_finish, model_from_arrays

contains

    !> Copy the flat arrays of flexmbs.model into a model value (counts may be 0;
    !! the arrays then have one unused padding entry).
    subroutine model_from_arrays(m, ndof, nc, nel, nload, nlaw, nnz, qref, lumped, gacc, &
                                 el_nen, el_dofs, el_len, el_prop, ld_dof, ld_law, ld_amp, &
                                 c_kind, c_dofs, c_coef, c_c0, c_law, c_lawcoef, &
                                 law_h, law_val, law_der, law_dd0, &
                                 map_el, map_diag, map_cq, map_qc, map_qq)
        type(mbs_model), intent(out) :: m
        integer, intent(in) :: ndof, nc, nel, nload, nlaw, nnz
        real(wp), intent(in) :: qref(:), lumped(:), gacc(:)
        integer, intent(in) :: el_nen(:), el_dofs(:, :)
        real(wp), intent(in) :: el_len(:), el_prop(:, :)
        integer, intent(in) :: ld_dof(:), ld_law(:)
        real(wp), intent(in) :: ld_amp(:)
        integer, intent(in) :: c_kind(:), c_dofs(:, :), c_law(:)
        real(wp), intent(in) :: c_coef(:, :), c_c0(:), c_lawcoef(:)
        real(wp), intent(in) :: law_h, law_val(:, :), law_der(:, :), law_dd0(:)
        integer, intent(in) :: map_el(:, :), map_diag(:), map_cq(:, :), map_qc(:, :), map_qq(:, :)
        integer :: e, r
        m%ndof = ndof
        m%nc = nc
        m%nel = nel
        m%nload = nload
        m%nlaw = nlaw
        m%nnz = nnz
        m%qref = qref(1:ndof)
        m%lumped = lumped(1:ndof)
        m%gacc = gacc(1:ndof)
        m%el_nen = el_nen(1:max(nel, 1))
        m%el_dofs = el_dofs(:, 1:max(nel, 1))
        m%el_len = el_len(1:max(nel, 1))
        m%el_prop = el_prop(:, 1:max(nel, 1))
        allocate (m%map_el(MAX_EDOF, MAX_EDOF, max(nel, 1)))
        do e = 1, max(nel, 1)
            m%map_el(:, :, e) = reshape(map_el(:, e), [MAX_EDOF, MAX_EDOF])
        end do
        m%ld_dof = ld_dof(1:max(nload, 1))
        m%ld_law = ld_law(1:max(nload, 1))
        m%ld_amp = ld_amp(1:max(nload, 1))
        m%c_kind = c_kind(1:max(nc, 1))
        m%c_dofs = c_dofs(:, 1:max(nc, 1))
        m%c_coef = c_coef(:, 1:max(nc, 1))
        m%c_c0 = c_c0(1:max(nc, 1))
        m%c_law = c_law(1:max(nc, 1))
        m%c_lawcoef = c_lawcoef(1:max(nc, 1))
        m%map_diag = map_diag(1:ndof)
        m%map_cq = map_cq(:, 1:max(nc, 1))
        m%map_qc = map_qc(:, 1:max(nc, 1))
        allocate (m%map_qq(MAX_CDOF, MAX_CDOF, max(nc, 1)))
        do r = 1, max(nc, 1)
            m%map_qq(:, :, r) = reshape(map_qq(:, r), [MAX_CDOF, MAX_CDOF])
        end do
        m%law_h = law_h
        m%law_val = law_val
        m%law_der = law_der
        m%law_dd0 = law_dd0
        call model_finish(m)
    end subroutine model_from_arrays

    !> Derived data: element mass matrices, constraint linearity, scales.
    subroutine model_finish(m)
        type(mbs_model), intent(inout) :: m
        integer :: e, ne
        m%n = m%ndof + m%nc
        if (allocated(m%el_mass)) deallocate (m%el_mass, m%el_mass_a, m%el_mass_i)
        allocate (m%el_mass(MAX_EDOF, MAX_EDOF, max(m%nel, 1)), &
                  m%el_mass_a(MAX_EDOF, MAX_EDOF, max(m%nel, 1)), &
                  m%el_mass_i(MAX_EDOF, MAX_EDOF, max(m%nel, 1)))
        m%el_mass_a = 0
        m%el_mass_i = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            call beam_mass(m%el_nen(e), m%el_len(e), 1.0_wp, 0.0_wp, m%el_mass_a(1:ne, 1:ne, e))
            call beam_mass(m%el_nen(e), m%el_len(e), 0.0_wp, 1.0_wp, m%el_mass_i(1:ne, 1:ne, e))
        end do
        if (allocated(m%el_eref)) deallocate (m%el_eref)
        allocate (m%el_eref(3, MAX_GAUSS, max(m%nel, 1)))
        m%el_eref = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            call beam_reference_strains(m%el_nen(e), m%el_len(e), m%qref(m%el_dofs(1:ne, e)), &
                                        m%el_eref(:, :, e))
        end do
        ! the consistent mass is linear in (rhoA, rhoI)
        do e = 1, max(m%nel, 1)
            m%el_mass(:, :, e) = m%el_prop(4, e) * m%el_mass_a(:, :, e) + m%el_prop(5, e) * m%el_mass_i(:, :, e)
        end do
        m%linear_constraints = .true.
        if (m%nc > 0) m%linear_constraints = all(m%c_kind(1:m%nc) == CON_LINEAR)
        m%qscale = max(1.0_wp, maxval(abs(m%qref)))
        if (m%nel > 0) m%qscale = max(m%qscale, maxval(m%el_len(1:m%nel)))
    end subroutine model_finish

    !> Cubic Hermite interpolation of law il at time t (exact on the grid).
    pure function law_value(m, il, t) result(v)
        type(mbs_model), intent(in) :: m
        integer, intent(in) :: il
        real(wp), intent(in) :: t
        real(wp) :: v, s, h00, h10, h01, h11
        integer :: k, npts
        npts = size(m%law_val, 2)
        k = min(max(int(floor(t / m%law_h)), 0), npts - 2)
        s = t / m%law_h - real(k, wp)
        if (abs(s) <= 1.0e-12_wp) then
            v = m%law_val(il, k + 1)
            return
        else if (abs(s - 1.0_wp) <= 1.0e-12_wp) then
            v = m%law_val(il, k + 2)
            return
        end if
        h00 = (1 + 2 * s) * (1 - s)**2
        h10 = s * (1 - s)**2
        h01 = s * s * (3 - 2 * s)
        h11 = s * s * (s - 1)
        v = h00 * m%law_val(il, k + 1) + h10 * m%law_h * m%law_der(il, k + 1) &
            + h01 * m%law_val(il, k + 2) + h11 * m%law_h * m%law_der(il, k + 2)
    end function law_value

    !> First derivative of law il at t = 0.
    pure function law_rate(m, il) result(v)
        type(mbs_model), intent(in) :: m
        integer, intent(in) :: il
        real(wp) :: v
        v = m%law_der(il, 1)
    end function law_rate

    !> Second derivative of law il at t = 0.
    pure function law_accel0(m, il) result(v)
        type(mbs_model), intent(in) :: m
        integer, intent(in) :: il
        real(wp) :: v
        v = m%law_dd0(il)
    end function law_accel0

end module model_data
