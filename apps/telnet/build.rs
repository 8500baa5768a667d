//! Stamps the build's date for `GETINFO:version`, which answers in the
//! vendor's shape `Ver 5.5 Sep  9 2020 16:10:19` (C's `__DATE__ __TIME__`).
//! `SOURCE_DATE_EPOCH` (reproducible builds) gives the date; without it the
//! time of the build, in UTC.

fn main() {
    println!("cargo:rerun-if-env-changed=SOURCE_DATE_EPOCH");
    println!("cargo:rerun-if-changed=src");
    println!("cargo:rerun-if-changed=Cargo.toml");
    let when = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|secs| secs.trim().parse::<i64>().ok())
        .and_then(|secs| chrono::DateTime::from_timestamp(secs, 0))
        .unwrap_or_else(chrono::Utc::now);
    println!(
        "cargo:rustc-env=PLCCOMS_BUILD_DATE={}",
        when.format("%b %e %Y %H:%M:%S")
    );
}
