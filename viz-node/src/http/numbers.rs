//! Numbers of the viewer's requests, read as the f64 they are written as and then narrowed,
//! so that a value beyond `f32` is named as given (`1e308`), not as the `inf` it would become.

use serde::{de::Error, Deserialize, Deserializer};

/// Largest orbit angle taken, degrees (a million: thousands of turns, each still exact).
pub const MAX_ANGLE_DEG: f64 = 1e6;

/// An orbit angle, degrees, within ±[`MAX_ANGLE_DEG`], reduced to (−360, 360).
pub fn angle<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    let v = f64::deserialize(d)?;
    if !(v.is_finite() && v.abs() <= MAX_ANGLE_DEG) {
        return Err(D::Error::custom(format!(
            "angle {} is out of range: degrees within ±{MAX_ANGLE_DEG:e}",
            shown(v)
        )));
    }
    Ok((v % 360.0) as f32)
}

/// A value that must fit an `f32` (elevation, zoom: their own ranges are checked later).
pub fn narrow<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    let v = f64::deserialize(d)?;
    if v.is_finite() && v.abs() <= f64::from(f32::MAX) {
        Ok(v as f32)
    } else {
        Err(D::Error::custom(format!("{} is out of range", shown(v))))
    }
}

/// `v` as a person would write it: `1e308`, not 309 digits.
fn shown(v: f64) -> String {
    if v != 0.0 && !(1e-6..1e16).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// [`narrow`] for an optional value.
pub fn narrow_opt<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f32>, D::Error> {
    narrow(d).map(Some)
}

#[cfg(test)]
mod tests {
    #[derive(serde::Deserialize, Debug)]
    struct Q {
        #[serde(default, deserialize_with = "super::angle")]
        angle: f32,
        #[serde(default, deserialize_with = "super::narrow")]
        elevation: f32,
    }

    #[test]
    fn values_are_named_as_given_and_angles_wrap() {
        let q: Q = serde_json::from_str(r#"{"angle": -999999.5, "elevation": 10}"#).unwrap();
        assert_eq!(q.angle, -279.5);
        assert_eq!(q.elevation, 10.0);
        let q: Q = serde_json::from_str(r#"{"angle": 370}"#).unwrap();
        assert_eq!(q.angle, 10.0);
        for far in ["1e308", "-1e308", "1000001"] {
            let e = serde_json::from_str::<Q>(&format!(r#"{{"angle": {far}}}"#)).unwrap_err();
            assert!(e.to_string().contains("is out of range"), "{far}: {e}");
        }
        let e = serde_json::from_str::<Q>(r#"{"elevation": 1e308}"#).unwrap_err();
        assert!(e.to_string().contains("1e308 is out of range"), "{e}");
    }
}
