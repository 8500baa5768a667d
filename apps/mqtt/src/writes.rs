//! Writes from MQTT: a message on `<prefix>/<section>/<VAR>/set` whose
//! payload is the value, as a SET takes it (UTF-8 here, cp1250 in the PLC).
//!
//! A write goes through exactly SET's validation and errors
//! (`Section::write`, READ_ONLY included), after this server's own checks:
//! the variable must match MQTT_WRITE, the message must not be a retained
//! one, and the name and value must have a cp1250 form. A retained `/set`
//! is always refused, whether it arrives while subscribed (MQTT 5's Retain
//! As Published marks it) or at a new subscription: otherwise it would be
//! written again at every reconnection, long after it was sent. The empty
//! retained message that clears it is taken silently (`connection.rs`).
//!
//! The value is the form the value topic shows (`payload.rs`): a time
//! type's ISO 8601 form is turned into the protocol's text before SET
//! ([`present::protocol_text`]); numbers and `true`/`false` go as they
//! are.
//! Writes of a section are made one at a time, in the order they arrive.
//!
//! A confirmed write is published on the value topic (the value read back
//! from the PLC), once: by the change stream, else from the write's outcome. A refused one is published on `<VAR>/error` (not retained),
//! counted, and logged (at most once a second per error code: any client of
//! the broker can cause refusals). Nothing is ever written later: a write that arrives while the
//! PLC is unreachable is refused at once (ERROR:10), and the client's
//! session is clean, so the broker keeps no writes for it while it is away.
//! A refusal made while the broker is away (the connection dropped during
//! the write) is queued like any QoS 1 message and published when the
//! broker returns.

use std::sync::Arc;

use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::cp1250;
use tokio::sync::mpsc;

use super::settings::SectionRules;
use super::topics::unlevel;
use plccoms_core::present;
use plccoms_core::section::write::{WriteRefusal, Written};
use plccoms_core::section::Section;

/// Writes waiting for the PLC, per section; more are refused at once.
pub const QUEUE: usize = 64;

/// The longest value a write may carry (a STRING holds at most 255
/// characters): longer ones are refused before anything else.
pub const MAX_VALUE: usize = 1024;

/// How much of the name and value a refusal line quotes.
const QUOTED: usize = 64;

/// A write accepted for the PLC.
#[derive(Debug)]
pub struct Request {
    /// The topic level the write came on (its `error` topic's level).
    pub level: String,
    pub name: Vec<u8>,
    pub value: Vec<u8>,
}

/// What became of a write.
#[derive(Debug)]
pub struct Outcome {
    pub level: String,
    pub result: Result<Written, Refused>,
}

/// A refusal: the error code and the line a client would read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refused {
    pub code: u16,
    pub line: String,
}

impl Refused {
    /// The section's refusal of `request`, as SET's error line.
    fn of(refusal: WriteRefusal, request: &Request) -> Refused {
        Refused {
            code: refusal.code().code(),
            line: refusal.line(&request.name, &request.value),
        }
    }
}

/// `ERROR:<code> <text> 'SET:<name>,<value>'` with this server's reason
/// after it.
fn refusal(code: ErrorCode, level: &str, value: &[u8], why: &str) -> Refused {
    let mut context = format!("SET:{},", shorten(level)).into_bytes();
    context.extend_from_slice(&cp1250::encode(&shorten(&String::from_utf8_lossy(value))));
    let mut line = Vec::new();
    write_error(&mut line, code, &context);
    let mut line = cp1250::decode(&line).into_owned();
    if !why.is_empty() {
        line.push_str(" (");
        line.push_str(why);
        line.push(')');
    }
    Refused {
        code: code.code(),
        line,
    }
}

/// `text` cut to [`QUOTED`] characters, `...` marking the cut: a refusal
/// quotes what came, but never makes a huge line of a huge message.
fn shorten(text: &str) -> String {
    match text.char_indices().nth(QUOTED) {
        Some((at, _)) => format!("{}...", &text[..at]),
        None => text.to_string(),
    }
}

