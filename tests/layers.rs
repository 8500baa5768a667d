//! The layers' rules (ARCHITECTURE.md), read from every crate's Cargo.toml:
//! a crate that depends on a layer it may not fails here, with the arrow
//! named. Cargo already refuses circles between crates; this refuses the
//! wrong arrows that would not be circles (an app importing a driver, core
//! importing an app's crate, a driver importing another driver).

use std::collections::BTreeSet;
use std::path::Path;

/// Where a crate of ours stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Layer {
    Protocol,
    Plc,
    /// The plugin ABI: types a plugin and the plugin host share; imports
    /// nothing of ours.
    PluginAbi,
    Core,
    Driver,
    App,
    /// The plccoms binary: wires drivers and apps to the core.
    Binary,
    /// The simulated PLC: a device, so the PLC model and nothing above.
    Simulator,
    /// Tools, plugins, benchmarks: outside the layers, may use any crate.
    Outside,
}

fn layer_of(dir: &str, name: &str) -> Layer {
    match (dir, name) {
        (_, "plccoms-protocol") => Layer::Protocol,
        (_, "plccoms-plc") => Layer::Plc,
        (_, "plccoms-plugin-abi") => Layer::PluginAbi,
        (_, "plccoms-core") => Layer::Core,
        (_, "plcsim") => Layer::Simulator,
        (_, "plccoms") => Layer::Binary,
        (dir, _) if dir.starts_with("drivers/") => Layer::Driver,
        (dir, _) if dir.starts_with("apps/") => Layer::App,
        (dir, _) if dir == "tools" || dir.starts_with("plugins/") => Layer::Outside,
        (dir, name) => {
            panic!("{dir} ({name}) is in no layer: place it in tests/layers.rs and ARCHITECTURE.md")
        }
    }
}

/// Whether a crate of layer `from` may depend on one of layer `to`
/// (`dev`: only for its tests).
fn may_import(from: Layer, to: Layer, dev: bool) -> bool {
    use Layer::*;
    match from {
        Protocol => false,
        Plc => to == Protocol,
        PluginAbi => false,
        Core => matches!(to, Protocol | Plc),
        // A driver's tests may run against the simulated PLC.
        Driver => matches!(to, Protocol | Plc | Core | PluginAbi) || (dev && to == Simulator),
        App => matches!(to, Protocol | Core),
        Simulator => matches!(to, Protocol | Plc),
        Binary | Outside => true,
    }
}

/// The crates of ours a manifest depends on: (name, only for tests).
fn our_dependencies(manifest: &str) -> Vec<(String, bool)> {
    let mut deps = Vec::new();
    let mut section: Option<bool> = None;
    for line in manifest.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            let table = line.trim_matches(|c| c == '[' || c == ']');
            // The root's [workspace.dependencies] lists versions, not arrows.
            section = match table
                .rsplit('.')
                .next()
                .filter(|_| !table.starts_with("workspace"))
            {
                Some("dependencies" | "build-dependencies") => Some(false),
                Some("dev-dependencies") => Some(true),
                _ => None,
            };
            continue;
        }
        let Some(dev) = section else { continue };
        let name = line
            .split(['=', '.', ' '])
            .next()
            .unwrap_or_default()
            .trim();
        if name.starts_with("plccoms") || name == "plcsim" {
            deps.push((name.to_string(), dev));
        }
    }
    deps
}

fn package_name(manifest: &str) -> String {
    manifest
        .lines()
        .skip_while(|line| line.trim() != "[package]")
        .find_map(|line| line.trim().strip_prefix("name = "))
        .map(|name| name.trim_matches('"').to_string())
        .expect("[package] name")
}

/// The workspace's members as the root manifest lists them.
fn members(root: &str) -> Vec<String> {
    let start = root.find("members = [").expect("workspace members");
    let list = &root[start..];
    let list = &list[list.find('[').unwrap() + 1..list.find(']').unwrap()];
    list.split(',')
        .map(|m| m.trim().trim_matches('"').to_string())
        .filter(|m| !m.is_empty())
        .collect()
}

/// Every wrong arrow among `crates` (directory, manifest text).
fn violations(crates: &[(String, String)]) -> Vec<String> {
    let layers: Vec<(String, Layer)> = crates
        .iter()
        .map(|(dir, manifest)| {
            let name = package_name(manifest);
            let layer = layer_of(dir, &name);
            (name, layer)
        })
        .collect();
    let layer_named = |name: &str| layers.iter().find(|(n, _)| n == name).map(|(_, l)| *l);
    let mut wrong = Vec::new();
    for ((dir, manifest), (name, from)) in crates.iter().zip(&layers) {
        for (dep, dev) in our_dependencies(manifest) {
            let Some(to) = layer_named(&dep) else {
                wrong.push(format!(
                    "{dir}: {name} depends on {dep}, which is no member"
                ));
                continue;
            };
            if !may_import(*from, to, dev) {
                let kind = if dev { " (dev)" } else { "" };
                wrong.push(format!(
                    "{dir}: {name} ({from:?}) may not depend on {dep} ({to:?}){kind}"
                ));
            }
        }
    }
    wrong
}

