//! From the MQTT keys to what the client needs: the broker's address and
//! transport, credentials (a password file read once, at start-up), the
//! client ids, the TLS configuration and each section's publishing rules.
//!
//! Each section has a connection of its own, because a connection has one
//! last will and every section has its own `status` topic: its client id is
//! `<base>-<section>`, the base being MQTT_CLIENT_ID or, by default,
//! `plccoms-<host name>-<hash of the configuration file's path>`, stable
//! across restarts and different for two configurations on one host.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use plccoms_protocol::{cp1250, Delta, Mask};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

use plccoms_core::config::{self, BrokerUrl, MqttFormat};

/// The `[*]` MQTT settings, resolved.
#[derive(Clone)]
pub struct Settings {
    /// MQTT_URL's brokers, tried round robin; never empty.
    pub brokers: Vec<BrokerUrl>,
    /// MQTT_VERSION = 3.1.1.
    pub v311: bool,
    pub credentials: Option<(String, String)>,
    /// Base of the client ids (`<base>-<section>`).
    pub client_id: String,
    pub prefix: String,
    pub tls: Option<Arc<rustls::ClientConfig>>,
    pub buffer: u64,
    pub spool: PathBuf,
    /// The Sparkplug B edge node's ids.
    pub sparkplug: crate::sparkplug::NodeSettings,
}

impl std::fmt::Debug for Settings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the password.
        f.debug_struct("Settings")
            .field("brokers", &self.brokers)
            .field("v311", &self.v311)
            .field("user", &self.credentials.as_ref().map(|c| &c.0))
            .field("client_id", &self.client_id)
            .field("prefix", &self.prefix)
            .field("tls", &self.tls.is_some())
            .field("buffer", &self.buffer)
            .field("spool", &self.spool)
            .field("sparkplug", &self.sparkplug)
            .finish()
    }
}

impl Settings {
    /// The settings of `[*]`, files read (password, certificates), relative
    /// paths from `dir` (the configuration's folder); `None` when MQTT_URL is
    /// unset. `config_path` seeds the default client id.
    pub fn load(
        mqtt: &config::MqttGlobal,
        dir: &Path,
        config_path: &Path,
    ) -> Result<Option<Settings>, String> {
        // Parsed, and a bad one refused, when the configuration was loaded.
        let Some(brokers) = mqtt.url.clone() else {
            return Ok(None);
        };
        config::check_prefix(&mqtt.prefix)
            .map_err(|p| format!("MQTT_PREFIX = {} {p}", mqtt.prefix))?;
        let password = match (&mqtt.password, &mqtt.password_file) {
            (Some(password), _) => Some(password.clone()),
            (None, Some(file)) => {
                let path = dir.join(file);
                let text = std::fs::read_to_string(&path)
                    .map_err(|e| format!("MQTT_PASSWORD_FILE {}: {e}", path.display()))?;
                Some(text.trim_end_matches(['\r', '\n']).to_string())
            }
            (None, None) => None,
        };
        let credentials = match (&mqtt.user, password) {
            (Some(user), password) => Some((user.clone(), password.unwrap_or_default())),
            (None, Some(_)) => return Err("MQTT_PASSWORD is given without MQTT_USER".into()),
            (None, None) => None,
        };
        let tls = if brokers.iter().any(|b| b.tls) {
            Some(Arc::new(tls_config(mqtt, dir)?))
        } else {
            None
        };
        let client_id = match &mqtt.client_id {
            Some(id) => id.clone(),
            None => default_client_id(config_path),
        };
        // Written: under systemd the configuration's folder is read-only.
        let spool = config::state_dir(config_path).join(&mqtt.spool);
        Ok(Some(Settings {
            sparkplug: crate::sparkplug::node_settings(mqtt, &spool)?,
            brokers,
            v311: mqtt.v311,
            credentials,
            client_id,
            prefix: mqtt.prefix.clone(),
            tls,
            buffer: mqtt.buffer,
            spool,
        }))
    }

    /// The client id of a section's connection.
    pub fn section_client_id(&self, section: &str) -> String {
        format!("{}-{}", self.client_id, id_safe(section))
    }
}

/// `plccoms-<host name>-<crc32 of the configuration's absolute path>`.
fn default_client_id(config_path: &Path) -> String {
    let host = nix::unistd::gethostname()
        .ok()
        .and_then(|h| h.into_string().ok())
        .unwrap_or_else(|| "host".into());
    let path = std::fs::canonicalize(config_path).unwrap_or_else(|_| config_path.to_path_buf());
    let hash = CRC32.checksum(path.as_os_str().as_encoded_bytes());
    format!("plccoms-{}-{hash:08x}", id_safe(&host))
}

