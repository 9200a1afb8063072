//! record_playback_plugin: recording in imd mode (AimRT's example config, files read back
//! with the `mcap` crate's reader; rotation by size and count; each compression mode; a
//! process killed mid-recording), playback (the recorded gaps kept, at a rate factor, as
//! fast as possible, a window of the bag), signal mode and the control service over HTTP,
//! and the configs it refuses.

use std::path::{Path, PathBuf};
use std::time::Duration;

use aimrt_e2e::{aimrt_example, assert_failure, http, run_main, run_main_in, with_port, Running};

const LIMIT: Duration = Duration::from_secs(60);

/// AimRT's record_imd example (100 messages a second), every message kept (no
/// sample_freq), no extra file.
fn example() -> String {
    // One delivery thread: the recorder's deliveries run in publish order, so the tests
    // can check sequences one by one (AimRT's four threads may swap two close messages
    // under load; `aimrts_example_records_every_message_once_with_its_schema` runs them).
    let pool = "      - name: work_thread_pool\n        type: asio_thread\n        options:\n          thread_num: ";
    let aimrt = example_as_aimrt();
    assert!(aimrt.contains(&format!("{pool}4\n")), "{aimrt}");
    aimrt.replace(&format!("{pool}4\n"), &format!("{pool}1\n"))
}

/// AimRT's record example: its `work_thread_pool` of four threads delivers to the
/// recorder.
fn example_as_aimrt() -> String {
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
fn aimrts_example_records_every_message_once_with_its_schema() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = example_as_aimrt();
    assert!(cfg.contains("thread_num: 4"), "{cfg}");
    let out = run_recording(dir.path(), &cfg, 2);
    let folder = bag(dir.path());
    let name = folder.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        name.starts_with("aimrtbag_") && name.len() == "aimrtbag_20250101_120000".len(),
        "{name}"
    );
    let files = mcaps(&folder);
    assert_eq!(files.len(), 1, "{files:?}");
    let mut got = messages(&files[0]);
    let n = published(&out.stdout);
    assert!(n >= 100, "{n} published");
    assert_eq!(got.len() as u32, n, "every published message, once");
    // Four threads deliver to the recorder: two close messages may be written in the
    // order their deliveries ran (as in AimRT). Each is there once, with its own bytes.
    got.sort_by_key(|(seq, _)| *seq);
    for (i, (seq, data)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u32 + 1, "each sequence once");
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

/// A disk that fills up mid-recording (here the process's file size limit, `ulimit -f`,
/// with SIGXFSZ ignored: writes past it fail as on a full disk): the failure is said once
/// a file with the system's reason, the messages after it are counted as failed, the
/// action opens a new file 5 s later (the limit is per file, so it can write again), the
/// process runs on and stops cleanly, and each file keeps what was written before.
#[test]
fn a_file_that_cannot_be_written_is_reported_once_and_a_new_one_tried() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = example()
        .replace("compression_mode: zstd", "compression_mode: none")
        // A chunk of 10 messages at a time: what came before the failure is on disk.
        .replace("msg_write_interval: 1000 ", "msg_write_interval: 10 ")
        .replace("channel_frq: 100", "channel_frq: 100\n  msg_size: 1000");
    assert!(cfg.contains("msg_write_interval: 10 "));
    std::fs::write(dir.path().join("cfg.yaml"), cfg).expect("write cfg");
    let out = aimrt_e2e::run_main_after(
        dir.path(),
        // 64 KiB (512-byte blocks) or 128 KiB, as the shell counts: about a second.
        "ulimit -f 128 && trap '' XFSZ",
        &["--cfg_file_path=./cfg.yaml", "--running_duration=8"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    let failed_lines: Vec<&str> = out
        .stdout
        .lines()
        .filter(|l| l.contains("': writing ") && l.contains(".mcap failed: "))
        .collect();
    for line in &failed_lines {
        assert!(
            line.contains("File too large (os error 27)")
                && line.contains("counted as failed until the action opens a new file"),
            "{line}"
        );
    }
    let stats = out
        .stdout
        .lines()
        .find(|l| l.contains("messages written to"))
        .unwrap_or_else(|| panic!("{}", out.stdout));
    let count = |word: &str| -> u64 {
        let before = stats.split(word).next().unwrap_or("");
        before
            .rsplit(|c: char| !c.is_ascii_digit())
            .find(|w| !w.is_empty())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no count before '{word}': {stats}"))
    };
    let (written, failed) = (count(" messages written"), count(" failed"));
    assert!(written > 0 && failed > 50, "{stats}");
    let folder = bag(dir.path());
    let files = mcaps(&folder);
    // The first file failed in about a second; 5 s later a second one opened, and each
    // file fails once (the last one may not have reached the limit by shutdown).
    assert!(files.len() >= 2, "{files:?}\n{}", out.stdout);
    assert!(
        failed_lines.len() + 1 >= files.len() && failed_lines.len() <= files.len(),
        "{} failures for {} files",
        failed_lines.len(),
        files.len()
    );
    // What reached the disk reads back, in order, up to where each file was cut; a new
    // file begins with the message before its first (cache_last_msg), so each file's
    // sequences are contiguous, and later files hold later messages.
    let mut readable_in_all = 0;
    let mut last_seq = None;
    for f in &files {
        let bytes = std::fs::read(f).unwrap();
        let readable: Vec<u32> = mcap::MessageStream::new(&bytes)
            .expect("an mcap file")
            .map_while(Result::ok)
            .map(|m| m.sequence)
            .collect();
        assert!(!readable.is_empty(), "{}", f.display());
        assert!(
            readable.windows(2).all(|w| w[1] == w[0] + 1),
            "{readable:?}"
        );
        assert!(
            last_seq.is_none_or(|l| readable[0] > l),
            "{readable:?} after {last_seq:?}"
        );
        last_seq = readable.last().copied();
        readable_in_all += readable.len() as u64;
    }
    assert!(readable_in_all <= written + files.len() as u64, "{stats}");
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).unwrap();
    assert_eq!(
        meta.matches("start_timestamp").count(),
        files.len(),
        "{meta}"
    );
    assert!(!folder.join("metadata.yaml.tmp").exists());
}

