//! A sample's key in a day file: the milliseconds since the day's start,
//! shifted, and the variable's id in the low bits. The store writes keys,
//! packed blocks and queries read them.

/// Bits of the key that hold the variable: 32,767 variables per section and
/// day, and a key below 2^42 (a 6-byte varint).
pub const VAR_BITS: u32 = 15;
pub const VAR_MASK: i64 = (1 << VAR_BITS) - 1;
pub const DAY_MS: i64 = 86_400_000;

/// The UTC day (days since 1970) of `t_ms`.
pub fn day_of(t_ms: i64) -> i64 {
    t_ms.div_euclid(DAY_MS)
}

/// `YYYY-MM-DD` of a day.
pub fn day_name(day: i64) -> String {
    chrono::DateTime::from_timestamp_millis(day * DAY_MS)
        .map(|d| d.format("%Y-%m-%d").to_string())
        .unwrap_or_else(|| format!("day{day}"))
}
