//! Blinn–Phong gradient shading with a headlight; only paid for when a scene turns it on.

use glam::Vec3;

/// Blinn–Phong coefficients. The light sits at the eye, so the half vector equals the light
/// direction and `n·h = n·l`; the normal is the normalised gradient, two-sided.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shading {
    /// Ambient weight.
    pub ambient: f32,
    /// Diffuse weight.
    pub diffuse: f32,
    /// Specular weight (white highlight).
    pub specular: f32,
    /// Specular exponent.
    pub shininess: f32,
}

impl Default for Shading {
    fn default() -> Self {
        Self {
            ambient: 0.3,
            diffuse: 0.7,
            specular: 0.3,
            shininess: 32.0,
        }
    }
}

impl Shading {
    /// Shades colour `rgb` given the voxel-space gradient, the ray direction (world, unit)
    /// and `1 / spacing`. A vanishing or non-finite gradient leaves the colour unshaded.
    #[inline]
    pub fn shade(
        &self,
        rgb: [f32; 3],
        gradient_voxel: Vec3,
        ray_dir: Vec3,
        inv_spacing: Vec3,
    ) -> [f32; 3] {
        let g = gradient_voxel * inv_spacing;
        let len = g.length();
        if !(len.is_finite() && len > 1e-12) {
            return rgb;
        }
        let n_dot_l = (g / len).dot(-ray_dir).abs();
        let diffuse = self.ambient + self.diffuse * n_dot_l;
        let specular = self.specular * n_dot_l.powf(self.shininess);
        rgb.map(|c| (c * diffuse + specular).clamp(0.0, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn facing_normal_gets_full_light() {
        let s = Shading::default();
        let out = s.shade([0.5, 0.5, 0.5], Vec3::Z, Vec3::NEG_Z, Vec3::ONE);
        let expect = 0.5 * (s.ambient + s.diffuse) + s.specular;
        assert!(out.iter().all(|&c| (c - expect.min(1.0)).abs() < 1e-6));
        let grazing = s.shade([0.5; 3], Vec3::X, Vec3::NEG_Z, Vec3::ONE);
        assert!(grazing.iter().all(|&c| (c - 0.5 * s.ambient).abs() < 1e-6));
        assert_eq!(s.shade([0.2; 3], Vec3::ZERO, Vec3::Z, Vec3::ONE), [0.2; 3]);
        assert_eq!(
            s.shade([0.2; 3], Vec3::splat(f32::NAN), Vec3::Z, Vec3::ONE),
            [0.2; 3]
        );
    }
}
