//! The EPSNET backend against the simulated PLC, over real UDP on 127.0.0.1.

use std::net::SocketAddr;
use std::time::Duration;

use plccoms_core::driver::{
    FileInfo, PlcBackend, PlcError, ReadRequest, Refusal, WriteData, WriteRequest,
    FILE_ATTRIBUTE_DIRECTORY, FILE_ATTRIBUTE_READONLY,
};
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::time::ttida_from_unix;
use plccoms_protocol::Area;
use plcsim::program::ProgramKind;
use plcsim::{SimConfig, SimHandle};

async fn sim_with(config: SimConfig) -> SimHandle {
    plcsim::spawn(SimConfig {
        bind: "127.0.0.1:0".parse().unwrap(),
        program: ProgramKind::Idle,
        ..config
    })
    .await
    .unwrap()
}

fn backend(plc: SocketAddr, timeout_ms: u64, step_ms: u64, retries: u32) -> EpsnetBackend {
    let mut config = EpsnetConfig::new(plc);
    config.local_ip = "127.0.0.1".parse().unwrap();
    config.timeout = Duration::from_millis(timeout_ms);
    config.timeout_step = Duration::from_millis(step_ms);
    config.retries = retries;
    EpsnetBackend::new(config)
}

fn pattern(len: usize, seed: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
        .collect()
}

fn read(area: Area, offset: u32, len: u32) -> ReadRequest {
    ReadRequest { area, offset, len }
}

#[tokio::test]
async fn connect_status_and_halt() {
    let sim = sim_with(SimConfig::default()).await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    assert_eq!(plc.max_read_block(Area::R), 1230);
    assert_eq!(plc.max_file_block(), 1150);
    let ident = plc.connect().await.unwrap();
    assert_eq!(ident, plcsim::device::DEFAULT_IDENT);
    assert!(plc.status().await.unwrap().run);
    sim.halt();
    assert!(!plc.status().await.unwrap().run);
    let s2 = plc.read(&[read(Area::S, 2, 1)]).await.unwrap();
    assert_eq!(s2[0].as_ref().unwrap()[0] & 0x04, 0, "__PLC_RUN cleared");
    sim.run();
    assert!(plc.status().await.unwrap().run);
}

#[tokio::test]
async fn reads_across_the_1230_split_and_batches() {
    let sim = sim_with(SimConfig::default()).await;
    let big = pattern(5000, 7);
    sim.device()
        .lock()
        .unwrap()
        .write(Area::R, 1000, &WriteData::Bytes(big.clone()))
        .unwrap();
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    let answers = plc
        .read(&[
            read(Area::R, 1000, 5000),
            read(Area::R, 1000, 1230),
            read(Area::R, 2229, 2),
            read(Area::R, 512 * 1024 - 2, 4),
            read(Area::R, 1001, 0),
        ])
        .await
        .unwrap();
    assert_eq!(answers[0].as_ref().unwrap(), &big);
    assert_eq!(answers[1].as_ref().unwrap(), &big[..1230]);
    assert_eq!(answers[2].as_ref().unwrap(), &big[1229..1231]);
    assert_eq!(answers[3], Err(Refusal::BAD_PARAMETERS));
    assert_eq!(answers[4].as_ref().unwrap(), &Vec::<u8>::new());

    // Many small reads: packed, answered in order.
    let requests: Vec<_> = (0..300).map(|i| read(Area::R, 1000 + i * 7, 3)).collect();
    let answers = plc.read(&requests).await.unwrap();
    for (i, answer) in answers.iter().enumerate() {
        let at = i * 7;
        assert_eq!(answer.as_ref().unwrap(), &big[at..at + 3], "read {i}");
    }
}

#[tokio::test]
async fn writes_and_bits_sharing_a_byte() {
    let sim = sim_with(SimConfig::default()).await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    let data = pattern(3000, 3);
    let answers = plc
        .write(&[
            WriteRequest {
                area: Area::R,
                offset: 10_000,
                data: WriteData::Bytes(data.clone()),
            },
            WriteRequest {
                area: Area::R,
                offset: 240,
                data: WriteData::Bit {
                    bit: 0,
                    value: true,
                },
            },
            WriteRequest {
                area: Area::R,
                offset: 240,
                data: WriteData::Bit {
                    bit: 1,
                    value: true,
                },
            },
            WriteRequest {
                area: Area::R,
                offset: 512 * 1024,
                data: WriteData::Bytes(vec![1]),
            },
            WriteRequest {
                area: Area::R,
                offset: 0,
                data: WriteData::Bit {
                    bit: 8,
                    value: true,
                },
            },
        ])
        .await
        .unwrap();
    assert_eq!(answers[..3], [Ok(()), Ok(()), Ok(())]);
    assert_eq!(answers[3], Err(Refusal::BAD_PARAMETERS));
    assert_eq!(answers[4], Err(Refusal::BAD_PARAMETERS));
    let back = plc
        .read(&[read(Area::R, 10_000, 3000), read(Area::R, 240, 1)])
        .await
        .unwrap();
    assert_eq!(back[0].as_ref().unwrap(), &data);
    assert_eq!(back[1].as_ref().unwrap(), &[0x03], "both BOOLs stuck");
    // Two separate batches, back to back, one bit each.
    for (bit, value) in [(0, false), (1, true)] {
        plc.write(&[WriteRequest {
            area: Area::R,
            offset: 240,
            data: WriteData::Bit { bit, value },
        }])
        .await
        .unwrap();
    }
    let back = plc.read(&[read(Area::R, 240, 1)]).await.unwrap();
    assert_eq!(back[0].as_ref().unwrap(), &[0x02]);
}

