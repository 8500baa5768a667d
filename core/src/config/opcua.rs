//! The OPC UA keys' settings: in `[*]` the server (port, host, security
//! policies, users, PKI, limits); in a PLC section what it shows and what
//! may be written. apps/opcua reads them.

/// The security policy and mode pairs OPCUA_SECURITY accepts, as written.
pub const OPCUA_SECURITY_CHOICES: [&str; 7] = [
    "None",
    "Basic256Sha256 Sign",
    "Basic256Sha256 SignAndEncrypt",
    "Aes128_Sha256_RsaOaep Sign",
    "Aes128_Sha256_RsaOaep SignAndEncrypt",
    "Aes256_Sha256_RsaPss Sign",
    "Aes256_Sha256_RsaPss SignAndEncrypt",
];

/// The OPC UA keys of `[*]`. The server is off while `port` is `None`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OpcuaGlobal {
    /// OPCUA_PORT.
    pub port: Option<u16>,
    /// OPCUA_HOST: the address bound and named in endpoint URLs.
    pub host: String,
    /// OPCUA_SECURITY: the endpoints, as [`OPCUA_SECURITY_CHOICES`] writes them.
    pub security: Vec<&'static str>,
    /// OPCUA_USERS: the users file (names, roles, password hashes).
    pub users: Option<String>,
    /// OPCUA_ANONYMOUS: anonymous sessions (and the None policy) also when
    /// OPCUA_HOST is not a loopback address.
    pub anonymous: bool,
    /// OPCUA_PKI: own certificate and key, trusted/ and rejected/.
    pub pki: String,
    /// OPCUA_MAX_SESSIONS, OPCUA_MAX_SUBSCRIPTIONS (per session),
    /// OPCUA_MAX_MONITORED_ITEMS (per subscription), OPCUA_MAX_NODES_PER_CALL.
    pub max_sessions: usize,
    pub max_subscriptions: usize,
    pub max_monitored_items: usize,
    pub max_nodes_per_call: usize,
}

impl Default for OpcuaGlobal {
    /// Placeholders: every field is set by its key's default.
    fn default() -> Self {
        OpcuaGlobal {
            port: None,
            host: String::new(),
            security: Vec::new(),
            users: None,
            anonymous: false,
            pki: String::new(),
            max_sessions: 0,
            max_subscriptions: 0,
            max_monitored_items: 0,
            max_nodes_per_call: 0,
        }
    }
}

/// The OPC UA keys of a PLC section.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct OpcuaSection {
    /// OPCUA_PUBLISH: masks of the variables in the address space (`None`:
    /// every variable of the project).
    pub publish: Option<Vec<String>>,
    /// OPCUA_WRITE: masks of the variables writers may write (none by
    /// default).
    pub write: Vec<String>,
}