/// A file that cannot take even its header (a full disk; here a file size limit of 0)
/// is removed at once: an imd action then cannot start, and says why.
#[test]
fn a_file_that_cannot_take_its_header_is_removed_and_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("cfg.yaml"), example()).expect("write cfg");
    let out = aimrt_e2e::run_main_after(
        dir.path(),
        "ulimit -f 0 && trap '' XFSZ",
        &["--cfg_file_path=./cfg.yaml", "--running_duration=2"],
        LIMIT,
    );
    assert_failure(
        &out,
        &[
            "record_actions[0] ('my_imd_record'): cannot start ",
            ".mcap: ",
            "File too large (os error 27)",
        ],
    );
    assert!(mcaps(&bag(dir.path())).is_empty());
}

#[test]
fn files_rotate_by_size_and_the_oldest_go_beyond_the_count() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = example()
        .replace("max_bag_size_m: 2048", "max_bag_size_m: 1")
        .replace("max_bag_num: 10", "max_bag_num: 3")
        .replace("compression_mode: zstd", "compression_mode: none")
        .replace("channel_frq: 100", "channel_frq: 100\n  msg_size: 100000");
    let out = run_recording(dir.path(), &cfg, 2);
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

/// The bag folder deleted while recording (a user clearing disk space): the next file
/// makes it again, with its metadata, and recording goes on.
#[test]
fn a_bag_folder_deleted_while_recording_is_made_again() {
    let cfg = example()
        .replace("max_bag_size_m: 2048", "max_bag_size_m: 1")
        .replace("compression_mode: zstd", "compression_mode: none")
        .replace("channel_frq: 100", "channel_frq: 100\n  msg_size: 100000");
    let mut rec = Running::start(&cfg);
    rec.wait_for("Open new mcap file to record", LIMIT);
    let folder = bag(rec.dir());
    // As `rm -rf` would be tried again: a file opened while the folder's entries were
    // removed leaves it not empty.
    let mut tries = 0;
    while let Err(e) = std::fs::remove_dir_all(&folder) {
        tries += 1;
        assert!(
            e.kind() == std::io::ErrorKind::DirectoryNotEmpty && tries < 100,
            "cannot remove {}: {e} (try {tries})",
            folder.display()
        );
    }
    rec.wait_for("Open new mcap file to record", LIMIT);
    rec.wait_for("Open new mcap file to record", LIMIT);
    assert_eq!(rec.interrupt(LIMIT), Some(0));
    let text = rec.text();
    assert!(!text.contains("cannot create"), "{text}");
    assert!(mcaps(&folder).len() >= 2, "{text}");
    // The metadata lists the files there are, so the folder plays back.
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).unwrap();
    let listed = meta.matches("start_timestamp").count();
    assert_eq!(listed, mcaps(&folder).len(), "{meta}");
    let (played, out) = play(&folder, "", 2);
    assert!(!played.is_empty(), "{out}");
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
        let out = run_recording(dir.path(), &cfg, 1);
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
fn a_type_support_package_of_abi_1_4_records_through_its_shorter_tables() {
    // Its tables end before `encode_to` (1.5): the recorder's messages, objects of those
    // tables, are encoded and copied, and the entry past the table is never reached.
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = example().replace("libexample_pb_ts.so", "libfixture_abi_1_4.so");
    assert!(cfg.contains("libfixture_abi_1_4.so"));
    let out = run_recording(dir.path(), &cfg, 1);
    assert!(
        !out.stdout.contains("encode_to reached"),
        "the host read past the 1.4 table: {}",
        out.stdout
    );
    let file = &mcaps(&bag(dir.path()))[0];
    let got = messages(file);
    assert_eq!(got.len() as u32, published(&out.stdout), "{}", out.stdout);
    let seqs: Vec<u32> = got.iter().map(|(seq, _)| *seq).collect();
    for (i, (seq, data)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u32 + 1, "sequences {seqs:?}\n{}", out.stdout);
        // ExampleEventMsg { msg: "count: n", num: n } in protobuf, byte for byte.
        let text = format!("count: {}", i + 1);
        let mut want = vec![0x0a, text.len() as u8];
        want.extend_from_slice(text.as_bytes());
        want.extend_from_slice(&[0x10, i as u8 + 1]);
        assert_eq!(data, &want, "message {i}");
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
            example().replace("          record_actions:", "          playback_actions:\n            - name: p\n              options: {bag_path: ./nowhere, mode: imd, executor: storage_executor}\n          record_actions:"),
            vec!["playback_actions[0] ('p'): bag_path: cannot read ./nowhere/metadata.yaml", "one bag folder"],
        ),
        (
            example().replace("          record_actions:", "          playback_actions:\n            - name: p\n              options: {bag_path: ./bag, mode: imd, executor: storage_executor, rate: 0}\n          record_actions:"),
            vec!["rate 0 must be a positive factor", "as_fast_as_possible: true"],
        ),
    ];
    for (cfg, expected) in &cases {
        let out = run_main(Some(cfg), &["--cfg_file_path=./cfg.yaml"], LIMIT);
        assert_failure(&out, expected);
    }
}

