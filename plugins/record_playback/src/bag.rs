//! AimRT's bag layout on disk: a folder `aimrtbag_YYYYMMDD_hhmmss` holding
//! `aimrtbag_YYYYMMDD_hhmmss.mcap` files and a `metadata.yaml` that lists the topics and
//! the files.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// `aimrtbag_` + the local time, to the second.
pub(crate) fn stamp_name(at: chrono::DateTime<chrono::Local>) -> String {
    format!("aimrtbag_{}", at.format("%Y%m%d_%H%M%S"))
}

/// A name in `dir` that does not exist yet: `base`, else `base_1`, `base_2`… (AimRT fails
/// when two bags or files open in the same second).
pub(crate) fn fresh(dir: &Path, base: &str, ext: &str) -> PathBuf {
    let mut n = 0;
    loop {
        let name = if n == 0 {
            format!("{base}{ext}")
        } else {
            format!("{base}_{n}{ext}")
        };
        let p = dir.join(name);
        if !p.exists() {
            return p;
        }
        n += 1;
    }
}

/// One topic of `metadata.yaml`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct TopicEntry {
    pub(crate) id: usize,
    pub(crate) topic_name: String,
    pub(crate) msg_type: String,
    pub(crate) serialization_type: String,
}

/// One file of `metadata.yaml`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct FileEntry {
    pub(crate) path: String,
    pub(crate) start_timestamp: u64,
}

#[derive(Debug, Serialize)]
struct Information<'a> {
    version: u32,
    extra_attributes: &'a BTreeMap<String, serde_json::Value>,
    topics: &'a [TopicEntry],
    files: &'a [FileEntry],
}

#[derive(Debug, Serialize)]
struct Metadata<'a> {
    aimrt_bagfile_information: Information<'a>,
}

/// Writes `<folder>/metadata.yaml` (version 1, AimRT's keys in AimRT's order).
pub(crate) fn write_metadata(
    folder: &Path,
    extra: &BTreeMap<String, serde_json::Value>,
    topics: &[TopicEntry],
    files: &[FileEntry],
) -> std::io::Result<()> {
    let m = Metadata {
        aimrt_bagfile_information: Information {
            version: 1,
            extra_attributes: extra,
            topics,
            files,
        },
    };
    let text = serde_saphyr::to_string(&m)
        .map_err(|e| std::io::Error::other(format!("cannot write metadata.yaml: {e}")))?;
    // Written beside, then renamed: a reader never sees half a file.
    let tmp = folder.join("metadata.yaml.tmp");
    std::fs::write(&tmp, text)?;
    std::fs::rename(tmp, folder.join("metadata.yaml"))
}

/// An open MCAP file.
pub(crate) type McapFile = mcap::Writer<BufWriter<File>>;

/// What `metadata.yaml` says, as playback reads it (keys it does not know are ignored, so
/// a later AimRT's additions do not stop playback).
#[derive(Debug, Deserialize)]
pub(crate) struct BagInfo {
    pub(crate) version: u32,
    #[serde(default)]
    pub(crate) topics: Vec<TopicEntry>,
    #[serde(default)]
    pub(crate) files: Vec<FileEntry>,
}

#[derive(Debug, Deserialize)]
struct MetadataIn {
    aimrt_bagfile_information: BagInfo,
}

/// Reads `<folder>/metadata.yaml`; `Err` says what is wrong with it.
pub(crate) fn read_metadata(folder: &Path) -> Result<BagInfo, String> {
    let path = folder.join("metadata.yaml");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("cannot read {}: {e}; bag_path must be one bag folder (aimrtbag_YYYYMMDD_hhmmss) holding metadata.yaml", path.display()))?;
    let m: MetadataIn = serde_saphyr::from_str(&text)
        .map_err(|e| format!("{} is not a bag's metadata: {e}", path.display()))?;
    Ok(m.aimrt_bagfile_information)
}

/// One message read back from a bag.
pub(crate) struct Recorded {
    /// The index of its topic among the played ones.
    pub(crate) topic: usize,
    pub(crate) log_time: u64,
    pub(crate) publish_time: u64,
    pub(crate) sequence: u32,
    pub(crate) data: Vec<u8>,
}

