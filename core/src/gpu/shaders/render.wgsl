// VDI rendering I from a new camera (Sec. 3.2, Fig. 2b): mirrors `vdi::render`. A ray is
// clipped to the volume box and the generation frustum, its projection into the generation
// image is walked with a 2D DDA, and in each pixel the overlapping supersegments of the
// depth-sorted list (compact layout: prefix offsets + flat array) are composited with
// α' = 1 − (1 − â)^ℓ.

struct RenderParams {
    eye: vec4<f32>,        // new camera: xyz eye
    right: vec4<f32>,      // xyz right, w tan(fov_x / 2)
    up: vec4<f32>,         // xyz up, w tan(fov_y / 2)
    forward: vec4<f32>,    // xyz view direction, w early-termination threshold
    g_eye: vec4<f32>,      // generation camera: xyz eye
    g_right: vec4<f32>,    // xyz right, w tan(fov_x / 2)
    g_up: vec4<f32>,       // xyz up, w tan(fov_y / 2)
    g_forward: vec4<f32>,  // xyz view direction
    box_min: vec4<f32>,
    box_max: vec4<f32>,
    image: vec4<u32>,      // width, height, first row of this band, r
    band: vec4<u32>,       // x: rows in this band
};

@group(0) @binding(0) var<uniform> P: RenderParams;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> segments: array<Segment>;
@group(0) @binding(3) var<storage, read_write> image_out: array<f32>;
// Per 8×8 tile of the generation image: depth range of its supersegments (empty: [MAX, −MAX]).
@group(0) @binding(4) var<storage, read> tile_depth: array<vec2<f32>>;

struct Accum {
    color: vec3<f32>,
    transmittance: f32,
    threshold: f32,
};

// Adds a frustum passed over world length len; true when the ray is done.
fn accum_add(acc: ptr<function, Accum>, s: Segment, len: f32) -> bool {
    if (len > 0.0 && s.alpha > 0.0) {
        var alpha = 1.0;
        if (s.alpha < 1.0) {
            alpha = 1.0 - exp2(len * log2(1.0 - s.alpha));
        }
        let w = (*acc).transmittance * alpha;
        (*acc).color += w * vec3<f32>(s.r, s.g, s.b);
        (*acc).transmittance *= 1.0 - alpha;
    }
    return (*acc).transmittance <= (*acc).threshold;
}

// First index in [lo, hi) whose segment has z_end > z (lists are depth-sorted).
fn first_ending_after(lo: u32, hi: u32, z: f32) -> u32 {
    var a = lo;
    var b = hi;
    while (a < b) {
        let mid = (a + b) / 2u;
        if (segments[mid].z_end <= z) {
            a = mid + 1u;
        } else {
            b = mid;
        }
    }
    return a;
}

// First index in [lo, hi) whose segment has z_start >= z.
fn first_starting_at(lo: u32, hi: u32, z: f32) -> u32 {
    var a = lo;
    var b = hi;
    while (a < b) {
        let mid = (a + b) / 2u;
        if (segments[mid].z_start < z) {
            a = mid + 1u;
        } else {
            b = mid;
        }
    }
    return a;
}

// Composites the list [lo, hi) over ray parameters [ta, tb], generation depth z0 + z1·t.
fn composite_span(lo: u32, hi: u32, z0: f32, z1: f32, ta: f32, tb: f32, acc: ptr<function, Accum>) -> bool {
    let span = tb - ta;
    let za = z0 + z1 * ta;
    let zb = z0 + z1 * tb;
    if (z1 > 0.0) {
        for (var k = first_ending_after(lo, hi, za); k < hi; k++) {
            let s = segments[k];
            if (s.z_start >= zb) {
                break;
            }
            let len = clamp((min(s.z_end, zb) - max(s.z_start, za)) / z1, 0.0, span);
            if (accum_add(acc, s, len)) {
                return true;
            }
        }
    } else if (z1 < 0.0) {
        var k = first_starting_at(lo, hi, za);
        while (k > lo) {
            k -= 1u;
            let s = segments[k];
            if (s.z_end <= zb) {
                break;
            }
            let len = clamp((min(s.z_end, za) - max(s.z_start, zb)) / -z1, 0.0, span);
            if (accum_add(acc, s, len)) {
                return true;
            }
        }
    } else {
        let k = first_ending_after(lo, hi, za);
        if (k < hi) {
            let s = segments[k];
            if (s.z_start <= za && accum_add(acc, s, span)) {
                return true;
            }
        }
    }
    return false;
}