/// Whether `python3` can import the `mcap` package; when not, says the test is skipped
/// (`.ci/run` installs it and sets `AIMRT_REQUIRE_PY_MCAP=1`, so there the check always
/// runs).
fn python_mcap() -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import mcap.reader"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok && std::env::var_os("AIMRT_REQUIRE_PY_MCAP").is_some() {
        panic!("AIMRT_REQUIRE_PY_MCAP is set, but python3 cannot import mcap (pip install mcap)");
    }
    if !ok {
        eprintln!("skipped: python3 cannot import mcap (pip install mcap); CI runs this check");
    }
    ok
}

/// The standard output of `python3 scripts/<script> <args>`, which must succeed.
fn python(script: &str, args: &[&str]) -> Vec<u8> {
    let script = format!("{}/scripts/{script}", env!("CARGO_MANIFEST_DIR"));
    let py = std::process::Command::new("python3")
        .arg(&script)
        .args(args)
        .output()
        .expect("run python3");
    assert!(
        py.status.success(),
        "{script}: {}",
        String::from_utf8_lossy(&py.stderr)
    );
    py.stdout
}

#[test]
fn an_independent_reader_the_mcap_python_package_reads_the_file_the_same() {
    if !python_mcap() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    run_recording(dir.path(), &example(), 1);
    let file = &mcaps(&bag(dir.path()))[0];
    let out = python("read_mcap.py", &[&file.display().to_string()]);
    let v: serde_json::Value = serde_json::from_slice(&out).expect("the script's JSON line");
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
    // A second of a 100 Hz publisher: some messages even on a loaded machine.
    assert!(ours.len() >= 20, "{} messages", ours.len());
    assert_eq!(
        theirs, ours,
        "both readers see the same messages in the same order"
    );
}

/// `(log_time, data)` of every message in the bag folder's files, in file order.
fn timed(folder: &Path) -> Vec<(u64, Vec<u8>)> {
    let mut all = Vec::new();
    for f in mcaps(folder) {
        let bytes = std::fs::read(&f).expect("read the mcap file");
        for m in mcap::MessageStream::new(&bytes).expect("an mcap file") {
            let m = m.expect("a readable message");
            all.push((m.log_time, m.data.to_vec()));
        }
    }
    all
}

