//! The times `plccoms history --from/--to` and `/api/history` take, and the
//! one way samples' times are written out.
//!
//! A time is `now`, relative to now (`-90s`, `-15m`, `-1h`, `-7d`, `-2w`),
//! or ISO 8601 / RFC 3339 (`2026-05-01T12:00:00Z`, with milliseconds or an
//! offset, or a date alone, `2026-05-01`, meaning its midnight UTC).

/// UTC milliseconds of `text`, relative times counted from `now_ms`. `Err`
/// says what is wrong and what is allowed.
pub fn parse(text: &str, now_ms: i64) -> Result<i64, String> {
    let text = text.trim();
    let allowed = "(allowed: now, -30s, -15m, -1h, -7d, -2w, 2026-05-01T12:00:00Z, 2026-05-01)";
    if text.eq_ignore_ascii_case("now") {
        return Ok(now_ms);
    }
    if let Some(relative) = text.strip_prefix('-') {
        let digits = relative.bytes().take_while(u8::is_ascii_digit).count();
        let (number, unit) = relative.split_at(digits);
        let unit_ms: i64 = match unit {
            "s" => 1_000,
            "m" => 60_000,
            "h" => 3_600_000,
            "d" => 86_400_000,
            "w" => 7 * 86_400_000,
            _ => return Err(format!("'{text}' is not a time {allowed}")),
        };
        let n: i64 = number
            .parse()
            .map_err(|_| format!("'{text}' is not a time {allowed}"))?;
        return n
            .checked_mul(unit_ms)
            .and_then(|ago| now_ms.checked_sub(ago))
            .ok_or_else(|| format!("'{text}' is too far back"));
    }
    if let Ok(t) = chrono::DateTime::parse_from_rfc3339(text) {
        return Ok(t.timestamp_millis());
    }
    if let Ok(date) = chrono::NaiveDate::parse_from_str(text, "%Y-%m-%d") {
        if let Some(t) = date.and_hms_opt(0, 0, 0) {
            return Ok(t.and_utc().timestamp_millis());
        }
    }
    Err(format!("'{text}' is not a time {allowed}"))
}

/// [`iso`] as a `String`, for messages.
pub fn iso_string(t_ms: i64) -> String {
    let mut out = Vec::new();
    iso(t_ms, &mut out);
    String::from_utf8_lossy(&out).into_owned()
}

/// ISO 8601 UTC with milliseconds: `2026-05-01T12:00:00.123Z`.
pub fn iso(t_ms: i64, out: &mut Vec<u8>) {
    use std::io::Write;
    // The date part is formatted once per day (exports write millions of
    // times, mostly of one day).
    thread_local! {
        static DAY: std::cell::RefCell<(i64, Vec<u8>)> = const { std::cell::RefCell::new((i64::MIN, Vec::new())) };
    }
    const DAY_MS: i64 = 86_400_000;
    let (day, ms) = (t_ms.div_euclid(DAY_MS), t_ms.rem_euclid(DAY_MS));
    let known = DAY.with_borrow_mut(|(cached, text)| {
        if *cached != day {
            let Some(date) = chrono::DateTime::from_timestamp_millis(day * DAY_MS) else {
                return false;
            };
            text.clear();
            let _ = write!(text, "{}", date.format("%Y-%m-%dT"));
            *cached = day;
        }
        out.extend_from_slice(text);
        true
    });
    if !known {
        let _ = write!(out, "{t_ms}");
        return;
    }
    let (h, m, s, milli) = (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
    let digits = |n: i64, width: usize, out: &mut Vec<u8>| {
        for i in (0..width).rev() {
            out.push(b'0' + (n / 10i64.pow(i as u32) % 10) as u8);
        }
    };
    digits(h, 2, out);
    out.push(b':');
    digits(m, 2, out);
    out.push(b':');
    digits(s, 2, out);
    out.push(b'.');
    digits(milli, 3, out);
    out.push(b'Z');
}

#[cfg(test)]
mod tests {
    use super::*;

    const NOW: i64 = 1_700_000_000_000;

    #[test]
    fn forms() {
        assert_eq!(parse("now", NOW), Ok(NOW));
        assert_eq!(parse("-1h", NOW), Ok(NOW - 3_600_000));
        assert_eq!(parse("-7d", NOW), Ok(NOW - 7 * 86_400_000));
        assert_eq!(parse("2023-11-14T22:13:20Z", NOW), Ok(NOW));
        assert_eq!(parse("2023-11-14T22:13:20.5Z", NOW), Ok(NOW + 500));
        assert_eq!(parse("2023-11-14T23:13:20+01:00", NOW), Ok(NOW));
        assert_eq!(parse("2023-11-14", NOW), Ok(NOW - 80_000_000));
        for bad in [
            "",
            "-",
            "-1",
            "-1y",
            "yesterday",
            "2023-13-01",
            "-99999999999999w",
        ] {
            assert!(parse(bad, NOW).is_err(), "{bad}");
        }
        let mut out = Vec::new();
        iso(NOW + 7, &mut out);
        assert_eq!(out, b"2023-11-14T22:13:20.007Z");
        out.clear();
        iso(-1, &mut out);
        assert_eq!(out, b"1969-12-31T23:59:59.999Z");
        out.clear();
        iso(i64::MAX, &mut out);
        assert_eq!(out, i64::MAX.to_string().as_bytes());
    }
}
