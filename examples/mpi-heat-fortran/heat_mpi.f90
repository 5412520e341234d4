!> Heat diffusion with MPI in Fortran 2008, pushing each rank's brick of the temperature to a
!> generator-node through the insitu Fortran module (client-c/fortran/insitu.f90).
!>
!> The model: an N³ grid of points, temperature 0 everywhere but a centred cube of side N/4
!> at 1, held at 0 outside the grid; explicit diffusion t' = t + 0.1·(sum of the six neighbours
!> − 6·t) per step. Every point is computed with the same operations in the same order
!> whatever the decomposition, so any number of ranks gives the same field as one.
!>
!> Decomposition: MPI_Dims_create over a non-periodic 3-D Cartesian communicator
!> (MPI_Cart_create); each rank owns a block of points and exchanges one halo plane with its
!> six face neighbours before every step. Every EVERY steps each rank pushes its owned points
!> plus the first halo plane on the upper side of each axis where a neighbour follows, so
!> neighbouring bricks share their boundary plane.
!>
!> Usage: mpirun -np P heat_mpi GENERATOR_ADDR N STEPS EVERY
!> The token, if the generator-node needs one, comes from INSITU_TOKEN.
program heat_mpi
  use mpi_f08
  use insitu
  use, intrinsic :: iso_fortran_env, only: real32, real64, error_unit
  implicit none

  type(MPI_Comm) :: cart
  type(insitu_client) :: client
  character(len=256) :: arg, addr
  integer :: n, steps, every, nranks, rank, s, a, status, failed
  integer :: dims(3), coords(3), lo(3), owned(3), brick(3)
  logical :: periods(3) = .false.
  real(real64), allocatable :: t(:, :, :), t2(:, :, :)
  real(real32), allocatable :: field(:, :, :)

  call MPI_Init()
  call MPI_Comm_size(MPI_COMM_WORLD, nranks)
  if (command_argument_count() /= 4) then
    write (error_unit, '(a)') 'usage: heat_mpi GENERATOR_ADDR N STEPS EVERY'
    call MPI_Abort(MPI_COMM_WORLD, 2)
  end if
  call get_command_argument(1, addr)
  call get_command_argument(2, arg); read (arg, *) n
  call get_command_argument(3, arg); read (arg, *) steps
  call get_command_argument(4, arg); read (arg, *) every

  dims = 0
  call MPI_Dims_create(nranks, 3, dims)
  call MPI_Cart_create(MPI_COMM_WORLD, 3, dims, periods, .false., cart)
  call MPI_Comm_rank(cart, rank)
  call MPI_Cart_coords(cart, rank, 3, coords)
  do a = 1, 3
    lo(a) = int(int(coords(a), 8) * n / dims(a))
    owned(a) = int(int(coords(a) + 1, 8) * n / dims(a)) - lo(a)
    brick(a) = owned(a)
    if (coords(a) + 1 < dims(a)) brick(a) = owned(a) + 1
  end do

  ! Owned points 1..owned(a), halo planes 0 and owned(a)+1 (0 outside the grid).
  allocate (t(0:owned(1) + 1, 0:owned(2) + 1, 0:owned(3) + 1), source=0.0_real64)
  call initial(t, lo, n)
  allocate (t2, mold=t)
  t2 = t
  allocate (field(brick(1), brick(2), brick(3)))

  failed = 0
  status = insitu_connect(client, trim(addr))
  if (status /= INSITU_OK) then
    write (error_unit, '(a,i0,a,a)') 'rank ', rank, ': insitu_connect: ', insitu_error()
    failed = 1
  end if
  call MPI_Allreduce(MPI_IN_PLACE, failed, 1, MPI_INTEGER, MPI_MAX, cart)
  do s = 1, steps
    if (failed /= 0) exit
    call exchange(t, cart)
    call diffuse(t, t2)
    if (mod(s, every) == 0) then
      call exchange(t, cart)
      field = real(t(1:brick(1), 1:brick(2), 1:brick(3)), real32)
      status = insitu_push(client, s, real(s, real64), field, [n, n, n], lo, rank, nranks)
      if (status /= INSITU_OK) then
        write (error_unit, '(a,i0,a,a)') 'rank ', rank, ': insitu_push: ', insitu_error()
        failed = 1
      end if
    end if
    ! One rank failing stops all: a simulation would not go on half-observed.
    call MPI_Allreduce(MPI_IN_PLACE, failed, 1, MPI_INTEGER, MPI_MAX, cart)
  end do
  status = insitu_close(client)
  if (status /= INSITU_OK .and. failed == 0) then
    write (error_unit, '(a,i0,a,a)') 'rank ', rank, ': insitu_close: ', insitu_error()
    failed = 1
  end if
  call MPI_Allreduce(MPI_IN_PLACE, failed, 1, MPI_INTEGER, MPI_MAX, cart)
  if (rank == 0 .and. failed == 0) then
    write (*, '(a,i0,a,i0,a,i0,a,i0,a,i0,a,i0,a,i0)') 'heat ', n, '^3, ', nranks, ' ranks (', &
      dims(1), 'x', dims(2), 'x', dims(3), '), ', steps, ' steps: pushed every ', every
  end if
  call MPI_Comm_free(cart)
  call MPI_Finalize()
  if (failed /= 0) error stop 'heat_mpi: a rank failed'