/// Runs `cfg` in `dir` for `secs` seconds; it must exit 0.
fn run_recording(dir: &Path, cfg: &str, secs: u32) -> aimrt_e2e::Output {
    let out = run_main_in(
        dir,
        Some(cfg),
        &[
            "--cfg_file_path=./cfg.yaml",
            &format!("--running_duration={secs}"),
        ],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    out
}

/// Records AimRT's example (every message) for `secs` seconds into `dir/bag`.
fn record_bag(dir: &Path, secs: u32) -> PathBuf {
    record_bag_cfg(dir, &example(), secs)
}

fn record_bag_cfg(dir: &Path, cfg: &str, secs: u32) -> PathBuf {
    run_recording(dir, cfg, secs);
    bag(dir)
}

/// AimRT's playback_imd example on `folder` from its start to its end, with `extra`
/// playback options, and a second record action that records what is played into
/// `./replay`.
fn playback_config(folder: &Path, extra: &str) -> String {
    aimrt_example(
        "record_playback_plugin_playback_imd",
        "examples_plugins_record_playback_plugin_playback_imd_cfg.yaml",
    )
    .replace(
        "bag_path: ./bag/aimrtbag_yyyymmdd_hhmmss",
        &format!("bag_path: {}", folder.display()),
    )
    .replace("skip_duration_s: 2  #", "skip_duration_s: 0  #")
    .replace(
        "play_duration_s: 10 # Effective only in imd mode",
        &format!("play_duration_s: 0\n{extra}"),
    )
    .replace(
        "          playback_actions:",
        "          timer_executor: storage_executor
          record_actions:
            - name: capture
              options:
                bag_path: ./replay
                mode: imd
                executor: record_thread
                storage_policy: {compression_mode: none}
                topic_meta_list:
                  - {topic_name: test_topic, msg_type: pb:aimrt.protocols.example.ExampleEventMsg}
          playback_actions:",
    )
    // Delivered on the publishing thread: what is recorded again keeps the played order.
    .replace(
        "subscriber_use_inline_executor: false",
        "subscriber_use_inline_executor: true",
    )
    .replace(
        "    executors:\n",
        "    executors:\n      - {name: record_thread, type: simple_thread}\n      - {name: storage_executor, type: asio_thread}\n",
    )
}

/// Plays `folder` with `extra` options for `secs` seconds; returns what was played, as
/// recorded again, and the output.
fn play(folder: &Path, extra: &str, secs: u32) -> (Vec<(u64, Vec<u8>)>, String) {
    play_config(&playback_config(folder, extra), secs)
}

/// Runs a [`playback_config`] for `secs` seconds.
fn play_config(cfg: &str, secs: u32) -> (Vec<(u64, Vec<u8>)>, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = run_recording(dir.path(), cfg, secs);
    let replay: Vec<PathBuf> = std::fs::read_dir(dir.path().join("replay"))
        .expect("replay/")
        .map(|e| e.expect("entry").path())
        .collect();
    assert_eq!(replay.len(), 1, "{replay:?}");
    (timed(&replay[0]), out.stdout)
}

/// Gap errors in ms: `|played gap - recorded gap / rate|`, sorted.
fn gap_errors(recorded: &[(u64, Vec<u8>)], played: &[(u64, Vec<u8>)], rate: f64) -> Vec<f64> {
    let gaps = |v: &[(u64, Vec<u8>)]| -> Vec<f64> {
        v.windows(2)
            .map(|w| (w[1].0 as f64 - w[0].0 as f64) / 1e6)
            .collect()
    };
    let mut errors: Vec<f64> = gaps(recorded)
        .iter()
        .zip(gaps(played))
        .map(|(r, p)| (p - r / rate).abs())
        .collect();
    errors.sort_by(f64::total_cmp);
    errors
}

fn same_messages(recorded: &[(u64, Vec<u8>)], played: &[(u64, Vec<u8>)], stdout: &str) {
    assert_eq!(
        played.len(),
        recorded.len(),
        "every recorded message is played: {stdout}"
    );
    for (i, (r, p)) in recorded.iter().zip(played).enumerate() {
        assert_eq!(r.1, p.1, "message {i}: the same bytes, in the same order");
    }
}

#[test]
fn playback_republishes_the_recording_with_its_gaps() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 2);
    let recorded = timed(&folder);
    // At least half the publisher's 100 Hz, as on a loaded machine.
    assert!(recorded.len() >= 100, "{} recorded", recorded.len());
    let (played, stdout) = play(&folder, "", 5);
    same_messages(&recorded, &played, &stdout);
    let errors = gap_errors(&recorded, &played, 1.0);
    let median = errors[errors.len() / 2];
    let max = errors[errors.len() - 1];
    assert!(median < 2.0, "median gap error {median:.3} ms");
    assert!(max < 50.0, "max gap error {max:.3} ms");
    assert!(stdout.contains("Stop playback"), "{stdout}");
}

#[test]
fn playback_at_rate_ten_and_as_fast_as_possible() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 2);
    let recorded = timed(&folder);
    let span = |v: &[(u64, Vec<u8>)]| (v[v.len() - 1].0 - v[0].0) as f64 / 1e6;
    let (played, stdout) = play(&folder, "                rate: 10", 2);
    same_messages(&recorded, &played, &stdout);
    let errors = gap_errors(&recorded, &played, 10.0);
    let median = errors[errors.len() / 2];
    assert!(median < 2.0, "median gap error {median:.3} ms at rate 10");
    let (r, p) = (span(&recorded), span(&played));
    assert!(
        (p - r / 10.0).abs() < 50.0,
        "played in {p:.1} ms, recorded in {r:.1} ms"
    );
    let (played, stdout) = play(&folder, "                as_fast_as_possible: true", 2);
    same_messages(&recorded, &played, &stdout);
    let p = span(&played);
    assert!(
        p < r / 10.0,
        "as fast as possible took {p:.1} ms for {r:.1} ms"
    );
}

#[test]
fn playback_plays_the_window_skip_and_play_durations_select() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 4);
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).expect("metadata");
    let start: u64 = meta
        .lines()
        .find_map(|l| l.trim().strip_prefix("start_timestamp: "))
        .and_then(|v| v.trim().parse().ok())
        .expect("a start_timestamp");
    let recorded = timed(&folder);
    let window: Vec<(u64, Vec<u8>)> = recorded
        .iter()
        .filter(|(t, _)| *t >= start + 1_000_000_000 && *t <= start + 2_000_000_000)
        .cloned()
        .collect();
    // A 100 Hz publisher: at least half its rate on a loaded machine (a CI run once had
    // 79 there).
    assert!(
        window.len() >= 40,
        "{} messages in the second second",
        window.len()
    );
    let cfg = playback_config(&folder, "                rate: 4")
        .replace("skip_duration_s: 0  #", "skip_duration_s: 1  #")
        .replace("play_duration_s: 0\n", "play_duration_s: 1\n");
    let (played, stdout) = play_config(&cfg, 3);
    same_messages(&window, &played, &stdout);
}