#[tokio::test]
async fn files_read_info_write_list() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("logs")).unwrap();
    std::fs::write(dir.path().join("logs/a.csv"), b"1;2;3\n").unwrap();
    let sim = sim_with(SimConfig {
        files: Some(dir.path().to_path_buf()),
        ..SimConfig::default()
    })
    .await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);

    // A block larger than the limit is refused (the link splits uploads).
    let content = pattern(4000, 9);
    assert_eq!(
        plc.write_file(b"/logs/big.bin", 0, &content[..1151], true)
            .await
            .unwrap(),
        Err(Refusal::BAD_PARAMETERS)
    );
    assert!(plc.file_info(b"/logs/big.bin").await.unwrap().is_err());

    // Write a file of 4 blocks.
    let mut at = 0;
    for (i, block) in [
        &content[..1000],
        &content[1000..2150],
        &content[2150..3300],
        &content[3300..],
    ]
    .iter()
    .enumerate()
    {
        let last = i == 3;
        assert_eq!(
            plc.write_file(b"/logs/new.bin", at, block, last)
                .await
                .unwrap(),
            Ok(())
        );
        if !last {
            assert!(plc.file_info(b"/logs/new.bin").await.unwrap().is_err());
        }
        at += block.len() as u64;
    }
    let info = plc.file_info(b"logs/new.bin").await.unwrap().unwrap();
    assert_eq!(info.size, 4000);
    assert_eq!(info.attributes & FILE_ATTRIBUTE_DIRECTORY, 0);

    let mut back = Vec::new();
    loop {
        let block = plc
            .read_file(b"logs/new.bin", back.len() as u64, 1150)
            .await
            .unwrap()
            .unwrap();
        if block.is_empty() {
            break;
        }
        back.extend(block);
    }
    assert_eq!(back, content);

    let list = plc.list_dir(b"/logs/").await.unwrap().unwrap();
    let names: Vec<&[u8]> = list.iter().map(|e| e.name.as_slice()).collect();
    assert_eq!(names, [&b"a.csv"[..], b"new.bin"]);
    let root = plc.list_dir(b"/").await.unwrap().unwrap();
    assert_eq!(root.len(), 1);
    assert_ne!(root[0].info.attributes & FILE_ATTRIBUTE_DIRECTORY, 0);

    let when = ttida_from_unix(1_700_000_000);
    let set = FileInfo {
        size: 0,
        attributes: FILE_ATTRIBUTE_READONLY,
        created: 0,
        modified: when,
    };
    assert_eq!(
        plc.write_file_info(b"logs/a.csv", &set).await.unwrap(),
        Ok(())
    );
    let info = plc.file_info(b"logs/a.csv").await.unwrap().unwrap();
    assert_eq!(info.modified, when);
    assert_ne!(info.attributes & FILE_ATTRIBUTE_READONLY, 0);

    // Escapes and missing files are refused by the PLC.
    assert_eq!(
        plc.read_file(b"../etc/passwd", 0, 100).await.unwrap(),
        Err(Refusal::BAD_PARAMETERS)
    );
    assert_eq!(
        plc.file_info(b"nope.txt").await.unwrap(),
        Err(Refusal::BAD_PARAMETERS)
    );
}

#[tokio::test]
async fn many_files_list_in_pages() {
    let dir = tempfile::tempdir().unwrap();
    for i in 0..120 {
        std::fs::write(
            dir.path()
                .join(format!("file_with_a_longish_name_{i:03}.txt")),
            b"x",
        )
        .unwrap();
    }
    let sim = sim_with(SimConfig {
        files: Some(dir.path().to_path_buf()),
        ..SimConfig::default()
    })
    .await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    let list = plc.list_dir(b"").await.unwrap().unwrap();
    assert_eq!(list.len(), 120);
    assert_eq!(list[119].name, b"file_with_a_longish_name_119.txt");
}

