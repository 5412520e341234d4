!> The Fortran client's push throughput: PUSHES pushes of an N³ real32 field to a
!> generator-node, after one warm-up push; prints GB/s (a push returns once the node has queued
!> the step). Built and run by `cargo bench -p insitu-e2e --bench pipeline` beside the Rust, C
!> and Python clients.
!>
!> Usage: push_throughput GENERATOR_ADDR N PUSHES
program push_throughput
  use insitu
  use, intrinsic :: iso_fortran_env, only: real32, real64, int64
  implicit none
  type(insitu_client) :: c
  character(len=256) :: addr, arg
  integer :: n, pushes, k, i, j, l, s
  integer(int64) :: t0, t1, rate
  real(real32), allocatable :: field(:, :, :)
  real(real64) :: secs, bytes

  call get_command_argument(1, addr)
  call get_command_argument(2, arg); read (arg, *) n
  call get_command_argument(3, arg); read (arg, *) pushes
  allocate (field(n, n, n))
  do l = 1, n
    do j = 1, n
      do i = 1, n
        field(i, j, l) = real(mod((i - 1) + n * ((j - 1) + n * (l - 1)), 977), real32)
      end do
    end do
  end do
  if (insitu_connect(c, trim(addr)) /= INSITU_OK) error stop 'connect failed'
  s = insitu_push(c, 0, 0.0_real64, field, [n, n, n], [0, 0, 0], 0, 1)
  if (s /= INSITU_OK) error stop 'push failed'
  call system_clock(t0, rate)
  do k = 1, pushes
    s = insitu_push(c, k, real(k, real64), field, [n, n, n], [0, 0, 0], 0, 1)
    if (s /= INSITU_OK) then
      print '(a)', insitu_error()
      error stop 'push failed'
    end if
  end do
  call system_clock(t1)
  secs = real(t1 - t0, real64) / real(rate, real64)
  bytes = real(n, real64)**3 * 4.0_real64
  ! f6.2: gfortran's f0.d drops the zero before the point.
  print '(a,i0,a,i0,a,f6.2,a,f6.2,a)', 'ingest (Fortran client): ', pushes, ' pushes of ', &
    nint(bytes / 1048576.0_real64), ' MiB in ', secs, ' s = ', pushes * bytes / secs / 1e9_real64, &
    ' GB/s'
  s = insitu_close(c, 60.0_real64)
end program push_throughput
