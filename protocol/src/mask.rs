//! Wildcard masks for variable names: `*` matches any run of characters
//! (including none), any number of `*` per mask. There is no other wildcard
//! and no implied leading or trailing `*`.

use crate::cp1250;

/// A compiled mask. The pattern is kept upper-cased (cp1250), so matching
/// takes names that are upper-cased already.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Mask {
    pattern: Vec<u8>,
}

impl Mask {
    pub fn new(pattern: &[u8]) -> Mask {
        let mut pattern = cp1250::to_upper(pattern);
        // `**` matches what `*` matches: a run of stars costs one.
        pattern.dedup_by(|a, b| *a == b'*' && *b == b'*');
        Mask { pattern }
    }

    /// The fewest bytes a matching name has (its characters other than
    /// `*`): a mask longer than every name matches none, without trying.
    pub fn min_len(&self) -> usize {
        self.pattern.iter().filter(|&&b| b != b'*').count()
    }

    /// The upper-cased pattern.
    pub fn pattern(&self) -> &[u8] {
        &self.pattern
    }

    pub fn has_wildcard(&self) -> bool {
        self.pattern.contains(&b'*')
    }

    /// The "all" form (empty or only `*`): it skips hidden variables.
    pub fn is_all(&self) -> bool {
        self.pattern.iter().all(|&b| b == b'*')
    }

    /// Whether `upper_name` (already upper-case) matches. An empty pattern
    /// matches everything, as a bare `GET:` or `EN:` means all.
    ///
    /// Greedy two-pointer match that on a mismatch backtracks only to the
    /// last `*`: O(pattern * name) at worst, no recursion.
    pub fn matches(&self, upper_name: &[u8]) -> bool {
        if self.pattern.is_empty() {
            return true;
        }
        let (p, n) = (&self.pattern[..], upper_name);
        let (mut pi, mut ni) = (0, 0);
        // Position after the last `*` seen, and the name position it was tried at.
        let mut star: Option<(usize, usize)> = None;
        while ni < n.len() {
            if pi < p.len() && p[pi] == b'*' {
                pi += 1;
                star = Some((pi, ni));
            } else if pi < p.len() && p[pi] == n[ni] {
                pi += 1;
                ni += 1;
            } else if let Some((sp, sn)) = star {
                // Let the last `*` swallow one more byte and retry.
                pi = sp;
                ni = sn + 1;
                star = Some((sp, sn + 1));
            } else {
                return false;
            }
        }
        p[pi..].iter().all(|&b| b == b'*')
    }

    /// Like [`Mask::matches`], for masks that mean the project's variables
    /// (MQTT_PUBLISH, MQTT_WRITE): a system variable (`__...`) or a direct
    /// address (`%...`) is matched only by a mask that begins the same way
    /// (`__*`, `%R*`), never by `*` or `*RUN`.
    pub fn matches_name(&self, upper_name: &[u8]) -> bool {
        for special in [&b"__"[..], b"%"] {
            if upper_name.starts_with(special) && !self.pattern.starts_with(special) {
                return false;
            }
        }
        self.matches(upper_name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(pattern: &str, name: &str) -> bool {
        Mask::new(pattern.as_bytes()).matches(&cp1250::to_upper(name.as_bytes()))
    }

    #[test]
    fn names_of_the_project_only_unless_the_mask_says_otherwise() {
        let n =
            |pattern: &str, name: &str| Mask::new(pattern.as_bytes()).matches_name(name.as_bytes());
        assert!(n("*", "COUNTER"));
        assert!(!n("*", "__PLC_RUN"));
        assert!(!n("*RUN", "__PLC_RUN"));
        assert!(!n("*", "%R100"));
        assert!(!n("*R100", "%R100"));
        assert!(n("__*", "__PLC_RUN"));
        assert!(n("__PLC_RUN", "__PLC_RUN"));
        assert!(n("%R*", "%R100"));
        assert!(!n("_*", "__PLC_RUN"));
        assert!(n("_*", "_LOCAL"));
        // The line protocol's masks are unchanged.
        assert!(m("*", "__PLC_RUN"));
    }

    #[test]
    fn manual_prefix_mask() {
        assert!(m("test_*", "test_1"));
        assert!(m("test_*", "TEST_2"));
        assert!(m("TEST_*", "test_"));
        assert!(!m("test_*", "test"));
        assert!(!m("test_*", "xtest_1"));
    }

    #[test]
    fn exact_without_star() {
        assert!(m("x", "X"));
        assert!(m("Get_Me", "GET_ME"));
        assert!(!m("temp", "temperature"));
        assert!(!m("temperature", "temp"));
        assert!(m("T_ZONES_SET[0].TOPIT_TC", "t_zones_set[0].topit_tc"));
    }

    #[test]
    fn several_stars() {
        assert!(m("*", ""));
        assert!(m("*", "anything"));
        assert!(m("**", "a"));
        assert!(m("*temp*", "roomtemperature"));
        assert!(m("a*b*c", "abc"));
        assert!(m("a*b*c", "axxbyyc"));
        assert!(!m("a*b*c", "axxbyy"));
        assert!(m("a*b*c", "abcbc"));
        assert!(!m("a*b", "abba_"));
        assert!(m("*.windDirection", "Meteo.WindDirection"));
        assert!(m("a*a*a*a*a*b", &("a".repeat(40) + "b")));
        assert!(!m("a*a*a*a*a*b", &"a".repeat(4000)));
    }

    #[test]
    fn czech_case_insensitive() {
        let pat = cp1250::encode("teplota_č*");
        let name = cp1250::to_upper(&cp1250::encode("TEPLOTA_ČERPADLO"));
        assert!(Mask::new(&pat).matches(&name));
    }

    #[test]
    fn all_form_and_wildcard() {
        assert!(Mask::new(b"").is_all());
        assert!(Mask::new(b"*").is_all());
        assert!(Mask::new(b"***").is_all());
        assert!(!Mask::new(b"a*").is_all());
        assert!(Mask::new(b"a*").has_wildcard());
        assert!(!Mask::new(b"abc").has_wildcard());
        assert!(Mask::new(b"").matches(b"ANY"));
        assert_eq!(Mask::new(b"ab*").pattern(), b"AB*");
    }

    #[test]
    fn star_runs_collapse_and_min_len_counts_the_rest() {
        let mask = Mask::new(b"**a***b*");
        assert_eq!(mask.pattern(), b"*A*B*");
        assert_eq!(mask.min_len(), 2);
        assert!(mask.matches(b"XAYBZ"));
        assert_eq!(Mask::new(b"").min_len(), 0);
    }
}
