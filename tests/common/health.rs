//! The link health rules at the vendor's default timeouts (EPSTOUT 1000 ms,
//! EPSTOUT_STEP 500 ms, COMM_LOOP_DELAY 100 ms), as a client sees them,
//! whatever carries EPSNET: a value is never served past its freshness, a
//! silent PLC is declared lost in time, and requests are then answered at
//! once.

use std::time::{Duration, Instant};

use super::Client;

/// Freshness bound at the defaults: 2 x 100 ms + 1000 ms.
pub const FRESH: Duration = Duration::from_millis(1200);
/// Loss declared within EPSTOUT + (EPSTOUT + STEP) at the defaults.
pub const LOSS: Duration = Duration::from_millis(2500);
/// Scheduling slack on a loaded machine.
pub const SLACK: Duration = Duration::from_millis(2000);

/// The answer to `request`, skipping the lines that come unasked: DIFF
/// (but a SET is answered by one) and public-file notices (but a SETCONF
/// is); and how long it took. A SET on a bad line may take its write and
/// its read-back with a retry each, behind a poll with one: up to 3 x 2.5 s.
pub async fn answer(c: &mut Client, request: &str) -> (String, Duration) {
    let sent = Instant::now();
    c.send(request.as_bytes()).await;
    loop {
        let line = c
            .line_within(Duration::from_secs(15))
            .await
            .unwrap_or_else(|| panic!("no answer to {request:?} within 15 s"));
        let line = String::from_utf8_lossy(&line).into_owned();
        let diff = line.starts_with("DIFF:") && !request.starts_with("SET:");
        let notice = line.starts_with("WARNING:25") && !request.starts_with("SETCONF:");
        if !diff && !notice {
            return (line, sent.elapsed());
        }
    }
}

/// Asks until the answer is `want`, within `within`.
pub async fn until(c: &mut Client, request: &str, want: &str, within: Duration) {
    let start = Instant::now();
    loop {
        let (line, _) = answer(c, request).await;
        if line == want {
            return;
        }
        assert!(start.elapsed() < within, "{request} still answers {line:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// The errors of a lost link (ERROR:21: a SET that waited past EPSTOUT to
/// be sent).
pub fn is_link_error(line: &str) -> bool {
    line == "ERROR:10 Unable to connect to PLC.\r\n"
        || line == "ERROR:20 Unable to get data from PLC.\r\n"
        || line == "ERROR:21 Unable to send data to PLC.\r\n"
}

/// Sends `request` (a GET of a polled variable) every 50 ms from `since`,
/// when the PLC went silent, until well past the loss bound, and checks the
/// rules: the answer `value` only while fresh, the first error in time,
/// errors at once once lost. Returns when the first error came and the
/// longest answer while lost.
pub async fn outage(
    c: &mut Client,
    request: &str,
    value: &str,
    since: Instant,
) -> (Duration, Duration) {
    let mut values_after_fresh = Vec::new();
    let mut first_error = None;
    let mut waits_after_loss = Vec::new();
    while since.elapsed() < LOSS + SLACK + Duration::from_millis(1500) {
        let sent_at = since.elapsed();
        let (line, took) = answer(c, request).await;
        if line == value {
            // Served from the poll: only while the poll was fresh (the last
            // one completed before the PLC went silent).
            if sent_at > FRESH {
                values_after_fresh.push(sent_at);
            }
        } else {
            assert!(is_link_error(&line), "{line:?}");
            first_error.get_or_insert(sent_at + took);
            if sent_at > LOSS + SLACK {
                waits_after_loss.push(took);
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        values_after_fresh.is_empty(),
        "old value served to requests sent {values_after_fresh:?} after the PLC went silent"
    );
    let first_error = first_error.expect("an error answer");
    assert!(
        first_error < LOSS + SLACK,
        "first error after {first_error:?}"
    );
    let longest = waits_after_loss
        .iter()
        .max()
        .copied()
        .expect("answers while lost");
    assert!(
        longest < Duration::from_millis(500),
        "not at once: {waits_after_loss:?}"
    );
    (first_error, longest)
}

/// A day of a demo program's `tim` (ms since midnight).
const DAY: i64 = 86_400_000;

/// Milliseconds since midnight UTC, as a simulated PLC's clock (`tim`).
pub fn time_of_day_ms() -> i64 {
    let ms = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis();
    (ms % DAY as u128) as i64
}

/// Whether `tim` was written no earlier than `since` (ms of day), allowing
/// one PLC cycle (10 ms) and midnight.
pub fn fresh(tim: i64, since: i64) -> bool {
    (tim - since + 20).rem_euclid(DAY) < DAY / 2
}