/// Checks a `/set` message that came on `level` before it goes to SET.
pub fn check(
    rules: &SectionRules,
    level: &str,
    payload: &[u8],
    retained: bool,
) -> Result<Request, Refused> {
    if retained {
        return Err(refusal(
            ErrorCode::BadRequest,
            level,
            payload,
            "a retained /set message is never written: clear it with an empty retained message on this topic",
        ));
    }
    if payload.len() > MAX_VALUE {
        return Err(refusal(
            ErrorCode::WrongValue,
            level,
            payload,
            &format!("a value of {} bytes; at most {MAX_VALUE}", payload.len()),
        ));
    }
    let name = unlevel(level)
        .map_err(|e| refusal(ErrorCode::UnknownVariable, level, payload, &e.to_string()))?;
    let value = std::str::from_utf8(payload)
        .ok()
        .and_then(cp1250::try_encode)
        .ok_or_else(|| {
            refusal(
                ErrorCode::WrongValue,
                level,
                payload,
                "the value is not UTF-8 text with a cp1250 form",
            )
        })?;
    if !rules.writable(&cp1250::to_upper(&name)) {
        return Err(refusal(
            ErrorCode::BadRequest,
            level,
            payload,
            "not writable over MQTT: see MQTT_WRITE",
        ));
    }
    Ok(Request {
        level: level.to_string(),
        name,
        value,
    })
}

/// The refusal of a write that found the queue full.
pub fn busy(request: &Request) -> Refused {
    refusal(
        ErrorCode::BadRequest,
        &request.level,
        &request.value,
        "too many writes waiting for the PLC",
    )
}

/// Makes the writes of a section one at a time, in order, until `requests`
/// closes.
pub async fn worker(
    section: Arc<Section>,
    mut requests: mpsc::Receiver<Request>,
    outcomes: mpsc::Sender<Outcome>,
) {
    while let Some(request) = requests.recv().await {
        let result = match in_protocol_terms(&section, &request) {
            Ok(text) => section
                .write(&request.name, &text)
                .await
                .map_err(|refusal| Refused::of(refusal, &request)),
            Err(refused) => Err(refused),
        };
        let outcome = Outcome {
            level: request.level,
            result,
        };
        if outcomes.send(outcome).await.is_err() {
            break;
        }
    }
}

/// The value of `request` as SET takes it: a time type's ISO 8601 form
/// (what the value topic shows) turned into the protocol's text, a whole
/// number's `5.0` into `5`; refused, naming the form expected, when it is
/// not one. A variable not in the table goes to SET as it came (SET
/// answers for it).
fn in_protocol_terms(section: &Section, request: &Request) -> Result<Vec<u8>, Refused> {
    let snapshot = section.latest();
    let Some(id) = snapshot.table.lookup(&request.name) else {
        return Ok(request.value.clone());
    };
    let ty = snapshot.table.var(id).ty;
    present::protocol_text(ty, &request.value, section.format())
        .map(|text| text.into_owned())
        .map_err(|expected| {
            let value = cp1250::decode(&request.value);
            refusal(
                ErrorCode::WrongValue,
                &request.level,
                value.as_bytes(),
                expected,
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::config::MqttSection;

    fn rules(write: &[&str]) -> SectionRules {
        SectionRules::new(&MqttSection {
            write: write.iter().map(|s| s.to_string()).collect(),
            ..MqttSection::default()
        })
        .unwrap()
    }

    #[test]
    fn checks_before_set() {
        let r = rules(&["SET*", "teplota_*"]);
        let ok = check(&r, "setpoint", b"21.5", false).unwrap();
        assert_eq!(
            (ok.name, ok.value),
            (b"setpoint".to_vec(), b"21.5".to_vec())
        );
        // cp1250 names and values.
        let ok = check(&r, "TEPLOTA_KUCHYNĚ", "Žluť".as_bytes(), false).unwrap();
        assert_eq!(ok.name, cp1250::encode("TEPLOTA_KUCHYNĚ").into_owned());
        assert_eq!(ok.value, cp1250::encode("Žluť").into_owned());
        let no = check(&r, "COUNTER", b"1", false).unwrap_err();
        assert_eq!(no.code, 30);
        assert_eq!(
            no.line,
            "ERROR:30 Bad client request: 'SET:COUNTER,1' (not writable over MQTT: see MQTT_WRITE)"
        );
        assert!(check(&r, "SETPOINT", b"1", true)
            .unwrap_err()
            .line
            .contains("retained"));
        assert_eq!(check(&r, "SETPOINT", b"\xff", false).unwrap_err().code, 35);
        assert_eq!(
            check(&r, "SETPOINT", "日".as_bytes(), false)
                .unwrap_err()
                .code,
            35
        );
        assert_eq!(check(&r, "SET%zz", b"1", false).unwrap_err().code, 33);
        assert_eq!(
            check(&rules(&[]), "SETPOINT", b"1", false)
                .unwrap_err()
                .code,
            30
        );
        let huge = check(&r, "SETPOINT", &[b'7'; 100_000], false).unwrap_err();
        assert_eq!(huge.code, 35);
        assert!(huge.line.len() < 300, "{}", huge.line);
        assert!(
            huge.line.contains("7777...' (a value of 100000 bytes"),
            "{}",
            huge.line
        );
    }
}
