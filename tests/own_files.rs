//! Every file and folder the configuration names is the server's own: for
//! each path key of the key table (`Kind::Path`), whatever its consumer
//! makes of it (a part that fails to start included), a line-protocol client
//! never writes it, and never reads it when it holds a key or a password or
//! is a folder the server writes. The keys are walked from the table, so a
//! path key added later is covered without a change here.
//!
//! Also: a plugin library that others could replace is refused at load, and
//! the clients' folder defaults to one of its own under systemd's
//! `$STATE_DIRECTORY`.

mod common;

use common::{process::free_port, Client};
use plccoms_core::config::{keys, Kind, PathUse, Scope};

#[tokio::test]
async fn no_client_writes_any_path_a_key_names_nor_reads_its_secrets() {
    let mut walked = 0;
    for key in keys() {
        let Kind::Path(used) = key.kind else { continue };
        if used == PathUse::ClientFiles {
            continue;
        }
        walked += 1;
        let name = format!("own-{}", key.name.to_lowercase());
        // The key names a file (a folder for State) in the clients' folder,
        // which is the configuration's by default, as the vendor's.
        let (global, section) = match key.scope() {
            Scope::Global => (format!("{} = ./{name}\n", key.name), String::new()),
            // On a section of its own, which may fail to start with such a
            // file: the demo section serves the client.
            Scope::Section => (
                String::new(),
                format!(
                    "\n[Other]\nSERVER_PORT = {}\nIPADDR = 0.0.0.0\n{} = ./{name}\n",
                    free_port(),
                    key.name
                ),
            ),
        };
        let (server, addr, dir) = common::simulated(&global, &section, None).await;
        let own = dir.path().join(&name);
        let inner = if used == PathUse::State {
            std::fs::create_dir_all(&own).unwrap();
            let inner = own.join("0001.seg");
            std::fs::write(&inner, b"state").unwrap();
            Some(inner)
        } else {
            std::fs::write(&own, b"private").unwrap();
            None
        };
        let mut c = Client::connect(addr).await;
        let target = match &inner {
            Some(_) => format!("./{name}/0001.seg"),
            None => format!("./{name}"),
        };
        assert_eq!(
            c.writefile(&target, b"client").await,
            format!("ERROR:42 Unable to write file: '{target}'\r\n"),
            "{} ({used:?}): written",
            key.name
        );
        if inner.is_some() {
            let added = format!("./{name}/0002.seg");
            assert_eq!(
                c.writefile(&added, b"client").await,
                format!("ERROR:42 Unable to write file: '{added}'\r\n"),
                "{}: a file added to the folder",
                key.name
            );
            assert!(!own.join("0002.seg").exists());
        }
        c.ask(
            &format!("WRITEFILEINFO:./{name}[27]=0 1 24700000000 24700000000\n"),
            &format!("ERROR:43 Unable to write file information: './{name}'\r\n"),
        )
        .await;
        let on_disk = std::fs::read(inner.as_ref().unwrap_or(&own)).unwrap();
        assert!(
            on_disk == b"private" || on_disk == b"state",
            "{}: the file changed",
            key.name
        );
        if used == PathUse::Input {
            c.ask(
                &format!("GETFILE:{target}\n"),
                &format!("GETFILE:{target}[7]=private\r\n"),
            )
            .await;
            c.expect(format!("GETFILE:{target}[0]=\r\n").as_bytes())
                .await;
        } else {
            c.ask(
                &format!("GETFILE:{target}\n"),
                &format!("ERROR:41 Unable to get file: '{target}'\r\n"),
            )
            .await;
            c.ask(
                &format!("GETFILEINFO:{target}\n"),
                &format!("ERROR:40 Unable to get information about file: '{target}'\r\n"),
            )
            .await;
        }
        drop(c);
        server.shutdown().await;
    }
    assert!(walked >= 14, "only {walked} path keys walked");
}