#[test]
fn a_damaged_bag_is_played_up_to_the_damage_and_a_missing_one_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    // A chunk every 10 messages: the cut falls among them.
    let cfg = example().replace("msg_write_interval: 1000 ", "msg_write_interval: 10 ");
    let folder = record_bag_cfg(dir.path(), &cfg, 1);
    let recorded = timed(&folder);
    // Cut the file inside its middle chunk: what is before the cut is played, with a
    // warning. (Half the file's length can fall in the summary when few messages were
    // recorded, and then nothing is lost.)
    let file = &mcaps(&folder)[0];
    let bytes = std::fs::read(file).unwrap();
    let chunks = mcap::Summary::read(&bytes)
        .expect("a summary")
        .expect("present")
        .chunk_indexes;
    assert!(chunks.len() >= 2, "{} chunks", chunks.len());
    let middle = &chunks[chunks.len() / 2];
    // A byte of the first chunk's records damaged: that chunk is passed over with a
    // warning, and every message of the other chunks is played, in order (the channel,
    // defined in that chunk, is read again from the summary).
    let first = &chunks[0];
    let mut damaged = bytes.clone();
    // Opcode, length, start, end, size, CRC, "zstd", size compressed; then the records.
    let records = first.chunk_start_offset as usize + 9 + 28 + 4 + 4 + 8;
    assert_eq!(&bytes[records - 12..records - 8], b"zstd");
    // In the middle of the compressed records (a byte of zstd's frame header, such as
    // its window size, may change nothing).
    let compressed = u64::from_le_bytes(bytes[records - 8..records].try_into().unwrap());
    damaged[records + compressed as usize / 2] ^= 0xff;
    std::fs::write(file, &damaged).unwrap();
    let (played, stdout) = play(&folder, "                as_fast_as_possible: true", 2);
    assert!(stdout.contains("has a damaged chunk"), "{stdout}");
    let kept: Vec<(u64, Vec<u8>)> = recorded
        .iter()
        .filter(|(t, _)| *t < first.message_start_time || *t > first.message_end_time)
        .cloned()
        .collect();
    assert!(kept.len() < recorded.len() && !kept.is_empty());
    same_messages(&kept, &played, &stdout);
    // The file cut inside its middle chunk.
    let cut = middle.chunk_start_offset + middle.chunk_length / 2;
    std::fs::write(file, &bytes[..cut as usize]).unwrap();
    let (played, stdout) = play(&folder, "                as_fast_as_possible: true", 2);
    assert!(
        stdout.contains("is read up to a damaged or cut record"),
        "{stdout}"
    );
    assert!(played.len() < recorded.len());
    same_messages(&recorded[..played.len()], &played, &stdout);
    // No file left: refused at start with what is wrong.
    std::fs::remove_file(file).unwrap();
    let out = run_main(
        Some(&playback_config(&folder, "")),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    assert_failure(&out, &["none of the files metadata.yaml lists is in"]);
    // The recording's bag_path given instead of one of its bags: the bags are named.
    let out = run_main(
        Some(&playback_config(folder.parent().unwrap(), "")),
        &["--cfg_file_path=./cfg.yaml"],
        LIMIT,
    );
    assert_failure(
        &out,
        &[
            "bag_path must be one bag folder",
            &format!(
                "the bag folders there, the newest last: {}",
                folder.display()
            ),
        ],
    );
}

/// A window past the bag's end plays nothing and says why, with when the messages were
/// logged.
#[test]
fn a_window_past_the_bags_end_says_why_nothing_played() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 1);
    let cfg = playback_config(&folder, "                as_fast_as_possible: true")
        .replace("skip_duration_s: 0  #", "skip_duration_s: 100  #");
    let (played, stdout) = play_config(&cfg, 2);
    assert!(played.is_empty());
    assert!(
        stdout.contains("nothing played: none of the ")
            && stdout
                .contains("was logged in the window (100.0 s to the end after the bag's start)"),
        "{stdout}"
    );
}

/// A bag whose `metadata.yaml` lists `test_topic` under two types: playing every topic is
/// refused (which type would it be?); a `topic_meta_list` that picks one plays it, and an
/// entry of that list that is not in the bag is warned about, naming the bag's topics.
#[test]
fn a_topic_recorded_with_two_types_is_played_only_when_the_list_picks_one() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 1);
    let recorded = timed(&folder);
    assert!(!recorded.is_empty());
    let meta = folder.join("metadata.yaml");
    let text = std::fs::read_to_string(&meta).expect("metadata.yaml");
    let second = "  - id: 1
    topic_name: test_topic
    msg_type: pb:aimrt.protocols.example.GetFooDataReq
    serialization_type: pb
  files:
