//! Sizes as people write them, shared by the budgets (`size:2MB`) and the limits
//! (`INSITU_READ_LIMIT=8GiB`): one reading of `MB` and `MiB` everywhere.

/// `1.5MB`, `800kB`, `2MiB`, `123456` (bytes) → bytes: `k`/`kB`, `M`/`MB`, `G`/`GB` decimal,
/// `KiB`, `MiB`, `GiB` binary; `None` for anything else, a negative or an overflowing size.
pub fn parse_bytes(s: &str) -> Option<u64> {
    let s = s.trim();
    let split = s.find(|c: char| c.is_ascii_alphabetic()).unwrap_or(s.len());
    let (num, unit) = s.split_at(split);
    let v: f64 = num.trim().parse().ok()?;
    let mul = match unit.trim() {
        "" | "B" => 1.0,
        "kB" | "KB" | "k" => 1e3,
        "MB" | "M" => 1e6,
        "GB" | "G" => 1e9,
        "KiB" => 1024.0,
        "MiB" => 1024.0 * 1024.0,
        "GiB" => 1024.0 * 1024.0 * 1024.0,
        _ => return None,
    };
    let b = v * mul;
    (0.0..1.8e19).contains(&b).then_some(b.round() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimal_and_binary_units_and_nonsense_is_refused() {
        assert_eq!(parse_bytes("4096"), Some(4096));
        assert_eq!(parse_bytes("1.5MB"), Some(1_500_000));
        assert_eq!(parse_bytes(" 3 kB "), Some(3000));
        assert_eq!(parse_bytes("8G"), Some(8_000_000_000));
        assert_eq!(parse_bytes("8GiB"), Some(8 << 30));
        assert_eq!(parse_bytes("512MiB"), Some(512 << 20));
        for bad in ["", "G", "-1", "NaN", "inf", "8 GB of RAM", "3XB", "1e30GB"] {
            assert_eq!(parse_bytes(bad), None, "{bad}");
        }
    }
}
