// Shared by the DVR and VDI-generation kernels: scene bindings, primary rays and the ray
// marcher. Mirrors `raycast::Raycaster::march_impl` operation for operation, so the GPU visits
// the same samples as the CPU (up to float rounding and fused multiply-adds).

const LUT_LAST: f32 = 4095.0;

struct Params {
    eye: vec4<f32>,          // xyz eye
    right: vec4<f32>,        // xyz right, w tan(fov_x / 2)
    up: vec4<f32>,           // xyz up, w tan(fov_y / 2)
    forward: vec4<f32>,      // xyz view direction, w ray-casting step Δ (world units)
    box_min: vec4<f32>,      // xyz volume box min, w early-termination threshold
    box_max: vec4<f32>,      // xyz volume box max, w interrupt threshold γ
    inv_spacing: vec4<f32>,  // xyz 1 / spacing, w lut domain low end
    max_voxel: vec4<f32>,    // xyz dims − 1, w lut scale (entries per data unit)
    shading: vec4<f32>,      // ambient, diffuse, specular, shininess
    dims: vec4<u32>,         // nx, ny, nz, empty-space skipping on (1) / off (0)
    cells: vec4<u32>,        // macro cells per axis, w their side in voxels
    image: vec4<u32>,        // width, height, first row of this band, work (0 DVR, 1 count, 2 write)
    band: vec4<u32>,         // rows in this band; generation: its first row within the counted
                             // band, the offset of its first supersegment, per-ray slots
};

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var volume: texture_3d<f32>;
@group(0) @binding(2) var tf_color: texture_1d<f32>;       // rgb, opacity per unit length a
@group(0) @binding(3) var tf_extinction: texture_1d<f32>;  // κ (clamped finite), α of a full step
@group(0) @binding(4) var<storage, read> macro_visible: array<u32>;

// Blinn–Phong shading is compiled in only when the scene turns it on.
override SHADE: bool = false;

// e^x − 1 without cancellation for small |x| (Kahan's trick on top of exp/log).
fn expm1_f(x: f32) -> f32 {
    if (abs(x) < 1e-5) {
        return x + 0.5 * x * x;
    }
    let u = exp(x);
    if (u == 1.0) {
        return x;
    }
    let um1 = u - 1.0;
    if (um1 == -1.0) {
        return -1.0;
    }
    return um1 * x / log(u);
}

struct Ray {
    origin: vec3<f32>,
    dir: vec3<f32>,
};

// The primary ray through the centre of pixel (i, j) of a width × height image.
fn pixel_ray(i: u32, j: u32) -> Ray {
    let w = f32(P.image.x);
    let h = f32(P.image.y);
    let sx = (2.0 * (f32(i) + 0.5) / w - 1.0) * P.right.w;
    let sy = (1.0 - 2.0 * (f32(j) + 0.5) / h) * P.up.w;
    return Ray(P.eye.xyz, normalize(P.forward.xyz + sx * P.right.xyz + sy * P.up.xyz));
}

fn voxel(x: u32, y: u32, z: u32) -> f32 {
    return textureLoad(volume, vec3<u32>(x, y, z), 0).x;
}

// Trilinear value at clamped voxel-space p with lower corner c; NaN if any corner is NaN.
fn trilinear(c: vec3<u32>, f: vec3<f32>) -> f32 {
    let n1 = P.dims.xyz - vec3<u32>(1u);
    let d = min(c + vec3<u32>(1u), n1);
    let v000 = voxel(c.x, c.y, c.z);
    let v100 = voxel(d.x, c.y, c.z);
    let v010 = voxel(c.x, d.y, c.z);
    let v110 = voxel(d.x, d.y, c.z);
    let v001 = voxel(c.x, c.y, d.z);
    let v101 = voxel(d.x, c.y, d.z);
    let v011 = voxel(c.x, d.y, d.z);
    let v111 = voxel(d.x, d.y, d.z);
    if (is_nan_f(v000) || is_nan_f(v100) || is_nan_f(v010) || is_nan_f(v110)
        || is_nan_f(v001) || is_nan_f(v101) || is_nan_f(v011) || is_nan_f(v111)) {
        return bitcast<f32>(0x7fc00000u);
    }
    let c00 = v000 + f.x * (v100 - v000);
    let c10 = v010 + f.x * (v110 - v010);
    let c01 = v001 + f.x * (v101 - v001);
    let c11 = v011 + f.x * (v111 - v011);
    let c0 = c00 + f.y * (c10 - c00);
    let c1 = c01 + f.y * (c11 - c01);
    return c0 + f.z * (c1 - c0);
}

fn lower_corner(p: vec3<f32>) -> vec3<u32> {
    let top = max(P.dims.xyz, vec3<u32>(2u)) - vec3<u32>(2u);
    return min(vec3<u32>(p), top);
}

fn sample_value(q: vec3<f32>) -> f32 {
    let p = clamp(q, vec3<f32>(0.0), P.max_voxel.xyz);
    let c = lower_corner(p);
    return trilinear(c, p - vec3<f32>(c));
}

fn macro_index(c: vec3<u32>) -> u32 {
    let m = c / P.cells.w;
    return m.x + P.cells.x * (m.y + P.cells.y * m.z);
}

// Ray parameter where o_v + t·d_v leaves the macro cell owning lower corner c.
fn cell_exit(c: vec3<u32>, o_v: vec3<f32>, d_v: vec3<f32>) -> f32 {
    let lo = vec3<f32>((c / P.cells.w) * P.cells.w);
    let hi = lo + vec3<f32>(f32(P.cells.w));
    var t = BIG;
    for (var a = 0; a < 3; a++) {
        if (d_v[a] > 0.0) {
            t = min(t, (hi[a] - o_v[a]) / d_v[a]);
        } else if (d_v[a] < 0.0) {
            t = min(t, (lo[a] - o_v[a]) / d_v[a]);
        }
    }
    return t;
}

