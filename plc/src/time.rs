//! Calendar arithmetic for the PLC clock and file times, in UTC (no time zone
//! database: the simulated PLC's clock runs on UTC).

use std::time::{SystemTime, UNIX_EPOCH};

/// Days since 1970-01-01 of a proleptic Gregorian date.
pub fn days_from_civil(year: i64, month: u32, day: u32) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let m = i64::from(month);
    let doy = (153 * (if m > 2 { m - 3 } else { m + 9 }) + 2) / 5 + i64::from(day) - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// Date of a day count since 1970-01-01.
pub fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let month = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let year = yoe + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

/// 1 = Monday .. 7 = Sunday.
pub fn weekday(days: i64) -> u8 {
    // 1970-01-01 was a Thursday (4).
    ((days + 3).rem_euclid(7) + 1) as u8
}

/// Seconds since 1970, now (0 if the clock is before 1970).
pub fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// The `ttida` u64 (little-endian bytes year-1900, month, day, hour, minute,
/// second, 0, 0) of a Unix time.
pub fn ttida_from_unix(secs: i64) -> u64 {
    let days = secs.div_euclid(86_400);
    let rem = secs.rem_euclid(86_400);
    let (year, month, day) = civil_from_days(days);
    let y = (year - 1900).clamp(0, 255) as u8;
    u64::from_le_bytes([
        y,
        month as u8,
        day as u8,
        (rem / 3600) as u8,
        (rem / 60 % 60) as u8,
        (rem % 60) as u8,
        0,
        0,
    ])
}

/// The Unix time of a `ttida` value; `None` if it is no valid date.
pub fn unix_from_ttida(ttida: u64) -> Option<i64> {
    let b = ttida.to_le_bytes();
    let (month, day) = (u32::from(b[1]), u32::from(b[2]));
    if !(1..=12).contains(&month) || !(1..=31).contains(&day) || b[3] > 23 || b[4] > 59 || b[5] > 60
    {
        return None;
    }
    let days = days_from_civil(1900 + i64::from(b[0]), month, day);
    Some(days * 86_400 + i64::from(b[3]) * 3600 + i64::from(b[4]) * 60 + i64::from(b[5]))
}

pub fn ttida_from_system(time: SystemTime) -> u64 {
    let secs = match time.duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_secs() as i64,
        Err(e) => -(e.duration().as_secs() as i64),
    };
    ttida_from_unix(secs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calendar_round_trips() {
        assert_eq!(days_from_civil(1970, 1, 1), 0);
        assert_eq!(civil_from_days(19_797), (2024, 3, 15));
        assert_eq!(weekday(19_797), 5);
        for days in (-1000..30_000).step_by(37) {
            let (y, m, d) = civil_from_days(days);
            assert_eq!(days_from_civil(y, m, d), days);
        }
        let t = ttida_from_unix(1_710_510_330); // 2024-03-15 13:45:30
        assert_eq!(t.to_le_bytes(), [124, 3, 15, 13, 45, 30, 0, 0]);
        assert_eq!(unix_from_ttida(t), Some(1_710_510_330));
        assert_eq!(unix_from_ttida(0), None);
    }
}