#[test]
fn no_crate_imports_a_layer_it_may_not() {
    let root_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = std::fs::read_to_string(root_dir.join("Cargo.toml")).unwrap();
    let crates: Vec<(String, String)> = members(&root)
        .into_iter()
        .map(|dir| {
            let manifest = if dir == "." {
                root.clone()
            } else {
                std::fs::read_to_string(root_dir.join(&dir).join("Cargo.toml"))
                    .unwrap_or_else(|e| panic!("{dir}/Cargo.toml: {e}"))
            };
            (dir, manifest)
        })
        .collect();
    let names: BTreeSet<String> = crates.iter().map(|(_, m)| package_name(m)).collect();
    for expected in ["plccoms-protocol", "plccoms-plc", "plccoms-core", "plccoms"] {
        assert!(
            names.contains(expected),
            "{expected} is no member: {names:?}"
        );
    }
    assert!(
        crates
            .iter()
            .filter(|(d, _)| d.starts_with("drivers/"))
            .count()
            >= 3
    );
    assert!(
        crates
            .iter()
            .filter(|(d, _)| d.starts_with("apps/"))
            .count()
            >= 4
    );
    let wrong = violations(&crates);
    assert!(wrong.is_empty(), "wrong arrows:\n{}", wrong.join("\n"));
}

/// The fuzz crate is a workspace of its own; it may use any layer but must
/// name only crates that exist.
#[test]
fn the_fuzz_crate_names_only_members() {
    let root_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let manifest = std::fs::read_to_string(root_dir.join("fuzz/Cargo.toml")).unwrap();
    for (dep, _) in our_dependencies(&manifest) {
        let path = manifest
            .lines()
            .find(|line| line.trim_start().starts_with(&format!("{dep} =")))
            .and_then(|line| line.split("path = \"").nth(1))
            .and_then(|rest| rest.split('"').next())
            .unwrap_or_else(|| panic!("fuzz/Cargo.toml: {dep} has no path"));
        assert!(
            root_dir.join("fuzz").join(path).join("Cargo.toml").exists(),
            "fuzz/Cargo.toml: {dep} at {path} does not exist"
        );
    }
}

/// The check itself: each kind of wrong arrow is found and named.
#[test]
fn wrong_arrows_are_named() {
    let manifest = |name: &str, deps: &[&str], dev: &[&str]| {
        let mut text = format!("[package]\nname = \"{name}\"\n\n[dependencies]\n");
        for dep in deps {
            text.push_str(&format!("{dep}.workspace = true\n"));
        }
        text.push_str("tokio = \"1\"\n\n[dev-dependencies]\n");
        for dep in dev {
            text.push_str(&format!("{dep} = {{ path = \"x\" }}\n"));
        }
        text
    };
    let good = vec![
        (
            "protocol".to_string(),
            manifest("plccoms-protocol", &[], &[]),
        ),
        (
            "plc".to_string(),
            manifest("plccoms-plc", &["plccoms-protocol"], &[]),
        ),
        (
            "core".to_string(),
            manifest("plccoms-core", &["plccoms-plc"], &[]),
        ),
        (
            "plcsim".to_string(),
            manifest("plcsim", &["plccoms-plc"], &[]),
        ),
        (
            "drivers/a".to_string(),
            manifest("plccoms-driver-a", &["plccoms-core"], &["plcsim"]),
        ),
        (
            "apps/b".to_string(),
            manifest("plccoms-b", &["plccoms-core", "plccoms-protocol"], &[]),
        ),
        (
            ".".to_string(),
            manifest("plccoms", &["plccoms-driver-a", "plccoms-b"], &[]),
        ),
    ];
    assert_eq!(violations(&good), Vec::<String>::new());
    let with = |dir: &str, text: String| {
        let mut crates = good.clone();
        crates.retain(|(d, _)| d != dir);
        crates.push((dir.to_string(), text));
        violations(&crates)
    };
    assert_eq!(
        with("apps/b", manifest("plccoms-b", &["plccoms-driver-a"], &[])),
        ["apps/b: plccoms-b (App) may not depend on plccoms-driver-a (Driver)"]
    );
    assert_eq!(
        with("core", manifest("plccoms-core", &["plccoms-b"], &[])),
        ["core: plccoms-core (Core) may not depend on plccoms-b (App)"]
    );
    assert_eq!(
        with("apps/b", manifest("plccoms-b", &[], &["plccoms-driver-a"])),
        ["apps/b: plccoms-b (App) may not depend on plccoms-driver-a (Driver) (dev)"]
    );
    assert_eq!(
        with("plc", manifest("plccoms-plc", &["plccoms-core"], &[])),
        ["plc: plccoms-plc (Plc) may not depend on plccoms-core (Core)"]
    );
    assert_eq!(
        with("drivers/a", manifest("plccoms-driver-a", &["plcsim"], &[])),
        ["drivers/a: plccoms-driver-a (Driver) may not depend on plcsim (Simulator)"]
    );
}

/// `-v`/`-vv` raise the reports of the crates plccoms::OUR_CRATES lists
/// and keep the libraries' at info: every crate the server runs is there.
#[test]
fn every_crate_the_server_runs_is_raised_by_verbose() {
    let root_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let root = std::fs::read_to_string(root_dir.join("Cargo.toml")).unwrap();
    for dir in members(&root) {
        let manifest = if dir == "." {
            root.clone()
        } else {
            std::fs::read_to_string(root_dir.join(&dir).join("Cargo.toml")).unwrap()
        };
        let name = package_name(&manifest);
        if matches!(layer_of(&dir, &name), Layer::Outside | Layer::PluginAbi) {
            continue;
        }
        let lib = name.replace('-', "_");
        assert!(
            plccoms::OUR_CRATES.contains(&lib.as_str()),
            "{lib} is not in plccoms::OUR_CRATES: -vv would not show its reports"
        );
    }
    let filter = plccoms::log_filter("trace");
    assert!(filter.starts_with("info,"), "{filter}");
    assert!(filter.contains(",plccoms_core=trace"), "{filter}");
}