fn direction(d: f32) -> i32 {
    if (d > 1e-3) {
        return 1;
    } else if (d < -1e-3) {
        return -1;
    }
    return 0;
}

fn start_cell(p: f32, step: i32, r: i32) -> i32 {
    var c: i32;
    if (step < 0) {
        c = i32(ceil(p)) - 1;
    } else {
        c = i32(floor(p));
    }
    return clamp(c, 0, r - 1);
}

// Side, in generation pixels, of the tiles the walk skips when they are empty.
const SKIP_TILE: i32 = 8;

// The eye-space slope x/z (sign 1) or y/z (sign −1, rows grow downwards) of pixel boundary b.
fn boundary(b: i32, r: f32, tan_half: f32, sign: f32) -> f32 {
    return sign * (2.0 * f32(b) / r - 1.0) * tan_half;
}

// Crossings behind the clipped segment are none; one a rounding error behind t is now.
fn guard(tc: f32, t0: f32, t: f32) -> f32 {
    if (is_nan_f(tc) || tc < t0) {
        return BIG;
    }
    return max(tc, t);
}

// Where the ray leaves pixel column (or row) i stepping by `step`; BIG for no step.
fn next_crossing(i: i32, step: i32, r: f32, tan_half: f32, z0: f32, z1: f32, a0: f32, a1: f32, sign: f32) -> f32 {
    if (step == 0) {
        return BIG;
    }
    return crossing(boundary(i + select(0, 1, step > 0), r, tan_half, sign), z0, z1, a0, a1);
}

// Solution t of (s·z0 − a0) / (a1 − s·z1), or BIG where there is none.
fn crossing(s: f32, z0: f32, z1: f32, a0: f32, a1: f32) -> f32 {
    let den = a1 - s * z1;
    if (den == 0.0) {
        return BIG;
    }
    return (s * z0 - a0) / den;
}