#[tokio::test]
async fn a_plugin_library_others_could_replace_is_refused_with_a_clear_line() {
    use std::os::unix::fs::PermissionsExt;
    let logs = common::logs::Logs::install();
    let dir = tempfile::tempdir().unwrap();
    let library = dir.path().join("libplant.so");
    std::fs::copy(common::process::plugin_lib("demo"), &library).unwrap();
    std::fs::set_permissions(&library, std::fs::Permissions::from_mode(0o664)).unwrap();
    let port = free_port();
    let ini = dir.path().join("PLCComS.ini");
    // A relative SHM_NAME starts from the configuration's folder, not from
    // wherever the server was started.
    std::fs::write(
        &ini,
        format!(
            "[*]\n[Plant]\nSERVER_PORT = {port}\nSHM_NAME = ./libplant.so\n\
                 SHM_SOCKET = 0\nSHM_PORT = 5\nPUBFILE = //demo.pub\n"
        ),
    )
    .unwrap();
    let config = plccoms_core::config::load(&ini).unwrap().config;
    let server = plccoms::startup::start(&config).await.unwrap();
    let mut c = Client::connect(std::net::SocketAddr::from(([127, 0, 0, 1], port))).await;
    common::health::until(
        &mut c,
        "GET:__PLC_RUN\n",
        "ERROR:10 Unable to connect to PLC.\r\n",
        std::time::Duration::from_secs(10),
    )
    .await;
    let refusal = "writable by group or others (mode 0664";
    common::epsnet::eventually(
        "the refusal logged",
        std::time::Duration::from_secs(10),
        || logs.count(refusal) > 0,
    )
    .await;
    assert!(logs.text().contains("libplant.so"), "{}", logs.text());
    server.shutdown().await;

    // Read-only for group and others: loaded, the PLC answers.
    std::fs::set_permissions(&library, std::fs::Permissions::from_mode(0o644)).unwrap();
    let server = plccoms::startup::start(&config).await.unwrap();
    let mut c = Client::connect(std::net::SocketAddr::from(([127, 0, 0, 1], port))).await;
    common::health::until(
        &mut c,
        "GET:setpoint\n",
        "GET:SETPOINT,0.000000\r\n",
        std::time::Duration::from_secs(10),
    )
    .await;
    server.shutdown().await;
}

/// Under systemd (`StateDirectory=`, as the shipped unit), clients' files
/// go to a folder of their own in the state directory, not beside the
/// configuration.
#[tokio::test]
async fn clients_files_default_to_a_folder_of_their_own_in_the_state_directory() {
    use common::process::{ChildGuard, PLCCOMS};
    let conf = tempfile::tempdir().unwrap();
    let state = tempfile::tempdir().unwrap();
    let port = free_port();
    std::fs::write(
        conf.path().join("PLCComS.ini"),
        format!("[*]\n[PLC]\nSERVER_PORT = {port}\nSIMULATOR = Yes\nIPADDR_LOCAL = 127.0.0.1\n"),
    )
    .unwrap();
    let _server = ChildGuard::spawn(
        "plccoms",
        std::process::Command::new(PLCCOMS)
            .arg("-c")
            .arg(conf.path().join("PLCComS.ini"))
            .current_dir(conf.path())
            .env("STATE_DIRECTORY", state.path())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null()),
    );
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], port));
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while tokio::net::TcpStream::connect(addr).await.is_err() {
        assert!(
            std::time::Instant::now() < deadline,
            "the server never listened"
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    let mut c = Client::connect(addr).await;
    assert_eq!(
        c.writefile("./note.txt", b"hello").await,
        "WRITEFILE:./note.txt OK\r\n"
    );
    assert_eq!(
        std::fs::read(state.path().join("files/note.txt")).unwrap(),
        b"hello"
    );
    assert!(!conf.path().join("note.txt").exists());
    c.ask(
        "GETFILE:./PLCComS.ini\n",
        "ERROR:41 Unable to get file: './PLCComS.ini'\r\n",
    )
    .await;
}
