//! How numbers appear in the JSON that the command line, the recording's export and the web
//! viewer print: an `f32` parameter such as γ as the number it was written as.

use serde_json::Value;

/// `v` as the JSON number it reads as: γ = 0.013 prints `0.013`, where
/// `serde_json::json!(v)` would widen it to `0.013000000268220901`. `null` for a value that
/// is not finite (JSON has no NaN or infinity).
pub fn f32_number(v: f32) -> Value {
    v.to_string()
        .parse::<f64>()
        .ok()
        .and_then(serde_json::Number::from_f64)
        .map_or(Value::Null, Value::Number)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_f32_prints_as_written_and_round_trips() {
        assert_eq!(
            serde_json::json!(0.013f32).to_string(),
            "0.013000000268220901"
        );
        for v in [
            0.013f32,
            0.001,
            0.26,
            1.0,
            0.0,
            1e-7,
            3.4e38,
            f32::MIN_POSITIVE,
        ] {
            let text = f32_number(v).to_string();
            assert!(text.len() <= 16, "{v}: {text}");
            assert_eq!(text.parse::<f32>().unwrap(), v, "{text}");
        }
        assert_eq!(f32_number(0.013).to_string(), "0.013");
        assert_eq!(f32_number(f32::NAN), Value::Null);
        assert_eq!(f32_number(f32::INFINITY), Value::Null);
    }
}
