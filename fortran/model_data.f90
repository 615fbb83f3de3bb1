!> The mechanism as the core sees it: flat arrays built once per mechanism by
!! flexmbs.model (Python), copied into one `mbs_model` value that the caller
!! owns (flexmbs_api.f90 model_create: behind an opaque handle). A run works on its
!! own copy (model_for_run) with the design's element properties and the time grid's
!! law tables. No module-level state: two models can be simulated side by side.
module model_data
    use iso_c_binding, only: c_int64_t, c_ptr, c_loc, c_f_pointer, c_associated
    use flexmbs_kinds, only: wp
    use beam2d, only: beam_mass, beam_reference_strains, MAX_EDOF, MAX_GAUSS
    use constraints, only: MAX_CDOF, CON_LINEAR
    use force_elements, only: SD_NPROP
    implicit none
    private
    public :: mbs_model, law_value, law_rate, law_accel0

    !> The arrays of the loads, constraints, spring-dampers and value positions are pointers:
    !! those of a run's model (model_for_run) point to the arrays of the model it was made
    !! from, which runs in parallel threads share and only read. The rest is allocatable, each
    !! run's own: the design's element properties and masses, the law tables, and a copy of
    !! the per-element arrays that the element loops of the adjoint and the sensitivities
    !! read, the lumped masses and the constraints' coordinates (read through pointers, they
    !! make the robot's backward pass about 6 % slower).
    type :: mbs_model
        integer :: ndof = 0                      !! coordinates (3 per node)
        integer :: nc = 0                        !! constraint rows (multipliers)
        integer :: n = 0                         !! unknowns of the iteration matrix: ndof + nc
        integer :: nel = 0                       !! beam elements
        integer :: nload = 0                     !! time-dependent nodal loads
        integer :: nlaw = 0                      !! tabulated time laws
        integer :: nnz = 0                       !! stored values of the iteration matrix
        integer :: nsd = 0                       !! spring-dampers (force_elements.f90)
        real(wp), allocatable :: qref(:)         !! reference (stress-free) configuration
        real(wp), allocatable :: lumped(:)       !! lumped diagonal masses (point masses, inertias)
        real(wp), pointer, contiguous :: gacc(:) => null()         !! gravity acceleration per coordinate
        integer, allocatable :: el_nen(:)        !! nodes per element
        integer, allocatable :: el_dofs(:, :)    !! (MAX_EDOF, nel) global coordinate indices
        real(wp), allocatable :: el_len(:)       !! reference lengths
        real(wp), allocatable :: el_prop(:, :)   !! (5, nel): EA, kGA, EI, rhoA, rhoI
        real(wp), allocatable :: el_eta(:)       !! (nel) Kelvin–Voigt time of the material (s)
        logical :: damped = .false.              !! some element has eta > 0 (beam2d.f90)
        real(wp), allocatable :: el_mass(:, :, :)!! (MAX_EDOF, MAX_EDOF, nel) element mass matrices
        real(wp), allocatable :: el_mass_a(:, :, :) !! element mass matrices per unit rhoA (rhoI = 0)
        real(wp), allocatable :: el_mass_i(:, :, :) !! element mass matrices per unit rhoI (rhoA = 0)
        real(wp), allocatable :: el_eref(:, :, :)   !! (3, MAX_GAUSS, nel) reference strains
        integer, pointer, contiguous :: ld_dof(:) => null()        !! loaded coordinate
        integer, pointer, contiguous :: ld_law(:) => null()        !! law of the load (0: constant)
        real(wp), pointer, contiguous :: ld_amp(:) => null()       !! amplitude of the load
        integer, pointer, contiguous :: c_kind(:) => null()        !! CON_* kind of each row
        integer, allocatable :: c_dofs(:, :)     !! (MAX_CDOF, nc) coordinates (0: unused)
        real(wp), pointer, contiguous :: c_coef(:, :) => null()    !! (MAX_CDOF, nc) coefficients / offsets
        real(wp), pointer, contiguous :: c_c0(:) => null()         !! constant terms
        integer, pointer, contiguous :: c_law(:) => null()         !! law of the row (0: none)
        real(wp), pointer, contiguous :: c_lawcoef(:) => null()    !! multiplier of the law
        logical :: linear_constraints = .true.   !! all rows CON_LINEAR (constant gradient)
        real(wp) :: law_h = 1.0_wp               !! grid step of the tabulated laws
        real(wp), allocatable :: law_val(:, :)   !! (nlaw, npts) values on the grid
        real(wp), allocatable :: law_der(:, :)   !! (nlaw, npts) first derivatives on the grid
        real(wp), allocatable :: law_dd0(:)      !! second derivatives at t = 0
        integer, pointer, contiguous :: sd_dofs(:, :) => null()    !! (4, nsd) coordinates x_a, y_a, x_b, y_b
        real(wp), pointer, contiguous :: sd_prop(:, :) => null()   !! (SD_NPROP, nsd) k, c, l0, f0
        integer, pointer, contiguous :: map_sd(:, :, :) => null()  !! (4, 4, nsd) value positions of the spring blocks
        integer, pointer, contiguous :: map_el(:, :, :) => null()  !! (MAX_EDOF, MAX_EDOF, nel) value positions
        integer, pointer, contiguous :: map_diag(:) => null()      !! (ndof) positions of the diagonal
        integer, pointer, contiguous :: map_cq(:, :) => null()     !! (MAX_CDOF, nc) positions of (ndof+r, dof)
        integer, pointer, contiguous :: map_qc(:, :) => null()     !! (MAX_CDOF, nc) positions of (dof, ndof+r)
        integer, pointer, contiguous :: map_qq(:, :, :) => null()  !! (MAX_CDOF, MAX_CDOF, nc) positions of (dof, dof)
        real(wp) :: qscale = 1.0_wp              !! length scale of the convergence test
        !> .true.: the arrays behind the pointers are this model's (model_from_arrays: freed by
        !! model_free); .false.: a run's model (model_for_run), whose pointers share them with
        !! the model it was made from; its allocatable arrays (design, law tables, element
        !! masses) are its own
        logical :: owner = .false.
    end type mbs_model

    public :: model_finish, model_from_arrays, model_free, model_for_run
    public :: model_address, model_at, model_of_run

