//! The committed man pages and shell completions (`doc/`) are what the
//! clap definitions generate now: a changed option without
//! `cargo run -p plccoms-tools --bin gen-docs` fails here.

#[test]
fn man_pages_and_completions_are_not_stale() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_gen-docs"))
        .arg("--check")
        .output()
        .expect("run gen-docs --check");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Every page of ours a man page names (`plccoms\-history(8)`,
/// `\fBplccoms\fR(8)`) exists in doc/man: no reference to a page we do not
/// ship.
#[test]
fn man_pages_name_only_pages_that_exist() {
    let man = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../doc/man");
    let mut named = Vec::new();
    for entry in std::fs::read_dir(&man).expect("doc/man") {
        let path = entry.expect("entry").path();
        let text = std::fs::read_to_string(&path).expect("page");
        let plain = text
            .replace("\\-", "-")
            .replace("\\fB", "")
            .replace("\\fR", "");
        for (i, _) in plain.match_indices('(') {
            let before = &plain[..i];
            let name: String = before
                .chars()
                .rev()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '_')
                .collect::<String>()
                .chars()
                .rev()
                .collect();
            let section: String = plain[i + 1..]
                .chars()
                .take_while(char::is_ascii_digit)
                .collect();
            if (name.starts_with("plccoms") || name.starts_with("plcsim")) && !section.is_empty() {
                named.push((path.clone(), format!("{name}.{section}")));
            }
        }
    }
    assert!(
        named.iter().any(|(_, page)| page == "plccoms-history.8"),
        "the SUBCOMMANDS section names plccoms-history(8): {named:?}"
    );
    for (page, name) in named {
        assert!(
            man.join(&name).exists(),
            "{} names {name}, which doc/man lacks",
            page.display()
        );
    }
}
