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
