//! OPCUA_USERS: the users who may open a session with a name and password,
//! one a line:
//!
//! ```text
//! # name  role   hash
//! scada   read   pbkdf2-sha256:100000:<salt, hex>:<hash, hex>
//! hmi     write  pbkdf2-sha256:100000:<salt, hex>:<hash, hex>
//! ```
//!
//! The hash is PBKDF2-HMAC-SHA256 of the UTF-8 password with the salt, 32
//! bytes (README, "OPC UA server", shows how to make one). Role `write`
//! may write the variables OPCUA_WRITE allows; `read` only reads. No
//! password is kept in the clear, and the check takes the same time
//! whatever the password ([`ring::pbkdf2::verify`]).

use std::collections::HashMap;
use std::num::NonZeroU32;

/// What a user may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    Read,
    Write,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Entry {
    role: Role,
    iterations: NonZeroU32,
    salt: Vec<u8>,
    hash: Vec<u8>,
}

#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Users {
    users: HashMap<String, Entry>,
}

/// Bounds of a hash's iterations: fewer is no protection, more lets the
/// file's author stall every login.
pub const MIN_ITERATIONS: u32 = 1000;
pub const MAX_ITERATIONS: u32 = 10_000_000;
/// Most users a file may hold, and the longest line.
pub const MAX_USERS: usize = 10_000;
const MAX_LINE: usize = 4096;

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {problem}")]
pub struct UsersError {
    pub line: usize,
    pub problem: String,
}

impl Users {
    /// Reads a users file's text.
    pub fn parse(text: &str) -> Result<Users, UsersError> {
        let mut users = HashMap::new();
        for (index, raw) in text.lines().enumerate() {
            let line = index + 1;
            let bad = |problem: String| UsersError { line, problem };
            if raw.len() > MAX_LINE {
                return Err(bad(format!("longer than {MAX_LINE} bytes")));
            }
            let content = raw.trim();
            if content.is_empty() || content.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = content.split_whitespace().collect();
            let [name, role, hash] = fields[..] else {
                return Err(bad(format!(
                    "expected 3 fields (name role hash), found {}",
                    fields.len()
                )));
            };
            let role = match role.to_ascii_lowercase().as_str() {
                "read" => Role::Read,
                "write" => Role::Write,
                other => return Err(bad(format!("role '{other}' is neither read nor write"))),
            };
            let (iterations, salt, hash) = parse_hash(hash).map_err(bad)?;
            if users.len() >= MAX_USERS {
                return Err(bad(format!("more than {MAX_USERS} users")));
            }
            let entry = Entry {
                role,
                iterations,
                salt,
                hash,
            };
            if users.insert(name.to_string(), entry).is_some() {
                return Err(bad(format!("user '{name}' is listed twice")));
            }
        }
        Ok(Users { users })
    }

    pub fn is_empty(&self) -> bool {
        self.users.is_empty()
    }

    pub fn len(&self) -> usize {
        self.users.len()
    }

    /// The role of `name` if `password` is theirs.
    pub fn check(&self, name: &str, password: &[u8]) -> Option<Role> {
        let entry = self.users.get(name)?;
        ring::pbkdf2::verify(
            ring::pbkdf2::PBKDF2_HMAC_SHA256,
            entry.iterations,
            &entry.salt,
            password,
            &entry.hash,
        )
        .ok()
        .map(|()| entry.role)
    }

    pub fn role(&self, name: &str) -> Option<Role> {
        self.users.get(name).map(|e| e.role)
    }
}

