program blob
  use insitu
  use, intrinsic :: iso_fortran_env, only: real32, real64
  implicit none
  integer, parameter :: n = 64, steps = 10
  real(real32) :: field(n, n, n), cx                    ! field(x, y, z): x varies fastest
  type(insitu_client) :: c
  character(len=256) :: addr
  integer :: step, i, j, k
  call get_command_argument(1, addr)                    ! the generator-node's address
  if (insitu_connect(c, trim(addr)) /= INSITU_OK) error stop insitu_error()
  do step = 0, steps - 1
    cx = 16.0 + 2.0 * step                              ! a blob moving along x
    do concurrent (k = 1:n, j = 1:n, i = 1:n)
      field(i, j, k) = exp(-((i - 1 - cx)**2 + (j - 33.0)**2 + (k - 33.0)**2) / 128.0)
    end do
    ! the time is real(real64): a literal needs its kind, 0.1_real64
    if (insitu_push(c, step, 0.1_real64 * step, field, [n, n, n], [0, 0, 0], 0, 1) /= INSITU_OK) &
      error stop insitu_error()
  end do
  if (insitu_close(c) /= INSITU_OK) error stop insitu_error()   ! flush: every step is stored
  print '(a, i0, a, i0, a)', 'pushed ', steps, ' steps of ', n, '^3'
end program blob