fn walk(origin: vec3<f32>, dir: vec3<f32>, acc: ptr<function, Accum>) {
    let hit = intersect_box(origin, dir, P.box_min.xyz, P.box_max.xyz);
    var t0 = max(hit.x, 0.0);
    var t1 = hit.y;
    let d = origin - P.g_eye.xyz;
    let x0 = dot(d, P.g_right.xyz);
    let y0 = dot(d, P.g_up.xyz);
    let z0 = dot(d, P.g_forward.xyz);
    let x1 = dot(dir, P.g_right.xyz);
    let y1 = dot(dir, P.g_up.xyz);
    let z1 = dot(dir, P.g_forward.xyz);
    let tx = P.g_right.w;
    let ty = P.g_up.w;
    // Frustum planes f0 + f1·t ≥ 0.
    var f0 = array<f32, 5>(tx * z0 - x0, tx * z0 + x0, ty * z0 - y0, ty * z0 + y0, z0 - 1e-6);
    var f1 = array<f32, 5>(tx * z1 - x1, tx * z1 + x1, ty * z1 - y1, ty * z1 + y1, z1);
    for (var k = 0; k < 5; k++) {
        if (f1[k] > 0.0) {
            t0 = max(t0, -f0[k] / f1[k]);
        } else if (f1[k] < 0.0) {
            t1 = min(t1, -f0[k] / f1[k]);
        } else if (f0[k] < 0.0) {
            return;
        }
    }
    if (is_nan_f(t0) || is_nan_f(t1) || t1 <= t0) {
        return;
    }
    let ri = i32(P.image.w);
    let r = f32(P.image.w);
    let px0 = (((x0 + x1 * t0) / ((z0 + z1 * t0) * tx)) + 1.0) * 0.5 * r;
    let py0 = (1.0 - (y0 + y1 * t0) / ((z0 + z1 * t0) * ty)) * 0.5 * r;
    let px1 = (((x0 + x1 * t1) / ((z0 + z1 * t1) * tx)) + 1.0) * 0.5 * r;
    let py1 = (1.0 - (y0 + y1 * t1) / ((z0 + z1 * t1) * ty)) * 0.5 * r;
    let step_x = direction(px1 - px0);
    let step_y = direction(py1 - py0);
    var ix = start_cell(px0, step_x, ri);
    var iy = start_cell(py0, step_y, ri);
    let tiles_x = (ri + SKIP_TILE - 1) / SKIP_TILE;
    var raw_x = next_crossing(ix, step_x, r, tx, z0, z1, x0, x1, 1.0);
    var raw_y = next_crossing(iy, step_y, r, ty, z0, z1, y0, y1, -1.0);
    var t = t0;
    var walking = -1;  // the tile whose pixels are being walked
    let max_iter = 2 * ri + 4;
    for (var it = 0; it < max_iter; it++) {
        let tile = ix / SKIP_TILE + tiles_x * (iy / SKIP_TILE);
        if (tile != walking) {
            // Entering a tile: where does the ray leave it, and does its depth over the tile
            // meet the tile's supersegments? (mirrors the CPU walk)
            let x0t = ix / SKIP_TILE * SKIP_TILE;
            let y0t = iy / SKIP_TILE * SKIP_TILE;
            var ex = BIG;
            if (step_x != 0) {
                let b = select(x0t, x0t + SKIP_TILE, step_x > 0);
                ex = guard(crossing(boundary(b, r, tx, 1.0), z0, z1, x0, x1), t0, t);
            }
            var ey = BIG;
            if (step_y != 0) {
                let b = select(y0t, y0t + SKIP_TILE, step_y > 0);
                ey = guard(crossing(boundary(b, r, ty, -1.0), z0, z1, y0, y1), t0, t);
            }
            let t_next = min(min(ex, ey), t1);
            let range = tile_depth[u32(tile)];
            let za = z0 + z1 * t;
            let zb = z0 + z1 * t_next;
            let margin = 1e-5 * max(abs(za), abs(zb));
            if (!(min(za, zb) > range.y + margin || max(za, zb) < range.x - margin)) {
                walking = tile;
            } else {
                if (t_next >= t1) {
                    return;
                }
                let z_at = z0 + z1 * t_next;
                if (ex <= ey) {
                    ix = select(x0t - 1, x0t + SKIP_TILE, step_x > 0);
                    let py = (1.0 - (y0 + y1 * t_next) / (z_at * ty)) * 0.5 * r;
                    iy = clamp(start_cell(py, step_y, ri), y0t, y0t + SKIP_TILE - 1);
                } else {
                    iy = select(y0t - 1, y0t + SKIP_TILE, step_y > 0);
                    let px = ((x0 + x1 * t_next) / (z_at * tx) + 1.0) * 0.5 * r;
                    ix = clamp(start_cell(px, step_x, ri), x0t, x0t + SKIP_TILE - 1);
                }
                if (ix < 0 || ix >= ri || iy < 0 || iy >= ri) {
                    return;
                }
                t = t_next;
                raw_x = next_crossing(ix, step_x, r, tx, z0, z1, x0, x1, 1.0);
                raw_y = next_crossing(iy, step_y, r, ty, z0, z1, y0, y1, -1.0);
                continue;
            }
        }
        let tnx = guard(raw_x, t0, t);
        let tny = guard(raw_y, t0, t);
        let t_next = min(min(tnx, tny), t1);
        if (t_next > t) {
            let p = u32(ix) + P.image.w * u32(iy);
            let lo = offsets[p];
            let hi = offsets[p + 1u];
            if (hi > lo && composite_span(lo, hi, z0, z1, t, t_next, acc)) {
                return;
            }
        }
        if (t_next >= t1) {
            return;
        }
        if (tnx <= tny) {
            ix += step_x;
            raw_x = next_crossing(ix, step_x, r, tx, z0, z1, x0, x1, 1.0);
        } else {
            iy += step_y;
            raw_y = next_crossing(iy, step_y, r, ty, z0, z1, y0, y1, -1.0);
        }
        if (ix < 0 || ix >= ri || iy < 0 || iy >= ri) {
            return;
        }
        t = t_next;
    }
}

@compute @workgroup_size(8, 8)
fn render_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let row = gid.y;
    let j = P.image.z + row;
    if (i >= P.image.x || j >= P.image.y || row >= P.band.x) {
        return;
    }
    let w = f32(P.image.x);
    let h = f32(P.image.y);
    let sx = (2.0 * (f32(i) + 0.5) / w - 1.0) * P.right.w;
    let sy = (1.0 - 2.0 * (f32(j) + 0.5) / h) * P.up.w;
    let dir = normalize(P.forward.xyz + sx * P.right.xyz + sy * P.up.xyz);
    var acc = Accum(vec3<f32>(0.0), 1.0, 1.0 - P.forward.w);
    walk(P.eye.xyz, dir, &acc);
    let color = clamp(acc.color, vec3<f32>(0.0), vec3<f32>(1.0));
    let o = 3u * (i + P.image.x * row);
    image_out[o] = color.x;
    image_out[o + 1u] = color.y;
    image_out[o + 2u] = color.z;
}