";
    assert!(text.contains("\n  files:\n"), "{text}");
    std::fs::write(&meta, text.replacen("  files:\n", second, 1)).expect("metadata.yaml");
    let listed = "                topic_meta_list:
                  - topic_name: test_topic
                    msg_type: pb:aimrt.protocols.example.ExampleEventMsg
";
    let cfg = playback_config(&folder, "                as_fast_as_possible: true");
    assert!(cfg.contains(listed), "{cfg}");
    let every = cfg.replace(listed, "");
    let out = run_main(Some(&every), &["--cfg_file_path=./cfg.yaml"], LIMIT);
    assert_failure(
        &out,
        &["topic 'test_topic' is recorded with two types; list the one to play in topic_meta_list"],
    );
    let picked = cfg.replace(
        listed,
        &format!(
            "{listed}                  - topic_name: no_such_topic
                    msg_type: pb:aimrt.protocols.example.ExampleEventMsg
"
        ),
    );
    let (played, stdout) = play_config(&picked, 2);
    assert!(
        stdout.contains(
            "topic_meta_list[1] ('no_such_topic', 'pb:aimrt.protocols.example.ExampleEventMsg') is not in the bag; its topics: test_topic (pb:aimrt.protocols.example.ExampleEventMsg), test_topic (pb:aimrt.protocols.example.GetFooDataReq)"
        ),
        "{stdout}"
    );
    same_messages(&recorded, &played, &stdout);
}

/// Playback reads chunks itself (see docs/decisions.md): files that another writer, the
/// `mcap` Python package, compressed with zstd, with lz4 or not at all, in many small
/// chunks, play every message in order.
#[test]
fn playback_plays_chunks_another_writer_compressed() {
    if !python_mcap() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    // Two seconds of a 100 Hz publisher: 60 messages even on a loaded machine make
    // about 10 chunks.
    let folder = record_bag(dir.path(), 2);
    let recorded = timed(&folder);
    assert!(recorded.len() >= 60, "{} recorded", recorded.len());
    let file = &mcaps(&folder)[0];
    let ours = std::fs::read(file).expect("the recorded file");
    for compression in ["zstd", "lz4", "none"] {
        let src = dir.path().join("ours.mcap");
        std::fs::write(&src, &ours).expect("a copy");
        let (src, dst) = (src.display().to_string(), file.display().to_string());
        // Chunks of at most 512 bytes: about 6 messages each (1 024-byte chunks of a
        // second's recording once gave only 4).
        python("rewrite_mcap.py", &[&src, &dst, compression, "512"]);
        let theirs = std::fs::read(file).expect("the rewritten file");
        let chunks = mcap::Summary::read(&theirs)
            .expect("a summary")
            .expect("present")
            .chunk_indexes;
        assert!(chunks.len() >= 5, "{compression}: {} chunks", chunks.len());
        let expect = if compression == "none" {
            ""
        } else {
            compression
        };
        assert!(
            chunks.iter().all(|c| c.compression == expect),
            "{compression}"
        );
        let (played, stdout) = play(&folder, "                as_fast_as_possible: true", 2);
        assert!(!stdout.contains("damaged"), "{compression}: {stdout}");
        same_messages(&recorded, &played, &stdout);
    }
}

const SERVICE: &str = "/rpc/aimrt.protocols.record_playback_plugin.RecordPlaybackService";

/// Calls `method` with a JSON body; returns the answer, checked to be HTTP 200.
fn call(addr: &str, method: &str, body: &str) -> serde_json::Value {
    let (status, text) = http(
        addr,
        "POST",
        &format!("{SERVICE}/{method}"),
        &[("content-type", "application/json")],
        body.as_bytes(),
    );
    assert_eq!(status, 200, "{method}: {text}");
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{method}: {e}: {text}"))
}

/// `(code, msg)` of an answer's CommonRsp (at the top or under `common_rsp`).
fn code(v: &serde_json::Value) -> (u64, String) {
    let c = v
        .get("common_rsp")
        .or_else(|| v.get("commonRsp"))
        .unwrap_or(v);
    (
        c["code"]
            .as_u64()
            .unwrap_or_else(|| panic!("no code in {v}")),
        c["msg"].as_str().unwrap_or_default().to_owned(),
    )
}

fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
}

/// AimRT's record_signal example (every message), listening on a port of its own.
fn signal_example() -> String {
    with_port(
        &aimrt_example(
            "record_playback_plugin_record_signal",
            "examples_plugins_record_playback_plugin_record_signal_cfg.yaml",
        )
        .replace("                    sample_freq: 10   #hz\n", ""),
        0,
    )
}