fn shade(rgb: vec3<f32>, p: vec3<f32>, dir: vec3<f32>) -> vec3<f32> {
    let h = 0.5;
    let gv = vec3<f32>(
        sample_value(p + vec3<f32>(h, 0.0, 0.0)) - sample_value(p - vec3<f32>(h, 0.0, 0.0)),
        sample_value(p + vec3<f32>(0.0, h, 0.0)) - sample_value(p - vec3<f32>(0.0, h, 0.0)),
        sample_value(p + vec3<f32>(0.0, 0.0, h)) - sample_value(p - vec3<f32>(0.0, 0.0, h)),
    ) / (2.0 * h);
    let g = gv * P.inv_spacing.xyz;
    if (is_nan_f(g.x) || is_nan_f(g.y) || is_nan_f(g.z)) {
        return rgb;
    }
    let len = length(g);
    if (!(len > 1e-12) || len > BIG) {
        return rgb;
    }
    let n_dot_l = abs(dot(g / len, -dir));
    let diffuse = P.shading.x + P.shading.y * n_dot_l;
    let specular = P.shading.z * pow(n_dot_l, P.shading.w);
    return clamp(rgb * diffuse + vec3<f32>(specular), vec3<f32>(0.0), vec3<f32>(1.0));
}

struct Marcher {
    dir: vec3<f32>,
    o_v: vec3<f32>,
    d_v: vec3<f32>,
    t_in: f32,
    t_far: f32,
    n_full: u32,
    n_full_f: f32,
    rem: f32,
    n_samples: u32,
    k: u32,
};

struct Sample {
    index: u32,
    t_start: f32,
    t_end: f32,
    len: f32,
    rgb: vec3<f32>,
    alpha_unit: f32,
    kappa: f32,
    alpha: f32,
};

fn marcher_new(ray: Ray) -> Marcher {
    var m: Marcher;
    m.dir = ray.dir;
    m.k = 0u;
    m.n_samples = 0u;
    let hit = intersect_box(ray.origin, ray.dir, P.box_min.xyz, P.box_max.xyz);
    let t_in = max(hit.x, 0.0);
    if (is_nan_f(hit.y) || is_nan_f(t_in) || hit.y <= t_in) {
        return m;
    }
    let step = P.forward.w;
    let length = hit.y - t_in;
    m.t_in = t_in;
    m.t_far = hit.y;
    m.n_full_f = min(floor(length / step), 2147483647.0);
    m.n_full = u32(m.n_full_f);
    m.rem = length - m.n_full_f * step;
    m.n_samples = m.n_full + select(0u, 1u, m.rem > step * 1e-4);
    m.o_v = (ray.origin - P.box_min.xyz) * P.inv_spacing.xyz;
    m.d_v = ray.dir * P.inv_spacing.xyz;
    return m;
}

// Advances to the next non-transparent sample; false when the ray has left the volume.
fn marcher_next(m: ptr<function, Marcher>, s: ptr<function, Sample>) -> bool {
    let step = P.forward.w;
    loop {
        let k = (*m).k;
        if (k >= (*m).n_samples) {
            return false;
        }
        var t0: f32;
        var t1: f32;
        var len: f32;
        if (k + 1u < (*m).n_full) {
            t0 = (*m).t_in + f32(k) * step;
            t1 = (*m).t_in + f32(k + 1u) * step;
            len = step;
        } else if (k + 1u == (*m).n_full) {
            t0 = (*m).t_in + f32(k) * step;
            t1 = select((*m).t_far, (*m).t_in + (*m).n_full_f * step, (*m).n_samples > (*m).n_full);
            len = step;
        } else {
            t0 = (*m).t_in + (*m).n_full_f * step;
            t1 = (*m).t_far;
            len = (*m).rem;
        }
        let p = clamp((*m).o_v + (t0 + 0.5 * len) * (*m).d_v, vec3<f32>(0.0), P.max_voxel.xyz);
        let c = lower_corner(p);
        if (P.dims.w != 0u && macro_visible[macro_index(c)] == 0u) {
            let t_exit = cell_exit(c, (*m).o_v, (*m).d_v);
            // The CPU marcher's margin: never skip a sample outside the cell.
            let margin = 0.125 * step + 1e-5 * abs(t_exit);
            let k_first = ceil((t_exit - margin - (*m).t_in) / step - 0.5);
            (*m).k = max(k + 1u, u32(clamp(k_first, 0.0, f32((*m).n_samples))));
            continue;
        }
        let v = trilinear(c, p - vec3<f32>(c));
        (*m).k = k + 1u;
        if (is_nan_f(v)) {
            continue;
        }
        let x = clamp((v - P.inv_spacing.w) * P.max_voxel.w, 0.0, LUT_LAST);
        let idx = u32(x + 0.5);
        let ext = textureLoad(tf_extinction, idx, 0);
        let kappa = ext.x;
        if (!(kappa > 0.0)) {
            continue;
        }
        var alpha: f32;
        if (len == step) {
            alpha = ext.y;
        } else {
            alpha = -expm1_f(-kappa * len);
        }
        if (!(alpha > 0.0)) {
            continue;
        }
        let col = textureLoad(tf_color, idx, 0);
        var rgb = col.xyz;
        if (SHADE) {
            rgb = shade(rgb, p, (*m).dir);
        }
        *s = Sample(k, t0, t1, len, rgb, col.w, kappa, alpha);
        return true;
    }
    return false;
}
