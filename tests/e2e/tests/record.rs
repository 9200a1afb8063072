//! record_playback_plugin, recording (imd): AimRT's example config, files read back with
//! the `mcap` crate's reader; rotation by size and count; each compression mode; a process
//! killed mid-recording; the configs it refuses.

use std::path::{Path, PathBuf};
use std::time::Duration;

use aimrt_e2e::{aimrt_example, assert_failure, run_main, run_main_in, Running};

const LIMIT: Duration = Duration::from_secs(60);

/// AimRT's record_imd example (100 messages a second), every message kept (no
/// sample_freq), no extra file.
fn example() -> String {
    aimrt_example(
        "record_playback_plugin_record_imd",
        "examples_plugins_record_playback_plugin_record_imd_cfg.yaml",
    )
    .replace("                    sample_freq: 10  #hz\n", "")
    .replace(
        "                extra_file_path:\n                  - /var/coredumps\n",
        "",
    )
}

/// The one bag folder under `dir/bag`.
fn bag(dir: &Path) -> PathBuf {
    let folders: Vec<PathBuf> = std::fs::read_dir(dir.join("bag"))
        .expect("bag/")
        .map(|e| e.expect("entry").path())
        .collect();
    assert_eq!(folders.len(), 1, "{folders:?}");
    folders[0].clone()
}

fn mcaps(folder: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)
        .expect("the bag folder")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
        .collect();
    files.sort();
    files
}

/// `(sequence, data)` of recorded messages.
type Recorded = Vec<(u32, Vec<u8>)>;

/// `(sequence, data)` of every message of `test_topic` in `file`, checking its channel and
/// schema.
fn messages(file: &Path) -> Recorded {
    let bytes = std::fs::read(file).expect("read the mcap file");
    mcap::MessageStream::new(&bytes)
        .expect("an mcap file")
        .map(|m| {
            let m = m.expect("a readable message");
            assert_eq!(m.channel.topic, "test_topic");
            assert_eq!(m.channel.message_encoding, "protobuf");
            let schema = m.channel.schema.as_ref().expect("a schema");
            assert_eq!(schema.name, "aimrt.protocols.example.ExampleEventMsg");
            assert_eq!(schema.encoding, "protobuf");
            assert!(m.log_time > 0 && m.publish_time > 0);
            (m.sequence, m.data.to_vec())
        })
        .collect()
}

fn published(stdout: &str) -> u32 {
    stdout
        .lines()
        .filter(|l| l.contains("Publish new pb event"))
        .count() as u32
}

#[test]
fn aimrts_example_records_every_message_once_in_order_with_its_schema() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = run_main_in(
        dir.path(),
        Some(&example()),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    let folder = bag(dir.path());
    let name = folder.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        name.starts_with("aimrtbag_") && name.len() == "aimrtbag_20250101_120000".len(),
        "{name}"
    );
    let files = mcaps(&folder);
    assert_eq!(files.len(), 1, "{files:?}");
    let got = messages(&files[0]);
    let n = published(&out.stdout);
    assert!(n >= 100, "{n} published");
    assert_eq!(got.len() as u32, n, "every published message, once");
    for (i, (seq, data)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u32 + 1, "in order");
        let text = format!("count: {}", i + 1);
        assert!(
            data.windows(text.len()).any(|w| w == text.as_bytes()),
            "message {i} is ExampleEventMsg{{{text}}}"
        );
    }
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).expect("metadata.yaml");
    for needle in [
        "aimrt_bagfile_information:",
        "version: 1",
        "platform: arm64",
        "topic_name: test_topic",
        "msg_type: pb:aimrt.protocols.example.ExampleEventMsg",
        "serialization_type: pb",
        &format!("path: {}", files[0].file_name().unwrap().to_string_lossy()),
        "start_timestamp: ",
    ] {
        assert!(meta.contains(needle), "{needle} not in\n{meta}");
    }
    assert!(
        out.stdout.contains(&format!("{n} messages written to"))
            && out.stdout.contains("0 dropped"),
        "{}",
        out.stdout
    );
}

