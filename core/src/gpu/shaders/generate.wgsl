// VDI generation R (Sec. 3.2, 5.2): one invocation per ray of a band of rows of the r × r
// generation image. Samples are merged front to back into the open supersegment until
// ‖â·ĉ − a·c‖₂ ≥ γ (mirrors `vdi::generate`'s builder). Two passes over the same rays with
// the same arithmetic make the compact list layout on the device:
// - counting (work 1) stores each ray's number of supersegments in `offsets` and its first
//   `budget` supersegments in its slots; `scan.wgsl` then turns the counts into offsets;
// - writing (work 2) stores each ray's list at its offset, less the part's first, in
//   `segments`: copied from its slots when they held it all, else marched again.
// Only rays longer than the budget are marched twice; with a budget of 0 every ray is.

@group(1) @binding(0) var<storage, read_write> segments: array<Segment>;
@group(1) @binding(1) var<storage, read_write> offsets: array<u32>;
@group(1) @binding(2) var<storage, read_write> slots: array<Segment>;

struct Open {
    last_index: u32,
    t_start: f32,
    t_end: f32,
    color: vec3<f32>,
    // A = Σ Tᵢ·αᵢ (no cancellation where A is small) and T = Π (1 − αᵢ).
    total: f32,
    transmittance: f32,
    optical_depth: f32,
    // Of the current extent L: â = 1 − e^(−τ/L), and â/A.
    unit: f32,
    unit_over_total: f32,
};

// 1 − e^(−x) without cancellation near 0 (the CPU's `fastmath::one_minus_exp_neg` avoids a
// libm call; here `exp` is the hardware's).
fn one_minus_exp_neg(x: f32) -> f32 {
    if (x < 1.0 / 64.0) {
        return x * (1.0 - x * (0.5 - x * (1.0 / 6.0 - x * (1.0 / 24.0))));
    }
    return 1.0 - exp(-x);
}

// â/A; A ≥ α > 0 (mirrors `generate::ratio`).
fn ratio(unit: f32, total: f32) -> f32 {
    return unit / max(total, 1.17549435e-38);
}

fn distance_sq(o: ptr<function, Open>, r: f32, ac: vec3<f32>) -> f32 {
    let d = r * (*o).color - ac;
    return dot(d, d);
}

// A supersegment of one sample: A = α and â = a from the classification.
fn open_new(s: Sample) -> Open {
    return Open(s.index, s.t_start, s.t_end, s.rgb * s.alpha, s.alpha, 1.0 - s.alpha,
        s.kappa * s.len, s.alpha_unit, ratio(s.alpha_unit, s.alpha));
}

fn close(o: Open, z_per_t: f32) -> Segment {
    let color = clamp(o.color / max(o.total, 1.17549435e-38), vec3<f32>(0.0), vec3<f32>(1.0));
    return Segment(o.t_start * z_per_t, o.t_end * z_per_t, color.x, color.y, color.z,
        clamp(o.unit, 0.0, 1.0));
}

// Stores a ray's `n`-th supersegment: in writing at `*at` (below `end`), in counting in its
// slot while `n` is within the budget.
fn store(write: bool, at: ptr<function, u32>, end: u32, slot: u32, budget: u32, n: u32,
         seg: Segment) {
    if (write) {
        if (*at < end) {
            segments[*at] = seg;
            *at += 1u;
        }
    } else if (n < budget) {
        slots[slot] = seg;
    }
}

@compute @workgroup_size(8, 8)
fn generate_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = P.image.x;
    let i = gid.x;
    let row = gid.y;
    let j = P.image.z + row;
    if (i >= r || j >= P.image.y || row >= P.band.x) {
        return;
    }
    // The ray's index within the counted band, and in writing its list's place in `segments`.
    let local = i + r * (row + P.band.y);
    let write = P.image.w == 2u;
    let budget = P.band.w;
    let slot = local * budget;
    var at = 0u;
    var end = 0u;
    if (write) {
        at = offsets[local] - P.band.z;
        end = offsets[local + 1u] - P.band.z;
        if (end - at <= budget) {
            for (var k = 0u; at + k < end; k++) {
                segments[at + k] = slots[slot + k];
            }
            return;
        }
    }
    let ray = pixel_ray(i, j);
    let z_per_t = dot(ray.dir, P.forward.xyz);
    let gamma_sq = P.box_max.w * P.box_max.w;
    let termination = P.box_min.w;
    var m = marcher_new(ray);
    var s: Sample;
    var o: Open;
    var has_open = false;
    var n = 0u;
    var transmittance = 1.0;
    while (marcher_next(&m, &s)) {
        let ac = s.rgb * s.alpha_unit;
        var keep = false;
        if (has_open) {
            if (s.index > o.last_index + 1u) {
                // A run of transparent samples: the first compares a·c = 0, then the sample
                // against the extent stretched to its start.
                if (distance_sq(&o, o.unit_over_total, vec3<f32>(0.0)) < gamma_sq) {
                    let unit = one_minus_exp_neg(o.optical_depth / (s.t_start - o.t_start));
                    let r = ratio(unit, o.total);
                    keep = distance_sq(&o, r, ac) < gamma_sq;
                }
            } else {
                keep = distance_sq(&o, o.unit_over_total, ac) < gamma_sq;
            }
        }
        if (keep) {
            let w = o.transmittance * s.alpha;
            o.color += w * s.rgb;
            o.total += w;
            o.transmittance *= 1.0 - s.alpha;
            o.optical_depth += s.kappa * s.len;
            o.last_index = s.index;
            o.t_end = s.t_end;
            // â and â/A of the new extent (mirrors `Open::merge`).
            o.unit = one_minus_exp_neg(o.optical_depth / (o.t_end - o.t_start));
            o.unit_over_total = ratio(o.unit, o.total);
        } else {
            if (has_open) {
                store(write, &at, end, slot + n, budget, n, close(o, z_per_t));
                n += 1u;
            }
            o = open_new(s);
            has_open = true;
        }
        transmittance *= 1.0 - s.alpha;
        if (1.0 - transmittance >= termination) {
            break;
        }
    }
    if (has_open) {
        store(write, &at, end, slot + n, budget, n, close(o, z_per_t));
        n += 1u;
    }
    if (!write) {
        offsets[local] = n;
    }
}
