//! Perspective cameras and primary rays (docs/conventions.md, "Camera").
//!
//! The default camera looks along −z at the centre of the volume box from `R / sin(15°)`
//! (`R` the half-diagonal), with a 30° vertical field of view and +y up, so the whole box is
//! in view. A view "at angle θ" orbits that camera about the box centre around +y by θ
//! degrees. Image row 0 is the top; pixel `(i, j)` is sampled at its centre `(i + ½, j + ½)`.

use crate::volume::Aabb;
use glam::{Quat, Vec3};

/// A perspective camera. Eye-space z is the distance along the view direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position, world units.
    pub eye: Vec3,
    /// Point looked at.
    pub target: Vec3,
    /// Up hint (need not be orthogonal to the view direction).
    pub up: Vec3,
    /// Vertical field of view, degrees, in (0, 180).
    pub fov_y_deg: f32,
}

/// A ray with unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Start point, world units.
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
}

/// Orthonormal view frame and image-plane scale of a camera for one image size.
#[derive(Clone, Copy, Debug)]
pub struct ViewFrame {
    /// Eye position.
    pub eye: Vec3,
    /// Image-right axis.
    pub right: Vec3,
    /// Image-up axis.
    pub up: Vec3,
    /// View direction.
    pub forward: Vec3,
    /// `tan(fov_x / 2)`: x/z at the right image edge.
    pub tan_half_x: f32,
    /// `tan(fov_y / 2)`: y/z at the top image edge.
    pub tan_half_y: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// The default view of a box: see the module documentation.
    pub fn default_for_box(b: &Aabb) -> Self {
        let c = b.center();
        let r = b.half_diagonal().max(1e-3);
        let dist = r / 15f32.to_radians().sin();
        Self {
            eye: c + Vec3::new(0.0, 0.0, dist),
            target: c,
            up: Vec3::Y,
            fov_y_deg: 30.0,
        }
    }

    /// This camera orbited about its target around +y by `angle_deg` degrees.
    pub fn orbit_y(&self, angle_deg: f32) -> Self {
        let q = Quat::from_rotation_y(angle_deg.to_radians());
        Self {
            eye: self.target + q * (self.eye - self.target),
            up: q * self.up,
            ..*self
        }
    }

    /// This camera orbited about its target: by `angle_deg` around +y (as [`Self::orbit_y`])
    /// and by `elevation_deg` up (positive: looking down from above) about the view's
    /// right axis, with the eye–target distance scaled by `zoom` (> 1 moves away). The up
    /// vector follows the elevation, so views over the pole stay valid. `orbit(a, 0, 1)` is
    /// `orbit_y(a)`. Angles are degrees; a non-finite input gives an invalid camera (see
    /// [`Self::is_valid`]).
    pub fn orbit(&self, angle_deg: f32, elevation_deg: f32, zoom: f32) -> Self {
        let offset = self.eye - self.target;
        let right = offset.cross(self.up).normalize_or_zero();
        let tilt = Quat::from_axis_angle(right, elevation_deg.to_radians());
        let spin = Quat::from_rotation_y(angle_deg.to_radians());
        let q = spin * tilt;
        Self {
            eye: self.target + q * offset * zoom,
            up: q * self.up,
            ..*self
        }
    }

    /// The zoom, a scale of this camera's eye–target distance as [`Self::orbit`] applies it,
    /// at which every corner of `b` projects within `margin` (in (0, 1]) of the half extents
    /// of a `width × height` image: the view that fits the box, its direction kept. For a
    /// corner `c` (relative to the target) with view coordinates `x`, `y` and depth `f` along
    /// the view direction, the depth at zoom `s` is `f + d·s`, and `|x| ≤ margin·tan(fov_x/2)·
    /// (f + d·s)` gives `s ≥ (|x| / (margin·tan(fov_x/2)) − f) / d` (the same on y); the
    /// answer is the largest bound over the corners. 1 for an invalid camera or box.
    pub fn fit_zoom(&self, b: &Aabb, width: u32, height: u32, margin: f32) -> f32 {
        let d = (self.eye - self.target).length();
        let margin = margin.clamp(1e-3, 1.0);
        if !(self.is_valid() && d > 0.0 && b.min.is_finite() && b.max.is_finite()) {
            return 1.0;
        }
        let f = self.frame(width, height);
        let (tx, ty) = (margin * f.tan_half_x, margin * f.tan_half_y);
        let fit = b
            .corners()
            .into_iter()
            .map(|corner| {
                let corner = corner - self.target;
                let depth = corner.dot(f.forward);
                let need = (corner.dot(f.right).abs() / tx).max(corner.dot(f.up).abs() / ty);
                (need - depth) / d
            })
            .fold(f32::MIN, f32::max);
        if fit.is_finite() && fit > 0.0 {
            fit
        } else {
            1.0
        }
    }