pub(super) const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// `text` with everything but ASCII letters, digits, `-` and `_` made `_`:
/// what every broker accepts in a client id.
pub fn id_safe(text: &str) -> String {
    text.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// rustls on ring: the broker checked against MQTT_CA, else the system's CA
/// store; a client certificate with MQTT_CERT and MQTT_KEY.
fn tls_config(mqtt: &config::MqttGlobal, dir: &Path) -> Result<rustls::ClientConfig, String> {
    let mut roots = rustls::RootCertStore::empty();
    match &mqtt.ca {
        Some(ca) => {
            let path = dir.join(ca);
            let certs = read_certs(&path, "MQTT_CA")?;
            for cert in certs {
                roots
                    .add(cert)
                    .map_err(|e| format!("MQTT_CA {}: {e}", path.display()))?;
            }
        }
        None => {
            let native = rustls_native_certs::load_native_certs();
            roots.add_parsable_certificates(native.certs);
            if roots.is_empty() {
                return Err(
                    "mqtts:// without MQTT_CA, and no CA certificates in the system's store".into(),
                );
            }
        }
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| format!("TLS: {e}"))?
        .with_root_certificates(roots);
    match (&mqtt.cert, &mqtt.key) {
        (Some(_), None) | (None, Some(_)) => {
            Err("MQTT_CERT and MQTT_KEY go together (a client certificate and its key)".into())
        }
        (Some(cert), Some(key)) => {
            let certs = read_certs(&dir.join(cert), "MQTT_CERT")?;
            let key_path = dir.join(key);
            let key = PrivateKeyDer::from_pem_file(&key_path)
                .map_err(|e| format!("MQTT_KEY {}: {e}", key_path.display()))?;
            builder
                .with_client_auth_cert(certs, key)
                .map_err(|e| format!("MQTT_CERT/MQTT_KEY: {e}"))
        }
        _ => Ok(builder.with_no_client_auth()),
    }
}

fn read_certs(path: &Path, key: &str) -> Result<Vec<CertificateDer<'static>>, String> {
    let certs = CertificateDer::pem_file_iter(path)
        .and_then(|iter| iter.collect::<Result<Vec<_>, _>>())
        .map_err(|e| format!("{key} {}: {e}", path.display()))?;
    if certs.is_empty() {
        return Err(format!("{key} {}: no certificate in it", path.display()));
    }
    Ok(certs)
}

/// A section's publishing rules, from its MQTT keys.
#[derive(Debug, Clone)]
pub struct SectionRules {
    /// MQTT_PUBLISH as given, for the change subscription.
    pub publish: Vec<Vec<u8>>,
    /// MQTT_WRITE, compiled.
    pub write: Vec<Mask>,
    pub qos: u8,
    pub retain: bool,
    pub format: MqttFormat,
    pub delta: Option<Delta>,
    pub ha_discovery: bool,
}

impl SectionRules {
    pub fn new(mqtt: &config::MqttSection) -> Result<SectionRules, String> {
        let delta = match &mqtt.delta {
            Some(text) => {
                let delta = Delta::parse(text.as_bytes())
                    .map_err(|e| format!("MQTT_DELTA = {text} {}", e.message()))?;
                (!delta.is_zero()).then_some(delta)
            }
            None => None,
        };
        let masks = |list: &[String]| -> Vec<Vec<u8>> {
            list.iter()
                .map(|m| cp1250::encode(m).into_owned())
                .collect()
        };
        Ok(SectionRules {
            publish: masks(&mqtt.publish),
            write: masks(&mqtt.write).iter().map(|m| Mask::new(m)).collect(),
            qos: mqtt.qos,
            retain: mqtt.retain,
            format: mqtt.format,
            delta,
            ha_discovery: mqtt.ha_discovery,
        })
    }

    /// Whether `/set` may write `upper_name` (MQTT_WRITE): system
    /// variables and direct addresses only by a mask that begins with `__`
    /// or `%` ([`Mask::matches_name`]).
    pub fn writable(&self, upper_name: &[u8]) -> bool {
        self.write.iter().any(|m| m.matches_name(upper_name))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_star_writes_the_project_s_variables_only() {
        let rules = |write: &[&str]| {
            SectionRules::new(&config::MqttSection {
                write: write.iter().map(|s| s.to_string()).collect(),
                ..config::MqttSection::default()
            })
            .unwrap()
        };
        let star = rules(&["*"]);
        assert!(star.writable(b"COUNTER"));
        assert!(!star.writable(b"__PLC_RUN"));
        assert!(!star.writable(b"%R100"));
        let explicit = rules(&["__*", "%R1*"]);
        assert!(explicit.writable(b"__PLC_RUN"));
        assert!(explicit.writable(b"%R100"));
        assert!(!explicit.writable(b"COUNTER"));
    }

    #[test]
    fn client_ids_are_stable_and_safe() {
        let a = default_client_id(Path::new("/etc/plccoms/a.ini"));
        assert_eq!(a, default_client_id(Path::new("/etc/plccoms/a.ini")));
        assert_ne!(a, default_client_id(Path::new("/etc/plccoms/b.ini")));
        assert!(a.starts_with("plccoms-"));
        assert_eq!(id_safe("Hala 1/ä"), "Hala_1__");
    }
}
