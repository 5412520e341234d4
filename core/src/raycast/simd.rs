//! Eight steps of one ray sampled at once with AVX2 (chosen at run time; the scalar path in
//! [`super`] stays the reference and the fallback).
//!
//! A visible macro cell's steps are independent until compositing, so their positions,
//! lower voxels, fractions, corner gathers (four for u8, u16 and i16: one 4-byte load holds a
//! corner and its x neighbour) and trilinear blends are computed eight lanes wide;
//! classification and the visitor then run per lane, in order. Every lane does the scalar
//! path's arithmetic in the scalar path's order (multiplications and additions, never fused;
//! truncation for the lower voxel), so the values are **bit-identical** to
//! [`super::trilinear`] at [`super::Raycaster::locate`]'s positions — the tests pin that.
//! Before the corner gathers, one gather of [`super::occupancy`]'s bits tells whether any
//! lane's 2³-voxel block can be visible; a batch with none returns at once (none of its values
//! could have been visible, so the visits are the same).

// The intrinsics are `unsafe`; this module is the workspace's one exception to
// `unsafe_code = "deny"`, and exposes only safe functions: the AVX2 kernel runs only behind
// an [`Avx2`] token (proof of detection) and only on inputs whose gathers it has checked.
#![allow(unsafe_code)]

use super::occupancy::{Layout, BLOCK};
use super::{Marching, Raycaster, Visit};
use crate::camera::Ray;
use crate::tf::{Lut, LUT_SIZE};
use crate::volume::Voxel;
use glam::Vec3;

/// Proof that this CPU runs AVX2: made only by [`Avx2::detect`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Avx2(());

impl Avx2 {
    /// The token, where the CPU has AVX2 (checked at run time).
    pub(crate) fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            return Some(Self(()));
        }
        None
    }
}

/// [`Raycaster::march`]'s loop compiled with AVX2 enabled, so that the scalar steps and the
/// bookkeeping around [`Lanes::classify`] use the same instruction set; the visitor (with a
/// fold's state) is a local of that function, kept in registers where it fits.
#[cfg(target_arch = "x86_64")]
#[inline]
pub(super) fn march<T: Gather, const SHADE: bool, V: Visit>(
    avx2: Avx2,
    rc: &Raycaster,
    data: &[T],
    ray: &Ray,
    visit: V,
) -> V {
    // SAFETY: the token proves that this CPU has AVX2.
    unsafe { march_avx2::<T, SHADE, V>(avx2, rc, data, ray, visit) }
}

/// [`march`].
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn march_avx2<T: Gather, const SHADE: bool, V: Visit>(
    avx2: Avx2,
    rc: &Raycaster,
    data: &[T],
    ray: &Ray,
    mut visit: V,
) -> V {
    rc.march_impl::<T, SHADE>(data, ray, &mut visit, Some(avx2));
    visit
}

/// Table entries per bit of the visibility map (`LUT_SIZE / 256`), and its log2.
const GROUP: usize = LUT_SIZE / 256;
const GROUP_SHIFT: i32 = GROUP.trailing_zeros() as i32;
const _: () = assert!(GROUP.is_power_of_two() && GROUP * 256 == LUT_SIZE);

/// The kernel's visibility map of `lut`: bit `g` (of 256; word `g / 32`, bit `g mod 32`) is
/// set where any of the entries `g·GROUP … g·GROUP + GROUP − 1` has `κ > 0`.
pub(super) fn visible_groups(lut: &Lut) -> [u32; 8] {
    let mut groups = [0u32; 8];
    for (i, e) in lut.entries().iter().enumerate().take(LUT_SIZE) {
        if e.kappa > 0.0 {
            groups[i / GROUP / 32] |= 1 << (i / GROUP % 32);
        }
    }
    groups
}

/// The stored types the kernel gathers, by size: u8, u16 and i16 as 32-bit loads at the
/// voxel's address, masked or sign-extended (reading up to [`Gather::OVERREAD`] elements past
/// it, which the storage's padding covers), f32 directly.
pub(super) trait Gather: Voxel {
    /// Elements a 4-byte load at the last voxel reads past it.
    const OVERREAD: usize = 4 / std::mem::size_of::<Self>() - 1;
    /// Whether the integer type is signed (sign-extended, not masked).
    const SIGNED: bool = false;
}
impl Gather for u8 {}
impl Gather for u16 {}
impl Gather for i16 {
    const SIGNED: bool = true;
}
impl Gather for f32 {}