#[tokio::test]
async fn no_file_store_is_not_activated() {
    let sim = sim_with(SimConfig::default()).await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    assert_eq!(
        plc.file_info(b"x").await.unwrap(),
        Err(Refusal::NOT_ACTIVATED)
    );
}

#[tokio::test]
async fn correct_answers_under_20_percent_loss() {
    let sim = sim_with(SimConfig {
        loss: 0.2,
        seed: Some(42),
        ..SimConfig::default()
    })
    .await;
    let data = pattern(20_000, 1);
    sim.device()
        .lock()
        .unwrap()
        .write(Area::R, 0, &WriteData::Bytes(data.clone()))
        .unwrap();
    let mut plc = backend(sim.local_addr(), 40, 10, 10);
    for round in 0..40u32 {
        let offset = (round * 397) % 15_000;
        let len = 1 + (round * 131) % 4000;
        let answers = plc
            .read(&[read(Area::R, offset, len), read(Area::R, offset + 1, 2)])
            .await
            .unwrap();
        let (o, l) = (offset as usize, len as usize);
        assert_eq!(answers[0].as_ref().unwrap(), &data[o..o + l]);
        assert_eq!(answers[1].as_ref().unwrap(), &data[o + 1..o + 3]);
    }
    for round in 0..20u8 {
        plc.write(&[WriteRequest {
            area: Area::R,
            offset: 30_000,
            data: WriteData::Bytes(vec![round; 10]),
        }])
        .await
        .unwrap()[0]
            .unwrap();
        let back = plc.read(&[read(Area::R, 30_000, 10)]).await.unwrap();
        assert_eq!(back[0].as_ref().unwrap(), &vec![round; 10]);
    }
}

#[tokio::test]
async fn late_answers_are_never_mismatched() {
    // Answers arrive after the first timeout: the retry's MESI differs, the
    // late answer to the first attempt still belongs to the same datagram,
    // and leftovers never answer a later request.
    let sim = sim_with(SimConfig {
        latency: Duration::from_millis(120),
        ..SimConfig::default()
    })
    .await;
    for i in 0..20u8 {
        sim.device()
            .lock()
            .unwrap()
            .write(Area::R, u32::from(i) * 4, &WriteData::Bytes(vec![i; 4]))
            .unwrap();
    }
    let mut plc = backend(sim.local_addr(), 50, 50, 5);
    for i in 0..20u8 {
        let answers = plc
            .read(&[read(Area::R, u32::from(i) * 4, 4)])
            .await
            .unwrap();
        assert_eq!(answers[0].as_ref().unwrap(), &vec![i; 4]);
    }
}

#[tokio::test]
async fn foreign_datagrams_are_ignored() {
    let sim = sim_with(SimConfig {
        latency: Duration::from_millis(50),
        ..SimConfig::default()
    })
    .await;
    let mut plc = backend(sim.local_addr(), 500, 100, 2);
    plc.connect().await.unwrap();
    let target = plc.local_addr().unwrap();
    let rogue = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let spam = tokio::spawn(async move {
        for i in 0..100u16 {
            // A plausible answer from the wrong address, and garbage.
            let mut bytes = vec![(i >> 8) as u8, i as u8, 2, 0, 0, 1, 0xE5, 0];
            let _ = rogue.send_to(&bytes, target).await;
            bytes.truncate(3);
            let _ = rogue.send_to(&bytes, target).await;
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    });
    for _ in 0..5 {
        let ok = plc
            .write(&[WriteRequest {
                area: Area::R,
                offset: 0,
                data: WriteData::Bytes(vec![5]),
            }])
            .await
            .unwrap();
        assert_eq!(ok, [Ok(())]);
        let back = plc.read(&[read(Area::R, 0, 1)]).await.unwrap();
        assert_eq!(back[0].as_ref().unwrap(), &[5]);
    }
    spam.await.unwrap();
}

#[tokio::test]
async fn recovers_when_the_plc_restarts_on_the_same_port() {
    let sim = sim_with(SimConfig::default()).await;
    let addr = sim.local_addr();
    let mut plc = backend(addr, 50, 20, 1);
    plc.connect().await.unwrap();
    sim.stop().await;
    match plc.status().await {
        Err(PlcError::Timeout(_)) => {}
        other => panic!("expected a timeout, got {other:?}"),
    }
    let mut restarted = None;
    for _ in 0..50 {
        match plcsim::spawn(SimConfig {
            bind: addr,
            program: ProgramKind::Idle,
            ..SimConfig::default()
        })
        .await
        {
            Ok(handle) => {
                restarted = Some(handle);
                break;
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
    let _sim = restarted.expect("port free again");
    assert!(plc.status().await.unwrap().run);
    assert!(plc.connect().await.is_ok());
}