contains

    !> Copy the flat arrays of flexmbs.model into a model value (counts may be 0;
    !! the arrays then have one unused padding entry). status = 0, or 1 when an
    !! allocation failed: nbytes is then the size asked for, and nothing of m stays
    !! allocated.
    subroutine model_from_arrays(m, ndof, nc, nel, nload, nlaw, nnz, qref, lumped, gacc, &
                                 el_nen, el_dofs, el_len, el_prop, ld_dof, ld_law, ld_amp, &
                                 c_kind, c_dofs, c_coef, c_c0, c_law, c_lawcoef, &
                                 law_h, law_val, law_der, law_dd0, &
                                 map_el, map_diag, map_cq, map_qc, map_qq, status, nbytes, &
                                 nsd, sd_dofs, sd_prop, map_sd, el_eta)
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
        integer, intent(out) :: status           !! 0 ok, 1 out of memory
        real(wp), intent(out) :: nbytes          !! bytes asked for when status = 1
        integer, intent(in), optional :: nsd     !! spring-dampers (0 when absent)
        integer, intent(in), optional :: sd_dofs(:, :), map_sd(:, :)
        real(wp), intent(in), optional :: sd_prop(:, :)
        real(wp), intent(in), optional :: el_eta(:)   !! Kelvin–Voigt times (0 when absent)
        integer :: e, r, ne, nca, nld, ierr, nsa
        m%ndof = ndof
        m%nc = nc
        m%nel = nel
        m%nload = nload
        m%nlaw = nlaw
        m%nnz = nnz
        ne = max(nel, 1)
        nca = max(nc, 1)
        nld = max(nload, 1)
        m%nsd = 0
        if (present(nsd)) m%nsd = nsd
        nsa = max(m%nsd, 1)
        status = 0
        nbytes = 0
        allocate (m%qref(ndof), m%lumped(ndof), m%gacc(ndof), m%map_diag(ndof), &
                  m%el_nen(ne), m%el_dofs(size(el_dofs, 1), ne), m%el_len(ne), &
                  m%el_prop(size(el_prop, 1), ne), m%el_eta(ne), m%map_el(MAX_EDOF, MAX_EDOF, ne), &
                  m%ld_dof(nld), m%ld_law(nld), m%ld_amp(nld), &
                  m%c_kind(nca), m%c_dofs(size(c_dofs, 1), nca), m%c_coef(size(c_coef, 1), nca), &
                  m%c_c0(nca), m%c_law(nca), m%c_lawcoef(nca), &
                  m%map_cq(size(map_cq, 1), nca), m%map_qc(size(map_qc, 1), nca), &
                  m%map_qq(MAX_CDOF, MAX_CDOF, nca), &
                  m%law_val(size(law_val, 1), size(law_val, 2)), &
                  m%law_der(size(law_der, 1), size(law_der, 2)), m%law_dd0(size(law_dd0)), &
                  m%sd_dofs(4, nsa), m%sd_prop(SD_NPROP, nsa), m%map_sd(4, 4, nsa), stat=ierr)
        if (ierr /= 0) then
            nbytes = 8.0_wp * (4.0_wp * ndof + real(ne, wp) * (2 + size(el_dofs, 1) + 1 &
                     + size(el_prop, 1) + MAX_EDOF**2) + 3.0_wp * nld &
                     + real(nca, wp) * (4 + size(c_dofs, 1) + size(c_coef, 1) + 2 * size(map_cq, 1) &
                     + MAX_CDOF**2) + 2.0_wp * size(law_val) + size(law_dd0) &
                     + real(nsa, wp) * (4 + SD_NPROP + 16))
            m%owner = .true.
            call model_free(m)
            status = 1
            return
        end if
        m%owner = .true.
        m%qref = qref(1:ndof)
        m%lumped = lumped(1:ndof)
        m%gacc = gacc(1:ndof)
        m%el_nen = el_nen(1:ne)
        m%el_dofs = el_dofs(:, 1:ne)
        m%el_len = el_len(1:ne)
        m%el_prop = el_prop(:, 1:ne)
        m%el_eta = 0
        if (present(el_eta)) m%el_eta = el_eta(1:ne)
        do e = 1, ne
            m%map_el(:, :, e) = reshape(map_el(:, e), [MAX_EDOF, MAX_EDOF])
        end do
        m%ld_dof = ld_dof(1:nld)
        m%ld_law = ld_law(1:nld)
        m%ld_amp = ld_amp(1:nld)
        m%c_kind = c_kind(1:nca)
        m%c_dofs = c_dofs(:, 1:nca)
        m%c_coef = c_coef(:, 1:nca)
        m%c_c0 = c_c0(1:nca)
        m%c_law = c_law(1:nca)
        m%c_lawcoef = c_lawcoef(1:nca)
        m%map_diag = map_diag(1:ndof)
        m%map_cq = map_cq(:, 1:nca)
        m%map_qc = map_qc(:, 1:nca)
        do r = 1, nca
            m%map_qq(:, :, r) = reshape(map_qq(:, r), [MAX_CDOF, MAX_CDOF])
        end do
        m%law_h = law_h
        m%law_val = law_val
        m%law_der = law_der
        m%law_dd0 = law_dd0
        m%sd_dofs = 1
        m%sd_prop = 0
        m%map_sd = 1
        if (m%nsd > 0) then
            m%sd_dofs = sd_dofs(:, 1:nsa)
            m%sd_prop = sd_prop(:, 1:nsa)
            do r = 1, nsa
                m%map_sd(:, :, r) = reshape(map_sd(:, r), [4, 4])
            end do
        end if
        call model_finish(m, status, nbytes)
        if (status /= 0) call model_free(m)
    end subroutine model_from_arrays

    !> Derived data: element mass matrices, constraint linearity, scales.
    !! status = 1 (nbytes: size asked for) when an allocation failed.
    subroutine model_finish(m, status, nbytes)
        type(mbs_model), intent(inout) :: m
        integer, intent(out) :: status
        real(wp), intent(out) :: nbytes
        integer :: e, ne, ierr
        status = 0
        nbytes = 0
        m%n = m%ndof + m%nc
        if (allocated(m%el_mass)) deallocate (m%el_mass)
        if (allocated(m%el_mass_a)) deallocate (m%el_mass_a)
        if (allocated(m%el_mass_i)) deallocate (m%el_mass_i)
        if (allocated(m%el_eref)) deallocate (m%el_eref)
        allocate (m%el_mass(MAX_EDOF, MAX_EDOF, max(m%nel, 1)), &
                  m%el_mass_a(MAX_EDOF, MAX_EDOF, max(m%nel, 1)), &
                  m%el_mass_i(MAX_EDOF, MAX_EDOF, max(m%nel, 1)), &
                  m%el_eref(3, MAX_GAUSS, max(m%nel, 1)), stat=ierr)
        if (ierr /= 0) then
            nbytes = 8.0_wp * real(max(m%nel, 1), wp) * (3 * MAX_EDOF**2 + 3 * MAX_GAUSS)
            if (allocated(m%el_mass)) deallocate (m%el_mass)
            status = 1
            return
        end if
        m%el_mass_a = 0
        m%el_mass_i = 0
        do e = 1, m%nel
            ne = 3 * m%el_nen(e)
            call beam_mass(m%el_nen(e), m%el_len(e), 1.0_wp, 0.0_wp, m%el_mass_a(1:ne, 1:ne, e))
            call beam_mass(m%el_nen(e), m%el_len(e), 0.0_wp, 1.0_wp, m%el_mass_i(1:ne, 1:ne, e))
        end do
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
        m%damped = .false.
        if (m%nel > 0 .and. allocated(m%el_eta)) m%damped = any(m%el_eta(1:m%nel) /= 0)
        m%linear_constraints = .true.
        if (m%nc > 0) m%linear_constraints = all(m%c_kind(1:m%nc) == CON_LINEAR)
        m%qscale = max(1.0_wp, maxval(abs(m%qref)))
        if (m%nel > 0) m%qscale = max(m%qscale, maxval(m%el_len(1:m%nel)))
    end subroutine model_finish

    !> The model of one run: `base` (a model_from_arrays model, read only here: runs in
    !! parallel threads share it; its pointer arrays are pointed to, its per-element arrays
    !! copied) with its own design's
    !! element properties el_prop (5, >= nel), element mass matrices (those of model_finish,
    !! linear in rhoA, rhoI) and the law tables of the run's time grid. status = 0, or 1 when
    !! an allocation failed (nbytes: the size asked for; nothing of m stays allocated).
    subroutine model_for_run(m, base, el_prop, law_h, law_val, law_der, law_dd0, status, nbytes)
        type(mbs_model), intent(out) :: m
        type(mbs_model), intent(in) :: base
        real(wp), intent(in) :: el_prop(:, :)
        real(wp), intent(in) :: law_h, law_val(:, :), law_der(:, :), law_dd0(:)
        integer, intent(out) :: status           !! 0 ok, 1 out of memory
        real(wp), intent(out) :: nbytes          !! bytes asked for when status = 1
        integer :: e, ne, ierr
        ne = size(base%el_nen)
        status = 0
        nbytes = 0
        allocate (m%el_prop(size(base%el_prop, 1), ne), m%el_mass(MAX_EDOF, MAX_EDOF, ne), &
                  m%qref(base%ndof), m%lumped(base%ndof), m%c_dofs(size(base%c_dofs, 1), size(base%c_dofs, 2)), &
                  m%el_nen(ne), m%el_dofs(size(base%el_dofs, 1), ne), &
                  m%el_len(ne), m%el_eta(ne), m%el_mass_a(MAX_EDOF, MAX_EDOF, ne), &
                  m%el_mass_i(MAX_EDOF, MAX_EDOF, ne), m%el_eref(3, MAX_GAUSS, ne), &
                  m%law_val(size(law_val, 1), size(law_val, 2)), &
                  m%law_der(size(law_der, 1), size(law_der, 2)), m%law_dd0(size(law_dd0)), stat=ierr)
        if (ierr /= 0) then
            nbytes = 8.0_wp * (real(ne, wp) * (size(base%el_prop, 1) + 3 * MAX_EDOF**2 + 3 &
                     + size(base%el_dofs, 1) + 3 * MAX_GAUSS) + 2.0_wp * base%ndof + size(base%c_dofs) &
                     + 2.0_wp * size(law_val) + size(law_dd0))
            call model_free(m)
            status = 1
            return
        end if
        m%owner = .false.
        m%ndof = base%ndof
        m%nc = base%nc
        m%n = base%n
        m%nel = base%nel
        m%nload = base%nload
        m%nlaw = base%nlaw
        m%nnz = base%nnz
        m%nsd = base%nsd
        m%damped = base%damped
        m%linear_constraints = base%linear_constraints
        m%qscale = base%qscale
        m%gacc => base%gacc
        m%ld_dof => base%ld_dof
        m%ld_law => base%ld_law
        m%ld_amp => base%ld_amp
        m%c_kind => base%c_kind
        m%c_coef => base%c_coef
        m%c_c0 => base%c_c0
        m%c_law => base%c_law
        m%c_lawcoef => base%c_lawcoef
        m%sd_dofs => base%sd_dofs
        m%sd_prop => base%sd_prop
        m%map_sd => base%map_sd
        m%map_el => base%map_el
        m%map_diag => base%map_diag
        m%map_cq => base%map_cq
        m%map_qc => base%map_qc
        m%map_qq => base%map_qq
        m%qref = base%qref
        m%lumped = base%lumped
        m%c_dofs = base%c_dofs
        m%el_nen = base%el_nen
        m%el_dofs = base%el_dofs
        m%el_len = base%el_len
        m%el_eta = base%el_eta
        m%el_mass_a = base%el_mass_a
        m%el_mass_i = base%el_mass_i
        m%el_eref = base%el_eref
        m%el_prop = el_prop(:, 1:ne)
        m%law_h = law_h
        m%law_val = law_val
        m%law_der = law_der
        m%law_dd0 = law_dd0
        ! the consistent mass is linear in (rhoA, rhoI), as in model_finish
        do e = 1, ne
            m%el_mass(:, :, e) = m%el_prop(4, e) * m%el_mass_a(:, :, e) + m%el_prop(5, e) * m%el_mass_i(:, :, e)
        end do
    end subroutine model_for_run

    !> The opaque address of a model allocated by the caller (flexmbs_api.f90 model_create),
    !! as a 64-bit integer for Python to hold; model_at turns it back into the model.
    function model_address(p) result(handle)
        type(mbs_model), pointer, intent(in) :: p
        integer(c_int64_t) :: handle
        handle = transfer(c_loc(p), handle)
    end function model_address

    !> The model at an address from model_address (null for 0).
    function model_at(handle) result(p)
        integer(c_int64_t), intent(in) :: handle
        type(mbs_model), pointer :: p
        type(c_ptr) :: cp
        p => null()
        if (handle == 0) return
        cp = transfer(handle, cp)
        if (c_associated(cp)) call c_f_pointer(cp, p)
    end function model_at

    !> The model of one run of the model at `handle` (model_for_run; the handle's model is
    !! only read). The caller's extents are checked against it: ndof coordinates, nca
    !! multiplier rows (max(nc, 1)), at least max(nel, 1) element columns of el_prop (5 rows),
    !! at least max(nlaw, 1) law rows on at least 2 grid points. status 0 ok, 1 out of
    !! memory (nbytes: the size asked for), 2 a null handle or extents of another model.
    subroutine model_of_run(m, handle, ndof, nca, el_prop, law_h, law_val, law_der, law_dd0, &
                            status, nbytes)
        type(mbs_model), intent(out) :: m
        integer(c_int64_t), intent(in) :: handle
        integer, intent(in) :: ndof, nca
        real(wp), intent(in) :: el_prop(:, :)
        real(wp), intent(in) :: law_h, law_val(:, :), law_der(:, :), law_dd0(:)
        integer, intent(out) :: status
        real(wp), intent(out) :: nbytes
        type(mbs_model), pointer :: base
        nbytes = 0
        status = 2
        base => model_at(handle)
        if (.not. associated(base)) return
        if (ndof /= base%ndof .or. nca /= size(base%c_kind) .or. size(el_prop, 1) /= 5 &
            .or. size(el_prop, 2) < size(base%el_nen) .or. size(law_val, 1) < max(base%nlaw, 1) &
            .or. size(law_val, 2) < 2 .or. any(shape(law_der) /= shape(law_val)) &
            .or. size(law_dd0) /= size(law_val, 1)) return
        call model_for_run(m, base, el_prop, law_h, law_val, law_der, law_dd0, status, nbytes)
    end subroutine model_of_run

    !> Release every array of a model (safe on a partly allocated one); a run's model
    !! (model_for_run) releases its own arrays only.
    subroutine model_free(m)
        type(mbs_model), intent(inout) :: m
        type(mbs_model) :: empty
        if (m%owner) then
            if (associated(m%gacc)) deallocate (m%gacc)
            if (associated(m%ld_dof)) deallocate (m%ld_dof)
            if (associated(m%ld_law)) deallocate (m%ld_law)
            if (associated(m%ld_amp)) deallocate (m%ld_amp)
            if (associated(m%c_kind)) deallocate (m%c_kind)
            if (associated(m%c_coef)) deallocate (m%c_coef)
            if (associated(m%c_c0)) deallocate (m%c_c0)
            if (associated(m%c_law)) deallocate (m%c_law)
            if (associated(m%c_lawcoef)) deallocate (m%c_lawcoef)
            if (associated(m%sd_dofs)) deallocate (m%sd_dofs)
            if (associated(m%sd_prop)) deallocate (m%sd_prop)
            if (associated(m%map_sd)) deallocate (m%map_sd)
            if (associated(m%map_el)) deallocate (m%map_el)
            if (associated(m%map_diag)) deallocate (m%map_diag)
            if (associated(m%map_cq)) deallocate (m%map_cq)
            if (associated(m%map_qc)) deallocate (m%map_qc)
            if (associated(m%map_qq)) deallocate (m%map_qq)
        end if
        m = empty
    end subroutine model_free

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