/// What the kernel needs of one ray through one volume, checked once when made
/// ([`Lanes::new`]): the fields are private so that no unchecked one exists.
pub(super) struct Lanes<'a, T> {
    /// Proof of AVX2, held so that no `Lanes` exists without it.
    _avx2: Avx2,
    /// The voxels and the storage's padding after them.
    data: &'a [T],
    dims: [usize; 3],
    strides: [usize; 3],
    max_voxel: Vec3,
    o_v: Vec3,
    d_v: Vec3,
    t_in: f32,
    step: f32,
    /// The classification's index map ([`crate::tf::Lut::mapping`]) and which groups of
    /// [`GROUP`] entries hold a visible one (`Raycaster::visible_groups`).
    lut_lo: f32,
    lut_scale: f32,
    visible_groups: [u32; 8],
    /// The layout and bits of [`super::occupancy::Occupancy`], made for these dimensions;
    /// `None` without them (every batch is gathered).
    occupancy: Option<(Layout, &'a [u32])>,
}

impl<'a, T: Gather> Lanes<'a, T> {
    /// The kernel for ray `m` of `rc` over `data` (the volume's storage, padding included);
    /// `None` for a volume the kernel cannot index (over `i32::MAX` voxels, or storage that
    /// does not match the dimensions), which the scalar path then samples.
    pub(super) fn new(
        avx2: Avx2,
        rc: &'a Raycaster<'a>,
        data: &'a [T],
        m: &Marching,
    ) -> Option<Self> {
        let dims = rc.volume.dims();
        let n = dims.iter().product::<usize>();
        let (lut_lo, lut_scale) = rc.lut.mapping();
        let fits = n == rc.volume.voxels().len()
            && data.len() >= n + T::OVERREAD
            && data.len() <= i32::MAX as usize
            && !dims.contains(&0)
            && rc.lut.entries().len() == LUT_SIZE;
        // `Occupancy::new` made the layout (cells of the volume's grid, shifts, `i32` word
        // indices) and the words for every cell of these dimensions.
        let occupancy = rc.occupancy().and_then(|o| o.for_dims(dims));
        fits.then_some(Self {
            occupancy,
            _avx2: avx2,
            data,
            dims,
            strides: rc.strides,
            max_voxel: rc.max_voxel,
            o_v: m.o_v,
            d_v: m.d_v,
            t_in: m.t_in,
            step: m.step,
            lut_lo,
            lut_scale,
            visible_groups: rc.visible_groups,
        })
    }

    /// The full steps `k … k + n − 1` (`n ≤ 64`) sampled (trilinear at their midpoints,
    /// positions clamped to the grid, so lanes past the ray's end read valid voxels and are
    /// simply not used) and classified, eight at a time: step `k + l`'s table index goes to
    /// `index[l / 8][l % 8]`, and bit `l` of the returned mask is set where it may be visible
    /// (not NaN, and in a group of table entries with one `κ > 0`: see [`visible_groups`]);
    /// bits from `n` on are clear.
    #[cfg(target_arch = "x86_64")]
    #[inline]
    pub(super) fn classify<const B: usize>(
        &self,
        k: u32,
        n: u32,
        index: &mut [[i32; 8]; B],
    ) -> u64 {
        // SAFETY: the token proves AVX2; `new`'s checks keep every gather in bounds (see
        // `gather8`).
        unsafe { self.classify_avx2(k, n, index) }
    }

