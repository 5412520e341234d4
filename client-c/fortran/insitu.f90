!> The insitu simulation client for Fortran: the module `insitu`, iso_c_binding interfaces over
!> the C library (libinsitu, client-c/include/insitu.h) and no runtime of its own.
!>
!>     use insitu
!>     type(insitu_client) :: c
!>     real(c_float), allocatable :: t(:, :, :)          ! t(nx, ny, nz): x fastest, as pushed
!>     if (insitu_connect(c, "127.0.0.1:50051") /= INSITU_OK) print *, insitu_error()
!>     ierr = insitu_push(c, step, time, t, global_dims, offset, rank, nranks)
!>     ierr = insitu_close(c)
!>
!> Build: `gfortran -c client-c/fortran/insitu.f90` (writes insitu.mod), then link your program
!> with target/release/libinsitu.a -lpthread -ldl -lm (or -linsitu).
!>
!> Every function returns a status (INSITU_OK, or INSITU_INVALID_ARGUMENT, INSITU_UNREACHABLE,
!> INSITU_REFUSED, INSITU_TIMEOUT, INSITU_INTERNAL); on anything but INSITU_OK, insitu_error()
!> says why. Dims and offsets are (x, y, z) and count grid points, offsets from 0 as in the C
!> API: a rank's brick is field(1:nx, 1:ny, 1:nz) of a Fortran array, which is x fastest in
!> memory, so a contiguous array is sent as it is. Bricks share their boundary planes (where a
!> neighbouring rank follows along an axis, the brick repeats that neighbour's first plane) or
!> split the points without overlap, as one splits an array.
module insitu
  use, intrinsic :: iso_c_binding
  use, intrinsic :: iso_fortran_env, only: real32, real64
  implicit none
  private

  public :: insitu_client, insitu_connect, insitu_push, insitu_flush, insitu_close, insitu_error
  public :: c_float, c_double

  integer, parameter, public :: INSITU_OK = 0
  integer, parameter, public :: INSITU_INVALID_ARGUMENT = 1
  integer, parameter, public :: INSITU_UNREACHABLE = 2
  integer, parameter, public :: INSITU_REFUSED = 3
  integer, parameter, public :: INSITU_TIMEOUT = 4
  integer, parameter, public :: INSITU_INTERNAL = 5

  integer(c_int32_t), parameter :: DTYPE_F32 = 4, DTYPE_F64 = 5

  !> A connection to one generator-node; null until insitu_connect, and again after
  !> insitu_close (a call on it then returns INSITU_INVALID_ARGUMENT).
  type :: insitu_client
    private
    type(c_ptr) :: handle = c_null_ptr
  end type insitu_client

  !> Pushes one rank's brick, a real32 or real64 array field(nx, ny, nz).
  interface insitu_push
    module procedure push_real32, push_real64
  end interface insitu_push

  !> The message of the last failed call (Fortran's own checks, else the C library's).
  character(len=:), allocatable, save :: message

  interface
    integer(c_int) function c_connect(addr, token, out) bind(C, name="insitu_connect")
      import :: c_int, c_char, c_ptr
      character(kind=c_char), dimension(*), intent(in) :: addr
      type(c_ptr), value :: token
      type(c_ptr), intent(out) :: out
    end function c_connect

    integer(c_int) function c_push_step(c, step, sim_time, data, data_bytes, dtype, &
        global_dims, brick_offset, brick_dims, spacing, rank, world_size, out) &
        bind(C, name="insitu_push_step")
      import :: c_int, c_ptr, c_int64_t, c_double, c_size_t, c_int32_t, c_float
      type(c_ptr), value :: c
      integer(c_int64_t), value :: step
      real(c_double), value :: sim_time
      type(c_ptr), value :: data
      integer(c_size_t), value :: data_bytes
      integer(c_int32_t), value :: dtype
      integer(c_int32_t), dimension(3), intent(in) :: global_dims, brick_offset, brick_dims
      real(c_float), dimension(3), intent(in) :: spacing
      integer(c_int32_t), value :: rank, world_size
      type(c_ptr), value :: out
    end function c_push_step

    integer(c_int) function c_flush(c, timeout_secs, out) bind(C, name="insitu_flush")
      import :: c_int, c_ptr, c_double
      type(c_ptr), value :: c
      real(c_double), value :: timeout_secs
      type(c_ptr), value :: out
    end function c_flush

    integer(c_int) function c_close(c, timeout_secs, out) bind(C, name="insitu_close")
      import :: c_int, c_ptr, c_double
      type(c_ptr), intent(inout) :: c
      real(c_double), value :: timeout_secs
      type(c_ptr), value :: out
    end function c_close

    type(c_ptr) function c_last_error() bind(C, name="insitu_last_error")
      import :: c_ptr
    end function c_last_error

    integer(c_size_t) function c_strlen(s) bind(C, name="strlen")
      import :: c_size_t, c_ptr
      type(c_ptr), value :: s
    end function c_strlen
  end interface

contains

  !> Why the last call failed ("" if none has).
  function insitu_error() result(text)
    character(len=:), allocatable :: text
    if (allocated(message)) then
      text = message
    else
      text = ""
    end if
  end function insitu_error

  !> Keeps the C library's message when `status` is a failure; returns `status`.
  integer function from_c(status)
    integer(c_int), intent(in) :: status
    character(kind=c_char), pointer :: chars(:)
    character(len=:), allocatable :: text
    type(c_ptr) :: p
    integer :: i, n
    from_c = int(status)
    if (status == INSITU_OK) return
    p = c_last_error()
    n = int(c_strlen(p))
    call c_f_pointer(p, chars, [n])
    allocate (character(len=n) :: text)
    do i = 1, n
      text(i:i) = chars(i)
    end do
    message = text
  end function from_c

  !> Fails with `text` as the message.
  integer function refuse(text)
    character(len=*), intent(in) :: text
    message = text
    refuse = INSITU_INVALID_ARGUMENT
  end function refuse

  !> Connects to the generator-node at `addr` ("host:port"); the token, if the node needs one,
  !> comes from the INSITU_TOKEN environment variable.
  integer function insitu_connect(client, addr)
    type(insitu_client), intent(out) :: client
    character(len=*), intent(in) :: addr
    insitu_connect = from_c(c_connect(trim(addr)//c_null_char, c_null_ptr, client%handle))
  end function insitu_connect

  !> Checks what both kinds of push share; 0 when it may go.
  integer function check_brick(client, shape_, contiguous_, global_dims, offset, rank, &
      world_size, spacing, dims, sp)
    type(insitu_client), intent(in) :: client
    integer, intent(in) :: shape_(3), global_dims(3), offset(3), rank, world_size
    logical, intent(in) :: contiguous_
    real, intent(in), optional :: spacing(3)
    integer(c_int32_t), intent(out) :: dims(3)
    real(c_float), intent(out) :: sp(3)
    check_brick = INSITU_OK
    dims = int(shape_, c_int32_t)
    sp = 1.0_c_float
    if (present(spacing)) sp = real(spacing, c_float)
    if (.not. c_associated(client%handle)) then
      check_brick = refuse("client is not connected (or was closed)")
    else if (.not. contiguous_) then
      check_brick = refuse("field is not contiguous: pass a whole array or a contiguous copy")
    else if (any(shape_ < 1)) then
      check_brick = refuse("field is empty")
    else if (any(offset < 0) .or. any(global_dims < 1) .or. rank < 0 .or. world_size < 1) then
      check_brick = refuse("offsets, global_dims, rank and world_size must be non-negative " &
        //"(global_dims and world_size at least 1)")
    end if
  end function check_brick

  !> Pushes `field(nx, ny, nz)` (real32) as rank `rank` of `world_size`'s brick at `offset`
  !> (x, y, z, points from 0) of the grid of `global_dims` points; `spacing` (x, y, z) between
  !> points, default 1. Returns once the node has queued it.
  integer function push_real32(client, step, sim_time, field, global_dims, offset, rank, &
      world_size, spacing)
    type(insitu_client), intent(in) :: client
    integer, intent(in) :: step, global_dims(3), offset(3), rank, world_size
    real(real64), intent(in) :: sim_time
    real(real32), intent(in), target :: field(:, :, :)
    real, intent(in), optional :: spacing(3)
    integer(c_int32_t) :: dims(3)
    real(c_float) :: sp(3)
    push_real32 = check_brick(client, shape(field), is_contiguous(field), global_dims, offset, &
      rank, world_size, spacing, dims, sp)
    if (push_real32 /= INSITU_OK) return
    push_real32 = from_c(c_push_step(client%handle, int(step, c_int64_t), real(sim_time, c_double), &
      c_loc(field), int(size(field, kind=c_size_t) * 4_c_size_t, c_size_t), DTYPE_F32, &
      int(global_dims, c_int32_t), int(offset, c_int32_t), dims, sp, int(rank, c_int32_t), &
      int(world_size, c_int32_t), c_null_ptr))
  end function push_real32

  !> As push_real32, for real64 fields.
  integer function push_real64(client, step, sim_time, field, global_dims, offset, rank, &
      world_size, spacing)
    type(insitu_client), intent(in) :: client
    integer, intent(in) :: step, global_dims(3), offset(3), rank, world_size
    real(real64), intent(in) :: sim_time
    real(real64), intent(in), target :: field(:, :, :)
    real, intent(in), optional :: spacing(3)
    integer(c_int32_t) :: dims(3)
    real(c_float) :: sp(3)
    push_real64 = check_brick(client, shape(field), is_contiguous(field), global_dims, offset, &
      rank, world_size, spacing, dims, sp)
    if (push_real64 /= INSITU_OK) return
    push_real64 = from_c(c_push_step(client%handle, int(step, c_int64_t), real(sim_time, c_double), &
      c_loc(field), int(size(field, kind=c_size_t) * 8_c_size_t, c_size_t), DTYPE_F64, &
      int(global_dims, c_int32_t), int(offset, c_int32_t), dims, sp, int(rank, c_int32_t), &
      int(world_size, c_int32_t), c_null_ptr))
  end function push_real64

  !> Waits until every step the node has received is generated and shipped, at most
  !> `timeout_secs` (default 600).
  integer function insitu_flush(client, timeout_secs)
    type(insitu_client), intent(in) :: client
    real(real64), intent(in), optional :: timeout_secs
    real(c_double) :: t
    t = 600.0_c_double
    if (present(timeout_secs)) t = real(timeout_secs, c_double)
    if (.not. c_associated(client%handle)) then
      insitu_flush = refuse("client is not connected (or was closed)")
      return
    end if
    insitu_flush = from_c(c_flush(client%handle, t, c_null_ptr))
  end function insitu_flush

  !> Flushes (as insitu_flush) and frees the client; it is null afterwards.
  integer function insitu_close(client, timeout_secs)
    type(insitu_client), intent(inout) :: client
    real(real64), intent(in), optional :: timeout_secs
    real(c_double) :: t
    t = 600.0_c_double
    if (present(timeout_secs)) t = real(timeout_secs, c_double)
    insitu_close = from_c(c_close(client%handle, t, c_null_ptr))
  end function insitu_close

end module insitu