    /// Whether the camera is usable: finite, eye ≠ target, up not parallel to the view
    /// direction, field of view in (0, 180).
    pub fn is_valid(&self) -> bool {
        let f = self.target - self.eye;
        self.eye.is_finite()
            && self.target.is_finite()
            && self.up.is_finite()
            && f.length() > 0.0
            && f.normalize().cross(self.up).length() > 1e-6
            && self.fov_y_deg.is_finite()
            && self.fov_y_deg > 0.0
            && self.fov_y_deg < 180.0
    }

    /// The view frame for a `width × height` image.
    pub fn frame(&self, width: u32, height: u32) -> ViewFrame {
        let forward = (self.target - self.eye).normalize_or(Vec3::NEG_Z);
        let right = forward.cross(self.up).normalize_or(Vec3::X);
        let up = right.cross(forward);
        let tan_half_y = (0.5 * self.fov_y_deg.to_radians()).tan();
        let aspect = width.max(1) as f32 / height.max(1) as f32;
        ViewFrame {
            eye: self.eye,
            right,
            up,
            forward,
            tan_half_x: tan_half_y * aspect,
            tan_half_y,
            width,
            height,
        }
    }
}

impl ViewFrame {
    /// The primary ray through image position `(px, py)` in pixels (row 0 at the top).
    #[inline]
    pub fn ray(&self, px: f32, py: f32) -> Ray {
        let sx = (2.0 * px / self.width as f32 - 1.0) * self.tan_half_x;
        let sy = (1.0 - 2.0 * py / self.height as f32) * self.tan_half_y;
        Ray {
            origin: self.eye,
            dir: (self.forward + sx * self.right + sy * self.up).normalize(),
        }
    }

