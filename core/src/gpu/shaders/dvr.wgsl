// Reference DVR: one invocation per pixel of a band of rows, front-to-back emission–absorption
// compositing with early ray termination (mirrors `dvr::render`). Output: RGB f32 per pixel.

@group(1) @binding(0) var<storage, read_write> image_out: array<f32>;

@compute @workgroup_size(8, 8)
fn dvr_main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let row = gid.y;
    let j = P.image.z + row;
    if (i >= P.image.x || j >= P.image.y || row >= P.band.x) {
        return;
    }
    let ray = pixel_ray(i, j);
    var m = marcher_new(ray);
    var s: Sample;
    var color = vec3<f32>(0.0);
    var transmittance = 1.0;
    let termination = P.box_min.w;
    while (marcher_next(&m, &s)) {
        color += (transmittance * s.alpha) * s.rgb;
        transmittance *= 1.0 - s.alpha;
        if (1.0 - transmittance >= termination) {
            break;
        }
    }
    color = clamp(color, vec3<f32>(0.0), vec3<f32>(1.0));
    let o = 3u * (i + P.image.x * row);
    image_out[o] = color.x;
    image_out[o + 1u] = color.y;
    image_out[o + 2u] = color.z;
}
