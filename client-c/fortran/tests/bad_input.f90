!> Bad input through the Fortran module: each case prints `case status message` on one line,
!> and the program goes on (tests/tests/e2e/fortran.rs checks every line). Usage:
!> bad_input GENERATOR_ADDR DEAD_ADDR
program bad_input
  use insitu
  use, intrinsic :: iso_fortran_env, only: real32, real64
  implicit none
  type(insitu_client) :: c, never
  character(len=256) :: addr, dead
  real(real32), allocatable :: f(:, :, :)
  real(real64), allocatable :: d(:, :, :)
  integer :: s

  call get_command_argument(1, addr)
  call get_command_argument(2, dead)
  allocate (f(8, 8, 8), source=0.5_real32)
  allocate (d(8, 8, 8), source=0.5_real64)

  s = insitu_connect(c, trim(dead))
  call say('dead_daemon', s)
  s = insitu_push(never, 1, 0.0_real64, f, [8, 8, 8], [0, 0, 0], 0, 1)
  call say('not_connected', s)
  s = insitu_connect(c, trim(addr))
  call say('connect', s)
  s = insitu_push(c, 1, 0.0_real64, f(1:8:2, :, :), [8, 8, 8], [0, 0, 0], 0, 1)
  call say('non_contiguous', s)
  s = insitu_push(c, 2, 0.0_real64, f, [8, 8, 8], [4, 0, 0], 0, 1)
  call say('outside_the_grid', s)
  s = insitu_push(c, 3, 0.0_real64, f, [8, 8, 8], [0, 0, 0], 1, 1)
  call say('bad_rank', s)
  s = insitu_push(c, 4, 0.0_real64, f(:, :, 1:0), [8, 8, 8], [0, 0, 0], 0, 1)
  call say('empty', s)
  s = insitu_push(c, 5, 0.0_real64, d, [8, 8, 8], [0, 0, 0], 0, 1)
  call say('real64', s)
  s = insitu_push(c, 6, 0.0_real64, f, [8, 8, 8], [0, 0, 0], 0, 1)
  call say('real32', s)
  s = insitu_close(c)
  call say('close', s)
  s = insitu_push(c, 7, 0.0_real64, f, [8, 8, 8], [0, 0, 0], 0, 1)
  call say('after_close', s)
  s = insitu_close(c)
  call say('close_twice', s)

contains

  subroutine say(what, status)
    character(len=*), intent(in) :: what
    integer, intent(in) :: status
    if (status == INSITU_OK) then
      print '(a,1x,i0)', what, status
    else
      print '(a,1x,i0,1x,a)', what, status, insitu_error()
    end if
  end subroutine say

end program bad_input