    /// The primary ray through the centre of pixel `(i, j)`.
    #[inline]
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        self.ray(i as f32 + 0.5, j as f32 + 0.5)
    }

    /// The pixels whose centre rays ([`ViewFrame::pixel_ray`]) can meet `b`: the bounding
    /// rectangle of its projected corners, a pixel wider on every side than rounding could
    /// move a silhouette, as half-open ranges `(x0..x1, y0..y1)`; the whole image when a corner
    /// is not clearly in front of the eye (the projection does not bound the rays there).
    pub fn footprint(&self, b: &Aabb) -> (std::ops::Range<u32>, std::ops::Range<u32>) {
        let whole = (0..self.width, 0..self.height);
        let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for corner in b.corners() {
            let e = self.to_eye(corner);
            // In front by more than a thousandth of the corner's distance (NaN is not).
            if e.z.partial_cmp(&(1e-3 * e.length())) != Some(std::cmp::Ordering::Greater) {
                return whole;
            }
            let Some((x, y)) = self.project(corner) else {
                return whole;
            };
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
        if !(x0.is_finite() && x1.is_finite() && y0.is_finite() && y1.is_finite()) {
            return whole;
        }
        let range = |lo: f32, hi: f32, n: u32| {
            let lo = (lo.floor() - 1.0).clamp(0.0, n as f32) as u32;
            let hi = (hi.ceil() + 1.0).clamp(0.0, n as f32) as u32;
            lo..hi.max(lo)
        };
        (range(x0, x1, self.width), range(y0, y1, self.height))
    }

    /// Eye-space coordinates `(x, y, z)` of a world point.
    #[inline]
    pub fn to_eye(&self, p: Vec3) -> Vec3 {
        let d = p - self.eye;
        Vec3::new(d.dot(self.right), d.dot(self.up), d.dot(self.forward))
    }

    /// Pixel coordinates of a world point in front of the camera, or `None` if `z ≤ 0`.
    pub fn project(&self, p: Vec3) -> Option<(f32, f32)> {
        let e = self.to_eye(p);
        (e.z > 0.0).then(|| {
            (
                (e.x / (e.z * self.tan_half_x) + 1.0) * 0.5 * self.width as f32,
                (1.0 - e.y / (e.z * self.tan_half_y)) * 0.5 * self.height as f32,
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_zoom_frames_the_box_head_on_and_from_any_side() {
        // A cube of side 2 at the origin seen head-on from +z at distance 10, fov 30°: its
        // near face (depth −1 along the view) needs tan(15°)·(10 s − 1) = 1.
        let cube = Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        };
        let cam = Camera {
            eye: Vec3::new(0.0, 0.0, 10.0),
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg: 30.0,
        };
        let s = cam.fit_zoom(&cube, 64, 64, 1.0);
        let expect = (1.0 / 15f32.to_radians().tan() + 1.0) / 10.0;
        assert!((s - expect).abs() < 1e-5, "{s} vs {expect}");
        // A wide image fits on y; a margin moves the eye back by its inverse, nearly.
        assert!((cam.fit_zoom(&cube, 128, 64, 1.0) - expect).abs() < 1e-5);
        assert!(cam.fit_zoom(&cube, 64, 64, 0.9) > s);
        // From any orbit, at the fit the box's footprint touches the frame's edge and stays inside.
        for (angle, elevation) in [(0.0, 0.0), (30.0, 20.0), (135.0, -60.0), (270.0, 89.0)] {
            let view = cam.orbit(angle, elevation, 1.0);
            let fitted = view.orbit(0.0, 0.0, view.fit_zoom(&cube, 100, 100, 1.0));
            let (xs, ys) = fitted.frame(100, 100).footprint(&cube);
            assert!(
                xs.start <= 2 || ys.start <= 2,
                "{angle} {elevation}: {xs:?} {ys:?}"
            );
            assert!(
                xs.end >= 98 || ys.end >= 98,
                "{angle} {elevation}: {xs:?} {ys:?}"
            );
        }
        // The default camera of a box shows it with room around it; the fit is closer.
        let default = Camera::default_for_box(&cube);
        assert!(default.fit_zoom(&cube, 64, 64, 0.95) < 1.0);
        // Nonsense in, no zoom change out.
        let nan = Aabb {
            min: Vec3::NAN,
            max: Vec3::ONE,
        };
        assert_eq!(cam.fit_zoom(&nan, 64, 64, 1.0), 1.0);
    }

    fn unit_box() -> Aabb {
        Aabb {
            min: Vec3::ZERO,
            max: Vec3::new(10.0, 20.0, 30.0),
        }
    }

    /// Every pixel whose centre ray meets the box lies in the footprint; boxes partly behind
    /// the eye or around it give the whole image.
    #[test]
    fn the_footprint_holds_every_pixel_whose_ray_meets_the_box() {
        let volume = unit_box();
        let small = Aabb {
            min: Vec3::new(7.0, 2.0, 20.0),
            max: Vec3::new(9.5, 6.0, 23.0),
        };
        let c = Camera::default_for_box(&volume);
        let (w, h) = (64, 40);
        let mut smaller = 0;
        for (b, camera) in [
            (small, c),
            (small, c.orbit_y(35.0)),
            (small, c.orbit(200.0, 40.0, 1.0)),
            (volume, c.orbit_y(90.0)),
            (volume, c.orbit(10.0, -30.0, 0.3)),
            (small, c.orbit(300.0, 10.0, 4.0)),
        ] {
            let f = camera.frame(w, h);
            let (xs, ys) = f.footprint(&b);
            let mut hits = 0;
            for j in 0..h {
                for i in 0..w {
                    let ray = f.pixel_ray(i, j);
                    let (near, far) = b.intersect(ray.origin, ray.dir.recip());
                    if far > near.max(0.0) {
                        hits += 1;
                        assert!(
                            xs.contains(&i) && ys.contains(&j),
                            "{camera:?}: pixel ({i}, {j}) meets the box outside {xs:?} × {ys:?}"
                        );
                    }
                }
            }
            assert!(hits > 0, "{camera:?}: the box is in view");
            smaller += usize::from(xs.len() * ys.len() < (w * h) as usize);
        }
        assert!(
            smaller >= 4,
            "the footprints bound: {smaller} of 6 below the image"
        );
        // The eye inside the box, or a corner behind it: the whole image.
        let mut inside = c;
        inside.eye = small.center();
        assert_eq!(inside.frame(w, h).footprint(&small), (0..w, 0..h));
        let mut behind = c;
        behind.eye = Vec3::new(small.min.x - 0.1, 4.0, 21.5);
        behind.target = behind.eye + Vec3::Z;
        behind.up = Vec3::Y;
        assert_eq!(behind.frame(w, h).footprint(&small), (0..w, 0..h));
    }

    #[test]
    fn orbit_tilts_up_keeps_or_scales_the_distance_and_stays_valid_over_the_pole() {
        let c = Camera::default_for_box(&unit_box());
        let d = (c.eye - c.target).length();
        for a in [-170.0, -30.0, 0.0, 45.0, 180.0] {
            let (o, y) = (c.orbit(a, 0.0, 1.0), c.orbit_y(a));
            assert!((o.eye - y.eye).length() < 1e-3 * d && (o.up - y.up).length() < 1e-5);
        }
        let up30 = c.orbit(0.0, 30.0, 1.0);
        assert!(((up30.eye - c.target).length() - d).abs() < 1e-3 * d);
        assert!(
            ((up30.eye.y - c.target.y) - d * 0.5).abs() < 1e-3 * d,
            "{up30:?}"
        );
        for (e, z) in [(90.0, 2.0), (-90.0, 0.5), (135.0, 1.0)] {
            let o = c.orbit(20.0, e, z);
            assert!(o.is_valid(), "{e}° {z}×: {o:?}");
            assert!(((o.eye - o.target).length() - d * z).abs() < 1e-3 * d);
            assert!((o.target - o.eye).normalize().dot(o.up).abs() < 1e-5);
        }
        assert!(!c.orbit(f32::NAN, 0.0, 1.0).is_valid());
    }

    #[test]
    fn default_camera_sees_the_whole_box() {
        let b = unit_box();
        let cam = Camera::default_for_box(&b);
        let f = cam.frame(64, 64);
        for i in 0..8 {
            let corner = Vec3::new(
                if i & 1 == 0 { b.min.x } else { b.max.x },
                if i & 2 == 0 { b.min.y } else { b.max.y },
                if i & 4 == 0 { b.min.z } else { b.max.z },
            );
            for angle in [0.0, 45.0, 90.0, 180.0] {
                let f = cam.orbit_y(angle).frame(64, 64);
                let (px, py) = f.project(corner).unwrap();
                assert!((0.0..=64.0).contains(&px) && (0.0..=64.0).contains(&py));
            }
        }
        // Looking along −z, +y up.
        assert!((f.forward - Vec3::NEG_Z).length() < 1e-6);
        assert!((f.up - Vec3::Y).length() < 1e-6);
    }

    #[test]
    fn pixel_rays_project_back_to_their_pixel() {
        let cam = Camera::default_for_box(&unit_box()).orbit_y(30.0);
        let f = cam.frame(40, 30);
        for (i, j) in [(0, 0), (39, 29), (20, 3)] {
            let r = f.pixel_ray(i, j);
            let (px, py) = f.project(r.origin + 50.0 * r.dir).unwrap();
            assert!((px - (i as f32 + 0.5)).abs() < 1e-3 && (py - (j as f32 + 0.5)).abs() < 1e-3);
        }
        // Row 0 is the top: its ray points up.
        assert!(f.pixel_ray(20, 0).dir.y > 0.0);
    }

    #[test]
    fn orbit_keeps_distance_and_target() {
        let cam = Camera::default_for_box(&unit_box());
        let o = cam.orbit_y(180.0);
        assert!(((o.eye - o.target).length() - (cam.eye - cam.target).length()).abs() < 1e-3);
        assert!((o.frame(8, 8).forward - Vec3::Z).length() < 1e-5);
        assert!(cam.is_valid());
        assert!(!Camera {
            up: Vec3::NEG_Z,
            ..cam
        }
        .is_valid());
    }
}