/// `pbkdf2-sha256:<iterations>:<salt hex>:<hash hex>`.
fn parse_hash(text: &str) -> Result<(NonZeroU32, Vec<u8>, Vec<u8>), String> {
    let mut parts = text.split(':');
    let (Some(scheme), Some(iterations), Some(salt), Some(hash), None) = (
        parts.next(),
        parts.next(),
        parts.next(),
        parts.next(),
        parts.next(),
    ) else {
        return Err("the hash is not pbkdf2-sha256:<iterations>:<salt hex>:<hash hex>".into());
    };
    if scheme != "pbkdf2-sha256" {
        return Err(format!(
            "hash scheme '{}' is not pbkdf2-sha256",
            scheme.chars().take(32).collect::<String>()
        ));
    }
    let iterations = iterations
        .parse::<u32>()
        .ok()
        .filter(|n| (MIN_ITERATIONS..=MAX_ITERATIONS).contains(n))
        .and_then(NonZeroU32::new)
        .ok_or_else(|| {
            format!("iterations must be a number from {MIN_ITERATIONS} to {MAX_ITERATIONS}")
        })?;
    let salt = hex(salt).ok_or("the salt is not hexadecimal")?;
    if salt.len() < 8 {
        return Err("the salt is shorter than 8 bytes".into());
    }
    let hash = hex(hash).ok_or("the hash is not hexadecimal")?;
    if hash.len() != 32 {
        return Err(format!("the hash is {} bytes, not 32", hash.len()));
    }
    Ok((iterations, salt, hash))
}

fn hex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(text.get(i..i + 2)?, 16).ok())
        .collect()
}

/// A users file line for `name` with `role` (`read` or `write`) and
/// `password`, hashed with `salt` (8 bytes or more) and `iterations`.
pub fn hash_line(name: &str, role: &str, password: &str, salt: &[u8], iterations: u32) -> String {
    let iterations = NonZeroU32::new(iterations.max(1)).unwrap_or(NonZeroU32::MIN);
    let mut out = [0u8; 32];
    ring::pbkdf2::derive(
        ring::pbkdf2::PBKDF2_HMAC_SHA256,
        iterations,
        salt,
        password.as_bytes(),
        &mut out,
    );
    let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02x}")).collect::<String>();
    format!(
        "{name} {role} pbkdf2-sha256:{iterations}:{}:{}",
        hex(salt),
        hex(&out)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_passwords_and_roles() {
        let text = format!(
            "# users\n\n{}\n  {}  \n",
            hash_line("hmi", "write", "secret", b"plccoms-salt", MIN_ITERATIONS),
            hash_line("scada", "READ", "other", b"plccoms-salt", MIN_ITERATIONS)
        );
        let users = Users::parse(&text).unwrap();
        assert_eq!(users.len(), 2);
        assert_eq!(users.check("hmi", b"secret"), Some(Role::Write));
        assert_eq!(users.check("hmi", b"Secret"), None);
        assert_eq!(users.check("scada", b"other"), Some(Role::Read));
        assert_eq!(users.check("nobody", b"secret"), None);
    }

    #[test]
    fn refuses_bad_lines_naming_them() {
        let good = hash_line("a", "read", "x", b"plccoms-salt", MIN_ITERATIONS);
        for (text, problem) in [
            ("a read".to_string(), "expected 3 fields"),
            (
                "a admin pbkdf2-sha256:1000:0011223344556677:00".to_string(),
                "neither read nor write",
            ),
            ("a read md5:1000:00:00".to_string(), "not pbkdf2-sha256"),
            (
                "a read pbkdf2-sha256:10:0011223344556677:00".to_string(),
                "iterations",
            ),
            (
                "a read pbkdf2-sha256:1000:zz11223344556677:00".to_string(),
                "salt is not hex",
            ),
            (
                "a read pbkdf2-sha256:1000:0011223344556677:0011".to_string(),
                "not 32",
            ),
            (format!("{good}\n{good}"), "listed twice"),
        ] {
            let err = Users::parse(&text).unwrap_err();
            assert!(err.to_string().contains(problem), "{text}: {err}");
        }
        assert_eq!(
            Users::parse(&format!("\n{}", "a".repeat(5000)))
                .unwrap_err()
                .line,
            2
        );
    }
}