#[test]
fn files_rotate_by_size_and_the_oldest_go_beyond_the_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = example()
        .replace("max_bag_size_m: 2048", "max_bag_size_m: 1")
        .replace("max_bag_num: 10", "max_bag_num: 3")
        .replace("compression_mode: zstd", "compression_mode: none")
        .replace("channel_frq: 100", "channel_frq: 100\n  msg_size: 100000");
    let out = run_main_in(
        dir.path(),
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    let folder = bag(dir.path());
    let files = mcaps(&folder);
    assert_eq!(files.len(), 3, "{files:?}");
    let opened = out.stdout.matches("Open new mcap file to record").count();
    assert!(
        opened >= 5,
        "{opened} files opened for ~200 messages of 100 KB"
    );
    // In recording order (names made in the same second differ by a suffix).
    let mut kept: Vec<(PathBuf, Recorded)> =
        files.iter().map(|f| (f.clone(), messages(f))).collect();
    kept.sort_by_key(|(_, m)| m.first().map_or(0, |x| x.0));
    let mut last_seq = 0;
    for (f, got) in &kept {
        let size = std::fs::metadata(f).unwrap().len();
        assert!(size < 2 << 20, "{}: {size} bytes", f.display());
        assert!(!got.is_empty(), "{}", f.display());
        // The kept files are the newest, in order, without gaps between them; each starts
        // with the last message of the one before (the example's cache_last_msg: true).
        if last_seq > 0 {
            assert_eq!(
                got[0].0,
                last_seq,
                "{}: the cached last message",
                f.display()
            );
            assert_eq!(
                got.get(1).map(|m| m.0),
                Some(last_seq + 1),
                "{}",
                f.display()
            );
        }
        last_seq = got.last().unwrap().0;
    }
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).unwrap();
    assert_eq!(meta.matches("start_timestamp").count(), 3, "{meta}");
}

#[test]
fn each_compression_mode_writes_chunks_of_its_kind() {
    for (mode, want) in [("none", ""), ("lz4", "lz4"), ("zstd", "zstd")] {
        let dir = tempfile::tempdir().expect("tempdir");
        let cfg = example()
            .replace(
                "compression_mode: zstd",
                &format!("compression_mode: {mode}"),
            )
            .replace("channel_frq: 100", "channel_frq: 100\n  msg_size: 4000");
        let out = run_main_in(
            dir.path(),
            Some(&cfg),
            &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
            LIMIT,
        );
        assert_eq!(out.code, Some(0), "{}", out.stdout);
        let file = &mcaps(&bag(dir.path()))[0];
        let bytes = std::fs::read(file).unwrap();
        let summary = mcap::Summary::read(&bytes)
            .expect("a summary")
            .expect("present");
        assert!(!summary.chunk_indexes.is_empty(), "{mode}");
        for c in &summary.chunk_indexes {
            assert_eq!(c.compression, want, "{mode}");
        }
        assert_eq!(
            messages(file).len() as u32,
            published(&out.stdout),
            "{mode}"
        );
    }
}

#[test]
fn a_process_killed_mid_recording_leaves_a_readable_file() {
    let cfg = example()
        .replace("msg_write_interval: 1000 ", "msg_write_interval: 10 ")
        .replace(
            "msg_write_interval_time: 1000",
            "msg_write_interval_time: 100",
        );
    let mut p = Running::start(&cfg);
    p.wait_for("loop count : 120 ", LIMIT);
    p.signal("KILL");
    let _ = p.wait_exit(LIMIT);
    let file = &mcaps(&bag(p.dir()))[0];
    let bytes = std::fs::read(file).unwrap();
    // No summary or footer: read message by message until the cut.
    let mut seqs = Vec::new();
    for m in mcap::MessageStream::new(&bytes).expect("an mcap header") {
        match m {
            Ok(m) => seqs.push(m.sequence),
            Err(_) => break,
        }
    }
    // At most one write interval (10 messages, or 100 ms = 10 messages) is lost.
    assert!(seqs.len() >= 105, "{} messages readable of 120", seqs.len());
    for (i, s) in seqs.iter().enumerate() {
        assert_eq!(*s, i as u32 + 1);
    }
}

