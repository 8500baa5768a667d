//! OPC UA node ids in their text form (OPC 10000-6, 5.3.1.10), as the
//! tag file and `OPCUA_BROWSE` write them:
//!
//! ```text
//! i=85                       namespace 0, numeric
//! ns=3;s="DB_Line1"."Speed"  namespace 3, string (everything after s=)
//! ns=2;g=09087E75-8E5E-499B-954F-F2A9603DB28A
//! ns=1;b=M/RbKBsRVkePCePcx24oRA==
//! nsu=http://example.com/plc;i=6001
//! ```
//!
//! `nsu=` names the namespace by URI; the backend finds its index in the
//! server's NamespaceArray. Pure: text in, a [`NodeRef`] or the reason out.

use std::fmt;

/// Longest node id text accepted: S7-1500 string ids are long, but not this.
pub const MAX_NODE_ID: usize = 4096;

/// Which namespace a node id is in.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Namespace {
    Index(u16),
    Uri(String),
}

/// The identifier part of a node id.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Identifier {
    Numeric(u32),
    String(String),
    /// Canonical upper-case `8-4-4-4-12` hex.
    Guid(String),
    /// Base64 text, checked for its alphabet and length.
    Opaque(String),
}

/// A parsed node id.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct NodeRef {
    pub namespace: Namespace,
    pub identifier: Identifier,
}

impl NodeRef {
    /// A numeric id in namespace 0 (the standard nodes).
    pub const fn standard(id: u32) -> NodeRef {
        NodeRef {
            namespace: Namespace::Index(0),
            identifier: Identifier::Numeric(id),
        }
    }
}

/// Parses a node id's text; the error says what is wrong and where.
pub fn parse(text: &str) -> Result<NodeRef, String> {
    let text = text.trim();
    if text.len() > MAX_NODE_ID {
        return Err(format!("node id longer than {MAX_NODE_ID} characters"));
    }
    let (namespace, rest) = if let Some(rest) = text.strip_prefix("ns=") {
        let (index, rest) = rest
            .split_once(';')
            .ok_or_else(|| format!("node id '{text}': ns= without ';' before the identifier"))?;
        let index = index
            .parse::<u16>()
            .map_err(|_| format!("node id '{text}': namespace index '{index}' is not 0-65535"))?;
        (Namespace::Index(index), rest)
    } else if let Some(rest) = text.strip_prefix("nsu=") {
        // The URI may not contain ';' (it would be escaped as %3B).
        let (uri, rest) = rest
            .split_once(';')
            .ok_or_else(|| format!("node id '{text}': nsu= without ';' before the identifier"))?;
        if uri.is_empty() {
            return Err(format!("node id '{text}': empty namespace URI"));
        }
        (Namespace::Uri(uri.to_string()), rest)
    } else {
        (Namespace::Index(0), text)
    };
    let (kind, value) = rest
        .split_once('=')
        .ok_or_else(|| format!("node id '{text}': expected i=, s=, g= or b= identifier"))?;
    let identifier = match kind {
        "i" => Identifier::Numeric(value.parse::<u32>().map_err(|_| {
            format!("node id '{text}': numeric identifier '{value}' is not 0-4294967295")
        })?),
        "s" if !value.is_empty() => Identifier::String(value.to_string()),
        "s" => return Err(format!("node id '{text}': empty string identifier")),
        "g" => Identifier::Guid(guid(value).ok_or_else(|| {
            format!("node id '{text}': '{value}' is not a GUID (8-4-4-4-12 hex digits)")
        })?),
        "b" if is_base64(value) => Identifier::Opaque(value.to_string()),
        "b" => return Err(format!("node id '{text}': '{value}' is not base64")),
        other => {
            return Err(format!(
                "node id '{text}': unknown identifier type '{other}=' (i, s, g or b)"
            ))
        }
    };
    Ok(NodeRef {
        namespace,
        identifier,
    })
}

fn guid(text: &str) -> Option<String> {
    let groups: Vec<&str> = text.split('-').collect();
    let lens = [8, 4, 4, 4, 12];
    (groups.len() == 5
        && groups
            .iter()
            .zip(lens)
            .all(|(g, n)| g.len() == n && g.bytes().all(|b| b.is_ascii_hexdigit())))
    .then(|| text.to_ascii_uppercase())
}

fn is_base64(text: &str) -> bool {
    let body = text.trim_end_matches('=');
    !text.is_empty()
        && text.len().is_multiple_of(4)
        && text.len() - body.len() <= 2
        && body
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'+' || b == b'/')
}

impl fmt::Display for NodeRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.namespace {
            Namespace::Index(0) => {}
            Namespace::Index(n) => write!(f, "ns={n};")?,
            Namespace::Uri(uri) => write!(f, "nsu={uri};")?,
        }
        match &self.identifier {
            Identifier::Numeric(n) => write!(f, "i={n}"),
            Identifier::String(s) => write!(f, "s={s}"),
            Identifier::Guid(g) => write!(f, "g={g}"),
            Identifier::Opaque(b) => write!(f, "b={b}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_form_parses_and_prints_back() {
        for text in [
            "i=85",
            "ns=3;s=\"DB_Line1\".\"Speed\"",
            "ns=2;g=09087E75-8E5E-499B-954F-F2A9603DB28A",
            "ns=1;b=M/RbKBsRVkePCePcx24oRA==",
            "nsu=http://example.com/plc;i=6001",
            "ns=2;s=a=b;c",
        ] {
            let node = parse(text).unwrap();
            assert_eq!(node.to_string(), text);
            assert_eq!(parse(&node.to_string()).unwrap(), node);
        }
        assert_eq!(parse(" ns=0;i=85 ").unwrap(), NodeRef::standard(85));
    }

    #[test]
    fn errors_name_the_fault() {
        for (text, says) in [
            ("", "expected i="),
            ("ns=70000;i=1", "namespace index"),
            ("ns=1", "without ';'"),
            ("ns=1;x=2", "unknown identifier type 'x='"),
            ("i=-1", "numeric identifier"),
            ("ns=1;s=", "empty string"),
            ("g=1234", "not a GUID"),
            ("b=@@@@", "not base64"),
            ("nsu=;i=1", "empty namespace URI"),
        ] {
            let err = parse(text).unwrap_err();
            assert!(err.contains(says), "{text}: {err}");
        }
        assert!(parse(&"s=x".repeat(2000)).is_err());
    }
}
