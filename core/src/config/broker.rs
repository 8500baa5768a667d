//! `MQTT_URL`: the brokers' addresses and transport, parsed once when the
//! configuration is loaded. Several URLs are the nodes of a cluster (or a
//! primary and a standby), tried round robin.

/// A broker address from MQTT_URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BrokerUrl {
    pub host: String,
    pub port: u16,
    pub tls: bool,
}

impl BrokerUrl {
    /// `mqtt://host[:port]` (port 1883) or `mqtts://host[:port]` (8883); the
    /// host a name, an IPv4 address or `[IPv6]`. `Err` says what is wrong.
    pub fn parse(text: &str) -> Result<BrokerUrl, String> {
        let (scheme, rest) = text
            .split_once("://")
            .ok_or("is not a URL (mqtt://host:port or mqtts://host:port)")?;
        let (tls, default_port) = match scheme.to_ascii_lowercase().as_str() {
            "mqtt" | "tcp" => (false, 1883),
            "mqtts" | "ssl" => (true, 8883),
            _ => return Err(format!("has scheme '{scheme}' (allowed mqtt, mqtts)")),
        };
        let authority = rest.strip_suffix('/').unwrap_or(rest);
        if authority.contains('/') || authority.contains('?') || authority.contains('#') {
            return Err("has a path or query (only mqtt://host:port)".into());
        }
        if authority.contains('@') {
            return Err("holds a user (give MQTT_USER and MQTT_PASSWORD instead)".into());
        }
        let bracketed = authority.starts_with('[');
        let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
            let (host, after) = v6.split_once(']').ok_or("has '[' without ']'")?;
            if host.parse::<std::net::Ipv6Addr>().is_err() {
                return Err(format!("has '[{host}]', which is not an IPv6 address"));
            }
            match after {
                "" => (host, None),
                _ => (
                    host,
                    Some(after.strip_prefix(':').ok_or("has text after ']'")?),
                ),
            }
        } else {
            match authority.rsplit_once(':') {
                Some((host, port)) => (host, Some(port)),
                None => (authority, None),
            }
        };
        if host.is_empty() {
            return Err("has no host".into());
        }
        if !bracketed
            && !host
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'))
        {
            return Err(format!(
                "has host '{host}', which is not a host name or address"
            ));
        }
        let port = match port {
            None => default_port,
            Some(p) => match p.parse::<u16>() {
                Ok(port) if port > 0 && p.bytes().all(|b| b.is_ascii_digit()) => port,
                _ => return Err(format!("has port '{p}' (allowed 1-65535)")),
            },
        };
        Ok(BrokerUrl {
            host: host.to_string(),
            port,
            tls,
        })
    }

    /// The most URLs MQTT_URL may list (a cluster's nodes, a standby).
    pub const MAX_LIST: usize = 16;

    /// MQTT_URL: one URL or several, separated by commas and/or blanks,
    /// each one as [`BrokerUrl::parse`] takes it; never empty, no URL
    /// twice. `Err` names the URL at fault by its place in the list.
    pub fn parse_list(text: &str) -> Result<Vec<BrokerUrl>, String> {
        let parts: Vec<&str> = text
            .split(|c: char| c == ',' || c.is_whitespace())
            .filter(|p| !p.is_empty())
            .collect();
        if parts.is_empty() {
            return Err("is empty (mqtt://host:port, several separated by commas)".into());
        }
        if parts.len() > Self::MAX_LIST {
            return Err(format!(
                "lists {} URLs (at most {})",
                parts.len(),
                Self::MAX_LIST
            ));
        }
        let mut list: Vec<BrokerUrl> = Vec::with_capacity(parts.len());
        for (n, part) in parts.iter().enumerate() {
            let url = BrokerUrl::parse(part).map_err(|problem| match parts.len() {
                1 => problem,
                _ => format!("(URL {} of {}, {part}) {problem}", n + 1, parts.len()),
            })?;
            if list.contains(&url) {
                return Err(format!("lists {part} twice"));
            }
            list.push(url);
        }
        Ok(list)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broker_urls() {
        for (text, host, port, tls) in [
            ("mqtt://broker", "broker", 1883, false),
            ("mqtts://10.0.0.1", "10.0.0.1", 8883, true),
            ("MQTT://b.lan:1884/", "b.lan", 1884, false),
            ("mqtts://[::1]:8884", "::1", 8884, true),
            ("mqtt://[fe80::1]", "fe80::1", 1883, false),
        ] {
            let host = host.to_string();
            assert_eq!(BrokerUrl::parse(text), Ok(BrokerUrl { host, port, tls }));
        }
        for (bad, says) in [
            ("broker:1883", "is not a URL"),
            ("http://b", "scheme 'http'"),
            ("mqtt://", "no host"),
            ("mqtt://b:0", "port '0'"),
            ("mqtt://b:70000", "port '70000'"),
            ("mqtt://b:+1", "port '+1'"),
            ("mqtt://u:p@b", "MQTT_USER"),
            ("mqtt://b/topic", "path"),
            ("mqtt://[::1", "without ']'"),
            ("mqtt://[zz]:1", "not an IPv6"),
            ("mqtt://b c", "not a host name"),
            ("mqtt://::1", "not a host name"),
        ] {
            let problem = BrokerUrl::parse(bad).unwrap_err();
            assert!(problem.contains(says), "{bad}: {problem}");
        }
    }

    #[test]
    fn broker_lists() {
        let url = |host: &str, port| BrokerUrl {
            host: host.into(),
            port,
            tls: false,
        };
        assert_eq!(BrokerUrl::parse_list("mqtt://a"), Ok(vec![url("a", 1883)]));
        for text in [
            "mqtt://a:1,mqtt://b:2 mqtt://c:3",
            " mqtt://a:1 , mqtt://b:2,\tmqtt://c:3, ",
        ] {
            assert_eq!(
                BrokerUrl::parse_list(text),
                Ok(vec![url("a", 1), url("b", 2), url("c", 3)]),
                "{text}"
            );
        }
        for (bad, says) in [
            ("", "is empty"),
            (" , ", "is empty"),
            ("http://b", "scheme 'http'"),
            (
                "mqtt://a, mqtt://b:0",
                "(URL 2 of 2, mqtt://b:0) has port '0'",
            ),
            ("mqtt://a,b", "(URL 2 of 2, b) is not a URL"),
            ("mqtt://a mqtt://a:1883", "lists mqtt://a:1883 twice"),
        ] {
            let problem = BrokerUrl::parse_list(bad).unwrap_err();
            assert!(problem.contains(says), "{bad}: {problem}");
        }
        let many = vec!["mqtt://h"; BrokerUrl::MAX_LIST + 1]
            .iter()
            .enumerate()
            .map(|(n, u)| format!("{u}:{}", n + 1))
            .collect::<Vec<_>>()
            .join(",");
        assert!(BrokerUrl::parse_list(&many)
            .unwrap_err()
            .contains("at most"));
    }
}