contains

  !> A centred cube of side n/4 at 1.
  subroutine initial(t, lo, n)
    real(real64), intent(inout) :: t(0:, 0:, 0:)
    integer, intent(in) :: lo(3), n
    integer :: i, j, k
    do k = 1, ubound(t, 3) - 1
      do j = 1, ubound(t, 2) - 1
        do i = 1, ubound(t, 1) - 1
          if (inside(lo(1) + i - 1, n) .and. inside(lo(2) + j - 1, n) &
              .and. inside(lo(3) + k - 1, n)) t(i, j, k) = 1.0_real64
        end do
      end do
    end do
  end subroutine initial

  !> Whether grid index `g` (from 0) lies in the hot cube of an n³ grid.
  logical function inside(g, n)
    integer, intent(in) :: g, n
    inside = g >= n / 2 - n / 8 .and. g < n / 2 + n / 8
  end function inside

  !> One explicit step over the owned points; the result replaces t.
  subroutine diffuse(t, t2)
    real(real64), intent(inout) :: t(0:, 0:, 0:), t2(0:, 0:, 0:)
    integer :: i, j, k
    do k = 1, ubound(t, 3) - 1
      do j = 1, ubound(t, 2) - 1
        do i = 1, ubound(t, 1) - 1
          t2(i, j, k) = t(i, j, k) + 0.1_real64 * (((((t(i - 1, j, k) + t(i + 1, j, k)) &
            + t(i, j - 1, k)) + t(i, j + 1, k)) + t(i, j, k - 1)) + t(i, j, k + 1) &
            - 6.0_real64 * t(i, j, k))
        end do
      end do
    end do
    t(1:ubound(t, 1) - 1, 1:ubound(t, 2) - 1, 1:ubound(t, 3) - 1) = &
      t2(1:ubound(t, 1) - 1, 1:ubound(t, 2) - 1, 1:ubound(t, 3) - 1)
  end subroutine diffuse

  !> Fills the halo planes from the face neighbours (left as they are, 0, at the grid's edge).
  subroutine exchange(t, cart)
    real(real64), intent(inout) :: t(0:, 0:, 0:)
    type(MPI_Comm), intent(in) :: cart
    integer :: axis, down, up, m(3), ps(3)
    real(real64), allocatable :: send(:, :, :), recv(:, :, :)
    m = ubound(t) - 1
    do axis = 1, 3
      call MPI_Cart_shift(cart, axis - 1, 1, down, up)
      ps = shape(t)
      ps(axis) = 1
      allocate (send(ps(1), ps(2), ps(3)), recv(ps(1), ps(2), ps(3)))
      ! Up: my last owned plane to the rank above, my lower halo from the rank below.
      send(:, :, :) = plane(t, axis, m(axis))
      call MPI_Sendrecv(send, size(send), MPI_DOUBLE_PRECISION, up, 0, recv, size(recv), &
        MPI_DOUBLE_PRECISION, down, 0, cart, MPI_STATUS_IGNORE)
      if (down /= MPI_PROC_NULL) call put(t, axis, 0, recv)
      ! Down: my first owned plane to the rank below, my upper halo from the rank above.
      send(:, :, :) = plane(t, axis, 1)
      call MPI_Sendrecv(send, size(send), MPI_DOUBLE_PRECISION, down, 1, recv, size(recv), &
        MPI_DOUBLE_PRECISION, up, 1, cart, MPI_STATUS_IGNORE)
      if (up /= MPI_PROC_NULL) call put(t, axis, m(axis) + 1, recv)
      deallocate (send, recv)
    end do
  end subroutine exchange

  !> The plane at index `at` along `axis`, halo included along the other axes.
  function plane(t, axis, at) result(p)
    real(real64), intent(in) :: t(0:, 0:, 0:)
    integer, intent(in) :: axis, at
    real(real64), allocatable :: p(:, :, :)
    select case (axis)
    case (1)
      p = t(at:at, :, :)
    case (2)
      p = t(:, at:at, :)
    case default
      p = t(:, :, at:at)
    end select
  end function plane

  subroutine put(t, axis, at, p)
    real(real64), intent(inout) :: t(0:, 0:, 0:)
    integer, intent(in) :: axis, at
    real(real64), intent(in) :: p(:, :, :)
    select case (axis)
    case (1)
      t(at:at, :, :) = p
    case (2)
      t(:, at:at, :) = p
    case default
      t(:, :, at:at) = p
    end select
  end subroutine put

end program heat_mpi