#[test]
fn configs_it_cannot_honour_are_refused_with_what_would_be_right() {
    let cases = [
        (
            example().replace("mode: imd # imd/signal", "mode: signal"),
            vec!["record_actions[0] ('my_imd_record')", "mode signal is not built yet"],
        ),
        (
            example().replace("mode: imd # imd/signal", "mode: live"),
            vec!["mode 'live' is not imd or signal"],
        ),
        (
            example().replace(
                "msg_type: pb:aimrt.protocols.example.ExampleEventMsg",
                "msg_type: pb:aimrt.protocols.example.Nope",
            ),
            vec!["topic_meta_list[0]: msg_type 'pb:aimrt.protocols.example.Nope' is in no type support pkg"],
        ),
        (
            example().replace("serialization_type: pb # optional", "serialization_type: ros2"),
            vec!["serialization_type 'ros2' is not a format of"],
        ),
        (
            example().replace("compression_mode: zstd", "compression_mode: gzip"),
            vec!["compression_mode 'gzip' is not none, lz4 or zstd"],
        ),
        (
            example().replace("          timer_executor: storage_executor  # require time schedule!\n", ""),
            vec!["timer_executor is required"],
        ),
        (
            example().replace("executor: record_thread # require thread safe!", "executor: no_such"),
            vec!["'no_such' is not an executor"],
        ),
        (
            // A pool of two runs tasks at once: writes would interleave.
            example().replace("executor: record_thread # require thread safe!", "executor: storage_executor"),
            vec!["Record executor storage_executor is not thread safe!", "asio_thread with thread_num 1"],
        ),
        (
            example().replace("          record_actions:", "          playback_actions:\n            - name: p\n              options: {}\n          record_actions:"),
            vec!["playback is not built yet"],
        ),
    ];
    for (cfg, expected) in &cases {
        let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        assert_failure(&out, expected);
    }
}

/// Whether `python3` can import the `mcap` package (`.ci/run` installs it and sets
/// `AIMRT_REQUIRE_PY_MCAP=1`, so there the check always runs).
fn python_mcap() -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import mcap.reader"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok && std::env::var_os("AIMRT_REQUIRE_PY_MCAP").is_some() {
        panic!("AIMRT_REQUIRE_PY_MCAP is set, but python3 cannot import mcap (pip install mcap)");
    }
    ok
}

#[test]
fn an_independent_reader_the_mcap_python_package_reads_the_file_the_same() {
    if !python_mcap() {
        eprintln!("skipped: python3 cannot import mcap (pip install mcap); CI runs this check");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let out = run_main_in(
        dir.path(),
        Some(&example()),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    let file = &mcaps(&bag(dir.path()))[0];
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/read_mcap.py");
    let py = std::process::Command::new("python3")
        .args([script, &file.display().to_string()])
        .output()
        .expect("run python3");
    assert!(
        py.status.success(),
        "{}",
        String::from_utf8_lossy(&py.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&py.stdout).expect("the script's JSON line");
    assert_eq!(v["profile"], "aimrtbag");
    assert_eq!(v["channels"][0]["topic"], "test_topic");
    assert_eq!(v["channels"][0]["message_encoding"], "protobuf");
    assert_eq!(
        v["channels"][0]["schema_name"],
        "aimrt.protocols.example.ExampleEventMsg"
    );
    assert_eq!(v["channels"][0]["schema_encoding"], "protobuf");
    let theirs: Vec<u64> = v["sequences"]
        .as_array()
        .expect("sequences")
        .iter()
        .filter_map(serde_json::Value::as_u64)
        .collect();
    let ours: Vec<u64> = messages(file).iter().map(|(s, _)| u64::from(*s)).collect();
    assert!(ours.len() >= 50, "{} messages", ours.len());
    assert_eq!(
        theirs, ours,
        "both readers see the same messages in the same order"
    );
}