    /// [`Lanes::classify`].
    ///
    /// # Safety
    /// As [`Lanes::gather8`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn classify_avx2<const B: usize>(
        &self,
        k: u32,
        n: u32,
        index: &mut [[i32; 8]; B],
    ) -> u64 {
        let n = n.min(B as u32 * 8).min(64);
        let mut visible = 0u64;
        for (b, index) in index.iter_mut().enumerate().take(n.div_ceil(8) as usize) {
            // SAFETY: as this function's.
            let mask = unsafe { self.gather8(k + 8 * b as u32, index) };
            visible |= u64::from(mask) << (8 * b);
        }
        if n < 64 {
            visible &= (1u64 << n) - 1;
        }
        visible
    }

    /// Eight steps of [`Lanes::classify`]: the samples' positions, the occupancy test of their
    /// blocks, the trilinear samples, and their table indices and visibility.
    ///
    /// # Safety
    /// The CPU must have AVX2, `nx·ny·nz + OVERREAD ≤ data.len() ≤ i32::MAX` (both made sure
    /// by [`Lanes::new`]).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn gather8(&self, k: u32, out: &mut [i32; 8]) -> u32 {
        // SAFETY: AVX2, as this function's contract.
        let (i, f) = unsafe { self.positions8(k) };
        // SAFETY: AVX2; the lower voxels are in the grid (`positions8`).
        if unsafe { self.blocks_empty8(i) } {
            return 0;
        }
        // SAFETY: AVX2 and the data's length, as this function's contract.
        let v = unsafe { self.sample8(i, f) };
        // SAFETY: AVX2.
        unsafe { self.classify8(v, out) }
    }

    /// Steps `k..k + 8`: each sample's lower voxel (clamped to `n − 2` per axis, so its
    /// corners are in the grid) and its fractions along x, y and z.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn positions8(
        &self,
        k: u32,
    ) -> (
        [std::arch::x86_64::__m256i; 3],
        [std::arch::x86_64::__m256; 3],
    ) {
        use std::arch::x86_64::*;
        let [nx, ny, nz] = self.dims;
        let kf = _mm256_cvtepi32_ps(_mm256_add_epi32(
            _mm256_set1_epi32(k as i32),
            _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
        ));
        // t0 = t_in + k·Δ; midpoint t0 + 0.5·Δ (as the scalar path: 0.5·len with len = Δ).
        let t0 = _mm256_add_ps(
            _mm256_set1_ps(self.t_in),
            _mm256_mul_ps(kf, _mm256_set1_ps(self.step)),
        );
        let tm = _mm256_add_ps(t0, _mm256_set1_ps(0.5 * self.step));
        let axis = |o: f32, d: f32, hi: f32, n: usize| {
            let p = _mm256_add_ps(_mm256_set1_ps(o), _mm256_mul_ps(tm, _mm256_set1_ps(d)));
            let p = _mm256_min_ps(_mm256_max_ps(p, _mm256_setzero_ps()), _mm256_set1_ps(hi));
            let i = _mm256_min_epi32(
                _mm256_cvttps_epi32(p),
                _mm256_set1_epi32(n.saturating_sub(2) as i32),
            );
            (i, _mm256_sub_ps(p, _mm256_cvtepi32_ps(i)))
        };
        let (ix, fx) = axis(self.o_v.x, self.d_v.x, self.max_voxel.x, nx);
        let (iy, fy) = axis(self.o_v.y, self.d_v.y, self.max_voxel.y, ny);
        let (iz, fz) = axis(self.o_v.z, self.d_v.z, self.max_voxel.z, nz);
        ([ix, iy, iz], [fx, fy, fz])
    }

    /// Whether every lane's 2³-voxel block is empty (occupancy bits; `false` without them).
    ///
    /// # Safety
    /// The CPU must have AVX2; `[ix, iy, iz]` lower voxels in the grid (as [`Self::positions8`]
    /// gives them).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn blocks_empty8(&self, [ix, iy, iz]: [std::arch::x86_64::__m256i; 3]) -> bool {
        use std::arch::x86_64::*;
        if let Some((o, words)) = self.occupancy {
            // The lanes' blocks: cell `c` from the lower voxel / S, block `b` within it from
            // (voxel / 2) mod (S/2) per axis; bit `b mod 32` of word `c·words + b / 32`. In
            // bounds: the lower voxel is at most n − 2 per axis, so its cell is one of the
            // grid's, whose words `new` checked are all there.
            let count = |n: i32| _mm_cvtsi32_si128(n);
            let cell = |i: __m256i| _mm256_srl_epi32(i, count(o.cell_shift));
            let block = |i: __m256i| {
                _mm256_and_si256(
                    _mm256_srli_epi32::<{ BLOCK.trailing_zeros() as i32 }>(i),
                    _mm256_set1_epi32((1 << o.per_axis_shift) - 1),
                )
            };
            let [cx, cy, _] = o.cells;
            let c = _mm256_add_epi32(
                cell(ix),
                _mm256_mullo_epi32(
                    _mm256_set1_epi32(cx),
                    _mm256_add_epi32(
                        cell(iy),
                        _mm256_mullo_epi32(_mm256_set1_epi32(cy), cell(iz)),
                    ),
                ),
            );
            // b = bx + (S/2)·(by + (S/2)·bz).
            let b = _mm256_or_si256(
                block(ix),
                _mm256_or_si256(
                    _mm256_sll_epi32(block(iy), count(o.per_axis_shift)),
                    _mm256_sll_epi32(block(iz), count(2 * o.per_axis_shift)),
                ),
            );
            let word = _mm256_i32gather_epi32::<4>(
                words.as_ptr().cast(),
                _mm256_add_epi32(
                    _mm256_sll_epi32(c, count(o.words_shift)),
                    _mm256_srli_epi32::<5>(b),
                ),
            );
            let bit = _mm256_srlv_epi32(word, _mm256_and_si256(b, _mm256_set1_epi32(31)));
            if _mm256_testz_si256(bit, _mm256_set1_epi32(1)) != 0 {
                // Every lane in an empty block: transparent, nothing to gather.
                return true;
            }
        }
        false
    }

    /// The trilinear samples at lower voxels `[ix, iy, iz]` with fractions `[fx, fy, fz]`.
    ///
    /// # Safety
    /// As [`Self::gather8`], with the voxels as [`Self::positions8`] gives them.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn sample8(
        &self,
        [ix, iy, iz]: [std::arch::x86_64::__m256i; 3],
        [fx, fy, fz]: [std::arch::x86_64::__m256; 3],
    ) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        let [nx, ny, _] = self.dims;
        let [sx, sy, sz] = self.strides.map(|s| s as i32);
        let base = _mm256_add_epi32(
            ix,
            _mm256_mullo_epi32(
                _mm256_set1_epi32(nx as i32),
                _mm256_add_epi32(iy, _mm256_mullo_epi32(_mm256_set1_epi32(ny as i32), iz)),
            ),
        );
        let ptr = self.data.as_ptr();
        // In bounds: the lower voxel is at most (n − 2) per axis where the stride is not 0,
        // so `base + sx + sy + sz` is a voxel of the grid, and a 4-byte load there ends
        // within the padding. Integer voxels are masked (unsigned) or sign-extended (i16) to
        // their width and converted exactly.
        let low16 = |g: __m256i| {
            if T::SIGNED {
                _mm256_srai_epi32::<16>(_mm256_slli_epi32::<16>(g))
            } else {
                _mm256_and_si256(g, _mm256_set1_epi32(0xffff))
            }
        };
        let at = |o: i32| {
            let index = _mm256_add_epi32(base, _mm256_set1_epi32(o));
            match std::mem::size_of::<T>() {
                1 => _mm256_cvtepi32_ps(_mm256_and_si256(
                    _mm256_i32gather_epi32::<1>(ptr.cast(), index),
                    _mm256_set1_epi32(0xff),
                )),
                2 => _mm256_cvtepi32_ps(low16(_mm256_i32gather_epi32::<2>(ptr.cast(), index))),
                _ => _mm256_i32gather_ps::<4>(ptr.cast(), index),
            }
        };
        let lerp = |a: __m256, b: __m256, f: __m256| {
            _mm256_add_ps(a, _mm256_mul_ps(f, _mm256_sub_ps(b, a)))
        };
        // Integer voxels along x (stride 1) come in pairs: one 4-byte load at a corner holds
        // its x neighbour too (byte or half-word 1), so four gathers fetch all eight corners.
        let (c00, c10, c01, c11) = if std::mem::size_of::<T>() < 4 && sx == 1 {
            let bits = 8 * std::mem::size_of::<T>() as i32;
            let mask = _mm256_set1_epi32((1 << bits) - 1);
            let pair = |o: i32| {
                let index = _mm256_add_epi32(base, _mm256_set1_epi32(o));
                let (lo, hi) = if bits == 8 {
                    let g = _mm256_i32gather_epi32::<1>(ptr.cast(), index);
                    let hi = _mm256_and_si256(_mm256_srli_epi32::<8>(g), mask);
                    (_mm256_and_si256(g, mask), hi)
                } else {
                    let g = _mm256_i32gather_epi32::<2>(ptr.cast(), index);
                    let hi = if T::SIGNED {
                        _mm256_srai_epi32::<16>(g)
                    } else {
                        _mm256_srli_epi32::<16>(g)
                    };
                    (low16(g), hi)
                };
                let (lo, hi) = (_mm256_cvtepi32_ps(lo), _mm256_cvtepi32_ps(hi));
                lerp(lo, hi, fx)
            };
            (pair(0), pair(sy), pair(sz), pair(sz + sy))
        } else if std::mem::size_of::<T>() == 4 && sx == 1 {
            // f32 along x likewise: one 8-byte load per lane holds a corner and its x
            // neighbour (two 4-lane gathers of 8 bytes: half the element loads of two 8-lane
            // gathers of 4), deinterleaved into the two corners' lanes.
            let pair = |o: i32| {
                let index = _mm256_add_epi32(base, _mm256_set1_epi32(o));
                let gather =
                    |i: __m128i| _mm256_castsi256_ps(_mm256_i32gather_epi64::<4>(ptr.cast(), i));
                let a = gather(_mm256_castsi256_si128(index));
                let b = gather(_mm256_extracti128_si256::<1>(index));
                // Lanes 0, 1, 4, 5 | 2, 3, 6, 7 of the corner (even words) and of its
                // neighbour (odd words), then the middle quarters swapped into order.
                let order = |v: __m256| {
                    _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(v)))
                };
                let lo = order(_mm256_shuffle_ps::<0b10_00_10_00>(a, b));
                let hi = order(_mm256_shuffle_ps::<0b11_01_11_01>(a, b));
                lerp(lo, hi, fx)
            };
            (pair(0), pair(sy), pair(sz), pair(sz + sy))
        } else {
            (
                lerp(at(0), at(sx), fx),
                lerp(at(sy), at(sy + sx), fx),
                lerp(at(sz), at(sz + sx), fx),
                lerp(at(sz + sy), at(sz + sy + sx), fx),
            )
        };
        let c0 = lerp(c00, c10, fy);
        let c1 = lerp(c01, c11, fy);
        lerp(c0, c1, fz)
    }

    /// The samples `v`'s table indices into `out` (0 for NaN) and the bits of the visible ones.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn classify8(&self, v: std::arch::x86_64::__m256, out: &mut [i32; 8]) -> u32 {
        use std::arch::x86_64::*;
        // Table index as `Lut::index`: ((v − lo)·scale) clamped to the table, + 0.5, truncated.
        // NaN lanes (unordered with themselves) are masked out of the gather and invisible.
        let x = _mm256_mul_ps(
            _mm256_sub_ps(v, _mm256_set1_ps(self.lut_lo)),
            _mm256_set1_ps(self.lut_scale),
        );
        let x = _mm256_min_ps(
            _mm256_max_ps(x, _mm256_setzero_ps()),
            _mm256_set1_ps((LUT_SIZE - 1) as f32),
        );
        let number = _mm256_cmp_ps::<_CMP_ORD_Q>(v, v);
        let index = _mm256_and_si256(
            _mm256_cvttps_epi32(_mm256_add_ps(x, _mm256_set1_ps(0.5))),
            _mm256_castps_si256(number),
        );
        // Visibility from the 256-bit group map, in registers: word `index / (32·GROUP)`,
        // bit `index / GROUP mod 32`. Conservative (a group is visible when any entry in it
        // is); the visitor drops the rare lane whose own entry is transparent (`α = 0`).
        let group = _mm256_srli_epi32::<GROUP_SHIFT>(index);
        let word = _mm256_permutevar8x32_epi32(
            _mm256_loadu_si256(self.visible_groups.as_ptr().cast()),
            _mm256_srli_epi32::<5>(group),
        );
        let bit = _mm256_and_si256(
            _mm256_srlv_epi32(word, _mm256_and_si256(group, _mm256_set1_epi32(31))),
            _mm256_set1_epi32(1),
        );
        let visible = _mm256_and_ps(
            number,
            _mm256_castsi256_ps(_mm256_cmpeq_epi32(bit, _mm256_set1_epi32(1))),
        );
        _mm256_storeu_si256(out.as_mut_ptr().cast(), index);
        _mm256_movemask_ps(visible) as u32
    }
}
