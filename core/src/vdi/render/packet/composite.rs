//! Compositing a pixel's supersegment list into the lanes that cross it, portable and AVX2.

#![allow(unsafe_code)]

use super::*;

/// The packet's accumulators (structure of arrays): each lane's premultiplied colour and
/// transmittance, as its [`FrontToBack`]'s.
pub(super) struct Accums {
    pub(super) rgb: [F; 3],
    pub(super) transmittance: F,
}

/// The spans the lanes composite at one pixel: ray parameters `[ta, tb]`, for the lanes
/// whose bits `lanes` holds.
pub(super) struct Spans {
    pub(super) ta: F,
    pub(super) tb: F,
    pub(super) lanes: u32,
}

/// Composites each lane of `spans` through the pixel list `list` (with its `keys`) as
/// [`composite_span`] does; returns the bits of the lanes that reached `termination`.
pub(super) fn composite_lanes(
    list: &[Supersegment],
    keys: &[[f32; 2]],
    l: &Lanes,
    spans: &Spans,
    acc: &mut Accums,
    termination: f32,
) -> u32 {
    let mut done = 0;
    for k in 0..LANES {
        if spans.lanes & (1 << k) == 0 {
            continue;
        }
        let mut a = Accum::new(termination);
        a.ray.color = [acc.rgb[0][k], acc.rgb[1][k], acc.rgb[2][k]];
        a.ray.transmittance = acc.transmittance[k];
        let z = Lin {
            f0: l.z0[k],
            f1: l.z1[k],
        };
        if composite_span(list, keys, z, spans.ta[k], spans.tb[k], &mut a) {
            done |= 1 << k;
        }
        for (c, v) in acc.rgb.iter_mut().zip(a.ray.color) {
            c[k] = v;
        }
        acc.transmittance[k] = a.ray.transmittance;
    }
    done
}

/// [`composite_lanes`] with AVX2: where every lane's depth runs the same way along its ray,
/// the list is traversed once for all of them, each supersegment composited into the eight
/// lanes at once (a lane outside it gets length 0, which composites nothing); else lane by
/// lane. The same operations per lane in the same order, so the same result.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn composite_lanes_avx2(
    list: &[Supersegment],
    keys: &[[f32; 2]],
    l: &Lanes,
    spans: &Spans,
    acc: &mut Accums,
    termination: f32,
) -> u32 {
    use crate::vdi::generate::one_minus_exp_neg_avx2;
    use lanes8::*;
    use std::arch::x86_64::*;
    let lanes = spans.lanes;
    let forward = l.deeper & lanes == lanes;
    if !forward && l.shallower & lanes != lanes {
        return composite_lanes(list, keys, l, spans, acc, termination);
    }
    let (ta, tb, z0, z1) = (load(&spans.ta), load(&spans.tb), load(&l.z0), load(&l.z1));
    let za = _mm256_add_ps(z0, _mm256_mul_ps(z1, ta));
    let zb = _mm256_add_ps(z0, _mm256_mul_ps(z1, tb));
    let span = _mm256_sub_ps(tb, ta);
    let mut live = lanes_mask(lanes);
    let (mut r, mut g, mut b) = (load(&acc.rgb[0]), load(&acc.rgb[1]), load(&acc.rgb[2]));
    let mut t = load(&acc.transmittance);
    let threshold = _mm256_set1_ps(Accum::new(termination).threshold);
    let zero = _mm256_setzero_ps();
    // The lanes' extreme depths: where the traversal starts and ends.
    let (big, small) = (_mm256_set1_ps(f32::MAX), _mm256_set1_ps(-f32::MAX));
    let z_lo = fold_ps(_mm256_blendv_ps(big, za, live), _mm256_min_ps);
    let z_hi = fold_ps(_mm256_blendv_ps(small, za, live), _mm256_max_ps);
    let z_min_b = fold_ps(_mm256_blendv_ps(big, zb, live), _mm256_min_ps);
    let z_max_b = fold_ps(_mm256_blendv_ps(small, zb, live), _mm256_max_ps);
    // One supersegment into every live lane, with `len` its length on each lane's ray.
    let mut add = |s: &Supersegment, kappa: f32, len: __m256| -> bool {
        // `len.clamp(0, span)`.
        let len = _mm256_blendv_ps(len, zero, _mm256_cmp_ps::<_CMP_LT_OQ>(len, zero));
        let len = _mm256_blendv_ps(len, span, _mm256_cmp_ps::<_CMP_GT_OQ>(len, span));
        let m = _mm256_and_ps(live, _mm256_cmp_ps::<_CMP_GT_OQ>(len, zero));
        if s.alpha > 0.0 && _mm256_movemask_ps(m) != 0 {
            let alpha = one_minus_exp_neg_avx2(_mm256_mul_ps(len, _mm256_set1_ps(kappa)));
            let w = _mm256_mul_ps(t, alpha);
            let c = s.color;
            r = _mm256_blendv_ps(
                r,
                _mm256_add_ps(r, _mm256_mul_ps(w, _mm256_set1_ps(c[0]))),
                m,
            );
            g = _mm256_blendv_ps(
                g,
                _mm256_add_ps(g, _mm256_mul_ps(w, _mm256_set1_ps(c[1]))),
                m,
            );
            b = _mm256_blendv_ps(
                b,
                _mm256_add_ps(b, _mm256_mul_ps(w, _mm256_set1_ps(c[2]))),
                m,
            );
            t = _mm256_blendv_ps(
                t,
                _mm256_mul_ps(t, _mm256_sub_ps(_mm256_set1_ps(1.0), alpha)),
                m,
            );
            // Lanes done: opaque enough.
            let done = _mm256_and_ps(m, _mm256_cmp_ps::<_CMP_LE_OQ>(t, threshold));
            live = _mm256_andnot_ps(done, live);
        }
        _mm256_movemask_ps(live) == 0
    };
    if forward {
        // From the first supersegment ending after the nearest entry, up to the farthest exit.
        let first = ending_after(keys, z_lo);
        for (s, k) in list[first..].iter().zip(&keys[first..]) {
            if s.z_start >= z_max_b {
                break;
            }
            let len = _mm256_div_ps(
                _mm256_sub_ps(
                    _mm256_min_ps(_mm256_set1_ps(s.z_end), zb),
                    _mm256_max_ps(_mm256_set1_ps(s.z_start), za),
                ),
                z1,
            );
            if add(s, k[1], len) {
                break;
            }
        }
    } else {
        // From the last supersegment starting before the farthest entry, down to the
        // nearest exit.
        let end = starting_before(list, z_hi);
        let neg_z1 = _mm256_xor_ps(z1, _mm256_set1_ps(-0.0));
        for (s, k) in list[..end].iter().zip(&keys[..end]).rev() {
            if s.z_end <= z_min_b {
                break;
            }
            let len = _mm256_div_ps(
                _mm256_sub_ps(
                    _mm256_min_ps(_mm256_set1_ps(s.z_end), za),
                    _mm256_max_ps(_mm256_set1_ps(s.z_start), zb),
                ),
                neg_z1,
            );
            if add(s, k[1], len) {
                break;
            }
        }
    }
    acc.rgb = [lanes_of(r), lanes_of(g), lanes_of(b)];
    acc.transmittance = lanes_of(t);
    lanes & !(_mm256_movemask_ps(live) as u32)
}
