//! The built-in demo: what runs without `-c` and without a `PLCComS.ini` in
//! the current folder. It is `PLCComS.ini.example`: a simulated PLC, served
//! on loopback only (its `IPADDR_LOCAL`), so that trying the server out on a
//! plant PC opens nothing to the network.

use plccoms_core::config::Config;

/// The demo configuration, built in.
pub const CONFIG: &str = include_str!("../PLCComS.ini.example");
/// The name messages give it.
pub const NAME: &str = "PLCComS.ini.example (built in)";

/// What `--help` says about it.
pub const HELP: &str = "\
Without -c and without a PLCComS.ini in the current folder, plccoms runs a
SIMULATED DEMO PLC (the built-in PLCComS.ini.example) on 127.0.0.1:5010 only.
To serve real PLCs, give their configuration: plccoms -c /path/to/PLCComS.ini";

/// The start-up warning: a simulated PLC runs, where, and how to point the
/// server at a real configuration.
pub fn banner(config: &Config) -> String {
    let ports: Vec<String> = config
        .sections
        .iter()
        .map(|s| {
            let ip = s
                .ipaddr_local
                .map_or("0.0.0.0".to_string(), |ip| ip.to_string());
            format!("{ip}:{}", s.server_port)
        })
        .collect();
    format!(
        "DEMO: no -c and no PLCComS.ini here, so a SIMULATED demo PLC is running \
         (the built-in PLCComS.ini.example), not a real one; clients on {} only. \
         For real PLCs: plccoms -c /path/to/PLCComS.ini",
        ports.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_demo_is_simulated_and_on_loopback_only() {
        let loaded = plccoms_core::config::parse(std::path::Path::new(NAME), CONFIG).unwrap();
        assert!(!loaded.config.sections.is_empty());
        for section in &loaded.config.sections {
            assert!(section.simulator.is_some(), "[{}]", section.name);
            let local = section.ipaddr_local.expect("IPADDR_LOCAL");
            assert!(local.is_loopback(), "[{}] {local}", section.name);
        }
        let banner = banner(&loaded.config);
        assert!(banner.contains("SIMULATED demo PLC"), "{banner}");
        assert!(banner.contains("127.0.0.1:5010 only"), "{banner}");
        assert!(banner.contains("plccoms -c "), "{banner}");
        assert!(HELP.contains("127.0.0.1:5010"), "{HELP}");
    }
}