#[test]
fn signal_mode_records_the_preparation_window_until_stopped_or_for_its_duration() {
    let mut p = Running::start(&signal_example());
    let addr = p.http_address(LIMIT);
    p.wait_for("loop count : 150 ", LIMIT);
    let action = r#""action_name":"my_signal_record""#;
    let before = now_ns();
    let v = call(
        &addr,
        "StartRecord",
        &format!(r#"{{{action},"preparation_duration_s":1,"record_duration_s":0}}"#),
    );
    let after = now_ns();
    assert_eq!(code(&v), (0, String::new()), "{v}");
    let folder = PathBuf::from(v["filefolder"].as_str().expect("filefolder"));
    assert!(
        folder.starts_with(p.dir().join("bag")) || folder.is_relative() || folder.exists(),
        "{v}"
    );
    let again = call(&addr, "StartRecord", &format!("{{{action}}}"));
    assert_eq!(code(&again).0, 3, "{again}");
    assert!(
        code(&again).1.starts_with("START_RECORD_FAILED: "),
        "{again}"
    );
    // record_duration_s 0 records until stopped (AimRT stops at the first message: #427).
    std::thread::sleep(Duration::from_millis(1500));
    let stop_at = now_ns();
    assert_eq!(
        code(&call(&addr, "StopRecord", &format!("{{{action}}}"))).0,
        0
    );
    p.wait_for("stop recording into", LIMIT);
    let twice = call(&addr, "StopRecord", &format!("{{{action}}}"));
    assert_eq!(
        code(&twice).0,
        5,
        "a second stop says it is not recording: {twice}"
    );
    let got = timed(&folder);
    // The kept window: from one second before the call (100 messages a second).
    let first = got[0].0;
    assert!(
        first + 1_000_000_000 >= before,
        "{} ms too early",
        (before - first - 1_000_000_000) / 1_000_000
    );
    assert!(
        first + 1_000_000_000 <= after + 30_000_000,
        "the window starts {} ms late",
        (first + 1_000_000_000 - after) / 1_000_000
    );
    let last = got[got.len() - 1].0;
    assert!(last <= stop_at + 100_000_000 && last + 100_000_000 >= stop_at);
    // At least half the publisher's 100 Hz, as on a loaded machine.
    assert!(got.len() >= 125, "{} messages in 2.5 s", got.len());
    // A timed recording ends by itself.
    let v = call(
        &addr,
        "StartRecord",
        &format!(r#"{{{action},"preparation_duration_s":0,"record_duration_s":1}}"#),
    );
    assert_eq!(code(&v).0, 0, "{v}");
    let timed_folder = PathBuf::from(v["filefolder"].as_str().expect("filefolder"));
    assert_ne!(timed_folder, folder);
    p.wait_for("stop recording into", LIMIT);
    let late = call(&addr, "StopRecord", &format!("{{{action}}}"));
    assert_eq!(code(&late).0, 5, "{late}");
    let got = timed(&timed_folder);
    let span = (got[got.len() - 1].0 - got[0].0) as f64 / 1e9;
    assert!(
        (0.9..=1.05).contains(&span),
        "{span} s recorded for record_duration_s 1"
    );
}

/// A signal action that was never started says so in its shutdown line, with the
/// messages its preparation window let go early.
#[test]
fn a_signal_action_never_started_says_it_made_no_bag_folder() {
    let mut p = Running::start(&signal_example());
    p.http_address(LIMIT);
    assert_eq!(p.interrupt(LIMIT), Some(0));
    let text = p.text();
    assert!(
        text.contains("record action 'my_signal_record': 0 messages written to no bag folder (StartRecord never came), 0 dropped (write queue full), 0 failed, ")
            && text.contains(" let go early from the preparation window (1073741824 bytes full)"),
        "{text}"
    );
}

#[test]
fn the_control_service_answers_every_method_truthfully() {
    let mut p = Running::start(&signal_example());
    let addr = p.http_address(LIMIT);
    let status = call(&addr, "GetRecordActionStatus", "{}");
    assert_eq!(code(&status).0, 0, "{status}");
    let list = status
        .get("record_action_status_list")
        .or_else(|| status.get("recordActionStatusList"))
        .expect("a list");
    assert_eq!(
        list[0]["action_name"]
            .as_str()
            .or(list[0]["actionName"].as_str()),
        Some("my_signal_record"),
        "{status}"
    );
    let unknown = call(&addr, "StartRecord", r#"{"action_name":"nope"}"#);
    assert_eq!(code(&unknown).0, 1);
    assert!(
        code(&unknown).1.contains("my_signal_record"),
        "names the actions: {unknown}"
    );
    assert_eq!(
        code(&call(&addr, "StartPlayback", r#"{"action_name":"nope"}"#)).0,
        1
    );
    // Switch the topic off and set a rate: the status says so.
    let topic =
        r#""topic_name":"test_topic","msg_type":"pb:aimrt.protocols.example.ExampleEventMsg""#;
    let v = call(
        &addr,
        "UpdateRecordAction",
        &format!(
            r#"{{"action_name":"my_signal_record","topic_metas":[{{{topic},"record_enabled":false,"sample_freq":5}}]}}"#
        ),
    );
    assert_eq!(code(&v).0, 0, "{v}");
    let status = call(
        &addr,
        "GetRecordActionStatus",
        r#"{"action_names":["my_signal_record"]}"#,
    );
    let text = status.to_string();
    assert!(
        text.contains(r#""record_enabled":false"#) || text.contains(r#""recordEnabled":false"#),
        "{text}"
    );
    assert!(text.contains("5"), "{text}");
    let v = call(
        &addr,
        "UpdateRecordAction",
        r#"{"action_name":"my_signal_record","topic_metas":[{"topic_name":"other","msg_type":"x"}]}"#,
    );
    assert_eq!(code(&v).0, 6, "{v}");
    assert!(code(&v).1.contains("does not record topic 'other'"), "{v}");
    // Metadata lands in metadata.yaml of the recording.
    let v = call(
        &addr,
        "StartRecord",
        r#"{"action_name":"my_signal_record"}"#,
    );
    let folder = PathBuf::from(v["filefolder"].as_str().expect("filefolder"));
    let v = call(
        &addr,
        "UpdateMetadata",
        r#"{"action_name":"my_signal_record","kv_pairs":{"robot":"r1","speeds":"[1, 2]"}}"#,
    );
    assert_eq!(code(&v).0, 0, "{v}");
    let meta = std::fs::read_to_string(folder.join("metadata.yaml")).expect("metadata");
    assert!(
        meta.contains("robot: r1") && meta.contains("platform: arm64"),
        "{meta}"
    );
    assert!(
        meta.contains("- 1") && meta.contains("- 2"),
        "a YAML value stays YAML: {meta}"
    );
    // The topic is off: nothing is recorded.
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(
        code(&call(
            &addr,
            "StopRecord",
            r#"{"action_name":"my_signal_record"}"#
        ))
        .0,
        0
    );
    assert!(timed(&folder).is_empty());
    // A malformed body is HTTP 400, not a crash.
    let (status, text) = http(
        &addr,
        "POST",
        &format!("{SERVICE}/StartRecord"),
        &[("content-type", "application/json")],
        b"{\"action_name\":",
    );
    assert_eq!(status, 400, "{text}");
    p.interrupt(LIMIT);
}

/// The messages the example's subscriber logged so far.
fn received(p: &Running) -> usize {
    p.text()
        .lines()
        .filter(|l| l.contains("Receive new pb event"))
        .count()
}

#[test]
fn signal_playback_starts_stops_and_plays_again_from_the_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let folder = record_bag(dir.path(), 1);
    let n = timed(&folder).len();
    let cfg = with_port(
        &aimrt_example(
            "record_playback_plugin_playback_signal",
            "examples_plugins_record_playback_plugin_playback_signal_cfg.yaml",
        )
        .replace(
            "bag_path: ./bag/aimrtbag_yyyymmdd_hhmmss",
            &format!("bag_path: {}", folder.display()),
        ),
        0,
    );
    let mut p = Running::start(&cfg);
    let addr = p.http_address(LIMIT);
    let action = r#""action_name":"my_signal_playback""#;
    for round in 1..=2 {
        let v = call(&addr, "StartPlayback", &format!("{{{action}}}"));
        assert_eq!(code(&v), (0, String::new()), "round {round}: {v}");
        let busy = call(&addr, "StartPlayback", &format!("{{{action}}}"));
        assert_eq!(code(&busy).0, 4, "{busy}");
        p.wait_for("Stop playback (", LIMIT);
        // Subscribers run on a pool: let the last deliveries be logged.
        p.collect_for(Duration::from_millis(500), "");
        let got = received(&p);
        assert_eq!(got, n * round, "round {round}: every message, each round");
    }
    // Stopped midway: fewer than all.
    assert_eq!(
        code(&call(&addr, "StartPlayback", &format!("{{{action}}}"))).0,
        0
    );
    p.collect_for(Duration::from_millis(200), "");
    assert_eq!(
        code(&call(&addr, "StopPlayback", &format!("{{{action}}}"))).0,
        0
    );
    assert_eq!(
        code(&call(&addr, "StopPlayback", &format!("{{{action}}}"))).0,
        4
    );
    p.collect_for(Duration::from_millis(500), "");
    let got = received(&p);
    assert!(got > 2 * n && got < 3 * n, "{got} of {}", 3 * n);
    p.interrupt(LIMIT);
}

#[test]
fn a_recorded_topic_nothing_publishes_is_a_warning_at_start() {
    let cfg = example().replace(
        "                  - topic_name: test_topic\n",
        "                  - topic_name: nobody_publishes_this\n",
    );
    assert!(cfg.contains("nobody_publishes_this"), "{cfg}");
    let out = run_main(
        Some(&cfg),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert_eq!(out.code, Some(0), "{}", out.stdout);
    let warning = out
        .stdout
        .lines()
        .find(|l| l.contains("Channel topic 'nobody_publishes_this'"))
        .unwrap_or_else(|| panic!("no warning:\n{}", out.stdout));
    assert!(
        warning.contains("[Warn]")
            && warning.contains("'record_playback_plugin' subscribes")
            && warning.contains("no module or plugin of this process publishes it"),
        "{warning}"
    );
    // The example's own topic, which a module publishes, draws no such line.
    let out = run_main(
        Some(&example()),
        &["--cfg_file_path=./cfg.yaml", "--running_duration=1"],
        LIMIT,
    );
    assert!(
        !out.stdout
            .contains("publishes it and only the local backend"),
        "{}",
        out.stdout
    );
}