/// Reads the messages of a bag's files in order, one file at a time and a piece of a file
/// at a time (files may be larger than memory). A file that ends early (a process killed
/// mid-recording) or is damaged is read up to there, with a warning.
pub(crate) struct BagReader {
    files: std::collections::VecDeque<PathBuf>,
    current: Option<FileReader>,
    topics: std::collections::HashMap<String, usize>,
    start: u64,
    stop: Option<u64>,
}

struct FileReader {
    path: PathBuf,
    file: File,
    reader: mcap::sans_io::LinearReader,
    channels: std::collections::HashMap<u16, Option<usize>>,
}

impl BagReader {
    /// Reads `files` (each with its start time, in order) for the messages of `topics`
    /// (name → index) logged in `start..=stop`. Files that end before `start` are skipped
    /// unread.
    pub(crate) fn new(
        files: &[(PathBuf, u64)],
        topics: std::collections::HashMap<String, usize>,
        start: u64,
        stop: Option<u64>,
    ) -> BagReader {
        // A file whose successor starts at or before `start` holds nothing to play.
        let first = files
            .iter()
            .rposition(|(_, begins)| *begins <= start)
            .unwrap_or(0);
        BagReader {
            files: files[first..].iter().map(|(p, _)| p.clone()).collect(),
            current: None,
            topics,
            start,
            stop,
        }
    }

    /// The next message, or `None` at the end (or past `stop`).
    pub(crate) fn next(&mut self) -> Option<Recorded> {
        loop {
            let Some(f) = self.current.as_mut() else {
                let path = self.files.pop_front()?;
                match File::open(&path) {
                    Ok(file) => {
                        self.current = Some(FileReader {
                            path,
                            file,
                            reader: mcap::sans_io::LinearReader::new(),
                            channels: Default::default(),
                        })
                    }
                    Err(e) => {
                        tracing::warn!("playback: cannot open {}: {e}; skipping it", path.display())
                    }
                }
                continue;
            };
            match f.step(&self.topics) {
                Ok(Some(m)) => {
                    if m.log_time < self.start {
                        continue;
                    }
                    if self.stop.is_some_and(|stop| m.log_time > stop) {
                        self.files.clear();
                        self.current = None;
                        return None;
                    }
                    return Some(m);
                }
                Ok(None) => self.current = None,
                Err(e) => {
                    tracing::warn!(
                        "playback: {} is read up to a damaged or cut record ({e}); going on with the next file",
                        f.path.display()
                    );
                    self.current = None;
                }
            }
        }
    }
}

impl FileReader {
    /// The next message of a played topic in this file; `Ok(None)` at its end.
    fn step(
        &mut self,
        topics: &std::collections::HashMap<String, usize>,
    ) -> Result<Option<Recorded>, String> {
        use std::io::Read;
        while let Some(event) = self.reader.next_event() {
            match event.map_err(|e| e.to_string())? {
                mcap::sans_io::LinearReadEvent::ReadRequest(need) => {
                    let buf = self.reader.insert(need.max(64 * 1024));
                    let n = self.file.read(buf).map_err(|e| e.to_string())?;
                    self.reader.notify_read(n);
                }
                mcap::sans_io::LinearReadEvent::Record { opcode, data } => {
                    match mcap::parse_record(opcode, data).map_err(|e| e.to_string())? {
                        mcap::records::Record::Channel(c) => {
                            self.channels.insert(c.id, topics.get(&c.topic).copied());
                        }
                        mcap::records::Record::Message { header, data } => {
                            if let Some(Some(topic)) = self.channels.get(&header.channel_id) {
                                return Ok(Some(Recorded {
                                    topic: *topic,
                                    log_time: header.log_time,
                                    publish_time: header.publish_time,
                                    sequence: header.sequence,
                                    data: data.into_owned(),
                                }));
                            }
                        }
                        _ => {}
                    }
                }
            }
        }
        Ok(None)
    }
}
