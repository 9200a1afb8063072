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

/// Makes a folder or a file in `dir` (with `make`, which must fail with `AlreadyExists`
/// for a name that is taken) under a name nothing has yet: `base` + `ext`, else
/// `base_1` + `ext`, `base_2` + `ext`… (AimRT fails when two bags or files open in the
/// same second). The name is taken by creating it, so two processes recording into the
/// same `bag_path` in the same second never share a folder or a file. `dir` is made first
/// when it is missing.
pub(crate) fn create_fresh<T>(
    dir: &Path,
    base: &str,
    ext: &str,
    make: impl Fn(&Path) -> std::io::Result<T>,
) -> std::io::Result<(PathBuf, T)> {
    std::fs::create_dir_all(dir)?;
    let mut n = 0u64;
    loop {
        let name = if n == 0 {
            format!("{base}{ext}")
        } else {
            format!("{base}_{n}{ext}")
        };
        let p = dir.join(name);
        match make(&p) {
            Ok(made) => return Ok((p, made)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => n += 1,
            Err(e) => return Err(e),
        }
    }
}

/// A new file for [`create_fresh`]: fails on a name that is taken.
pub(crate) fn new_file(p: &Path) -> std::io::Result<File> {
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(p)
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
    let written = std::fs::write(&tmp, text)
        .and_then(|()| std::fs::rename(&tmp, folder.join("metadata.yaml")));
    if written.is_err() {
        // A full disk leaves the last metadata.yaml as it was, and no half-written copy.
        let _ = std::fs::remove_file(&tmp);
    }
    written
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

/// The most a bag's `metadata.yaml` may hold. It lists the bag's topics and files, about
/// 90 bytes a file: a day recorded at 1 MiB a second in files of 1 MiB is 86 400 files,
/// some 8 MiB.
pub(crate) const MAX_METADATA_BYTES: u64 = 64 << 20;

/// Reads `<folder>/metadata.yaml`; `Err` says what is wrong with it.
pub(crate) fn read_metadata(folder: &Path) -> Result<BagInfo, String> {
    let path = folder.join("metadata.yaml");
    let read = aimrt_plugin_api::read_regular_file(&path, MAX_METADATA_BYTES)
        .and_then(|b| String::from_utf8(b).map_err(std::io::Error::other));
    let text = read.map_err(|e| {
        format!(
            "cannot read {}: {e}; bag_path must be one bag folder (aimrtbag_YYYYMMDD_hhmmss) holding metadata.yaml{}",
            path.display(),
            bags_near(folder)
        )
    })?;
    let m: MetadataIn = serde_saphyr::from_str(&text)
        .map_err(|e| format!("{} is not a bag's metadata: {e}", path.display()))?;
    Ok(m.aimrt_bagfile_information)
}

/// The bag folders a wrong `bag_path` most likely meant: those inside it (the recording's
/// `bag_path` given instead of one of its bags), else those beside it; the newest three.
fn bags_near(folder: &Path) -> String {
    let bags_in = |dir: &Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.path().join("metadata.yaml").is_file())
            .filter_map(|e| e.file_name().into_string().ok())
            .filter(|n| n.starts_with("aimrtbag_"))
            .collect();
        names.sort();
        names
    };
    let (dir, names) = match bags_in(folder) {
        inside if !inside.is_empty() => (folder, inside),
        _ => {
            let parent = folder
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            (parent, bags_in(parent))
        }
    };
    if names.is_empty() {
        return String::new();
    }
    let newest: Vec<String> = names[names.len().saturating_sub(3)..]
        .iter()
        .map(|n| dir.join(n).display().to_string())
        .collect();
    format!(
        "; the bag folders there, the newest last: {}{}",
        if names.len() > 3 { "…, " } else { "" },
        newest.join(", ")
    )
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
    topics: Topics,
    start: u64,
    stop: Option<u64>,
    /// Messages of the played topics returned (in the window) and read (at any time),
    /// and when the first and the last read were logged: what [`why_nothing`](Self::why_nothing)
    /// says.
    returned: u64,
    read: u64,
    read_span: Option<(u64, u64)>,
}

/// The largest record read, and the largest chunk once decompressed, unless the file
/// itself is larger: a length field above it is damage, refused before anything is
/// allocated for it.
pub(crate) const RECORD_LIMIT: u64 = 256 << 20;

/// The largest summary section read for its channels (a real one holds an index entry of
/// about 100 bytes a chunk).
const SUMMARY_LIMIT: u64 = 64 << 20;

/// One MCAP file read in order, from a file or (in tests) from memory.
///
/// The `mcap` crate finds the records; chunks are decompressed and read here, whole and
/// with every length checked against what holds it, because the crate's streaming reader
/// can loop forever on a damaged compressed chunk (mcap 0.24).
struct FileReader<R = File> {
    path: PathBuf,
    file: R,
    /// The file's size.
    len: u64,
    /// Bytes of the file not read yet: a record that claims more is cut or damaged.
    left: u64,
    limit: u64,
    reader: mcap::sans_io::LinearReader,
    channels: Channels,
    /// Chunks passed over because they do not read.
    damaged_chunks: u64,
    /// The records of the chunk being read, and where the next one starts.
    chunk: Vec<u8>,
    chunk_at: usize,
}

impl BagReader {
    /// Reads `files` (each with its start time, in order) for the messages of `topics`
    /// (name → index) logged in `start..=stop`. Files that end before `start` are skipped
    /// unread.
    pub(crate) fn new(
        files: &[(PathBuf, u64)],
        topics: Topics,
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
            returned: 0,
            read: 0,
            read_span: None,
        }
    }

    /// The next message, or `None` at the end (or past `stop`).
    pub(crate) fn next(&mut self) -> Option<Recorded> {
        loop {
            let Some(f) = self.current.as_mut() else {
                let path = self.files.pop_front()?;
                match File::open(&path).and_then(|f| Ok((f.metadata()?.len(), f))) {
                    Ok((len, file)) => self.current = Some(FileReader::new(path, file, len)),
                    Err(e) => {
                        tracing::warn!("playback: cannot open {}: {e}; skipping it", path.display())
                    }
                }
                continue;
            };
            match f.step(&self.topics) {
                Ok(Some(Found::Message(m))) => {
                    self.read += 1;
                    let (first, last) = self.read_span.unwrap_or((m.log_time, m.log_time));
                    self.read_span = Some((first.min(m.log_time), last.max(m.log_time)));
                    if m.log_time < self.start {
                        continue;
                    }
                    if self.stop.is_some_and(|stop| m.log_time > stop) {
                        self.files.clear();
                        self.close_file();
                        return None;
                    }
                    self.returned += 1;
                    return Some(m);
                }
                Ok(Some(Found::DamagedChunk(e))) => {
                    if f.damaged_chunks <= WARNED_CHUNKS {
                        tracing::warn!(
                            "playback: {} has a damaged chunk ({e}); its messages are not played, the file goes on after it",
                            f.path.display()
                        );
                    }
                }
                Ok(None) => self.close_file(),
                Err(e) => {
                    tracing::warn!(
                        "playback: {} is read up to a damaged or cut record ({e}); going on with the next file",
                        f.path.display()
                    );
                    self.close_file();
                }
            }
        }
    }

    /// Why a playback that reached its end published nothing, in seconds after the bag's
    /// start `bag_start`; `None` when it returned a message.
    pub(crate) fn why_nothing(&self, bag_start: u64) -> Option<String> {
        if self.returned > 0 {
            return None;
        }
        let secs = |t: u64| t.saturating_sub(bag_start) as f64 / 1e9;
        let window = match self.stop {
            Some(stop) => format!("{:.1} s to {:.1} s", secs(self.start), secs(stop)),
            None => format!("{:.1} s to the end", secs(self.start)),
        };
        Some(match self.read_span {
            Some((first, last)) => format!(
                "none of the {} messages of the played topics read was logged in the window \
                 ({window} after the bag's start); they were logged {:.1} s to {:.1} s after it \
                 (skip_duration_s, play_duration_s)",
                self.read,
                secs(first),
                secs(last)
            ),
            None => format!(
                "the files read hold no message of the played topics (window {window} after \
                 the bag's start); check topic_meta_list against the bag's metadata.yaml"
            ),
        })
    }

    /// Leaves the current file, saying what of it could not be played beyond the damage
    /// already reported.
    fn close_file(&mut self) {
        let Some(f) = self.current.take() else {
            return;
        };
        if f.damaged_chunks > WARNED_CHUNKS {
            tracing::warn!(
                "playback: {} had {} damaged chunks in all (the first {WARNED_CHUNKS} named above); their messages are not played",
                f.path.display(),
                f.damaged_chunks
            );
        }
        if f.channels.orphans > 0 {
            tracing::warn!(
                "playback: {} messages of {} name a channel whose record was in a damaged chunk; they are not played",
                f.channels.orphans,
                f.path.display()
            );
        }
    }
}

/// What a step through a file found.
enum Found {
    /// A message of a played topic.
    Message(Recorded),
    /// A chunk that does not read, and why; the file goes on after it.
    DamagedChunk(String),
}

/// How many damaged chunks of a file are warned about one by one; the rest are counted.
const WARNED_CHUNKS: u64 = 5;

/// The channels of a file: its id → the index of its topic when played.
#[derive(Default)]
struct Channels {
    ids: std::collections::HashMap<u16, Option<usize>>,
    /// Messages whose channel was never defined: its record was lost to damage.
    orphans: u64,
}

impl<R: std::io::Read + std::io::Seek> FileReader<R> {
    /// A reader of `file`, `len` bytes long, named `path` in what it reports.
    fn new(path: PathBuf, file: R, len: u64) -> FileReader<R> {
        let limit = len.max(RECORD_LIMIT);
        FileReader {
            path,
            file,
            len,
            left: len,
            limit,
            reader: mcap::sans_io::LinearReader::new_with_options(
                mcap::sans_io::LinearReaderOptions::default()
                    .with_emit_chunks(true)
                    .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX)),
            ),
            channels: Channels::default(),
            chunk: Vec::new(),
            chunk_at: 0,
            damaged_chunks: 0,
        }
    }

    /// The next message of a played topic in this file; `Ok(None)` at its end.
    fn step(&mut self, topics: &Topics) -> Result<Option<Found>, String> {
        loop {
            while self.chunk_at < self.chunk.len() {
                let read =
                    next_in_chunk(&self.chunk, &mut self.chunk_at).and_then(|(opcode, record)| {
                        read_record(&mut self.channels, opcode, record, topics)
                    });
                match read {
                    Ok(Some(m)) => return Ok(Some(Found::Message(m))),
                    Ok(None) => {}
                    Err(e) => {
                        // The chunk's own records are damaged (its CRC was 0, "not
                        // computed"): the rest of it is passed over.
                        self.chunk_at = self.chunk.len();
                        return Ok(Some(self.damaged_chunk(e, topics)));
                    }
                }
            }
            let Some(event) = self.reader.next_event() else {
                return Ok(None);
            };
            match event.map_err(|e| e.to_string())? {
                mcap::sans_io::LinearReadEvent::ReadRequest(need) => {
                    // What a record claims beyond the file's end is never allocated.
                    if need as u64 > self.left {
                        return Err(format!(
                            "a record needs {need} more bytes, the file has {} left",
                            self.left
                        ));
                    }
                    let want = need
                        .max(64 * 1024)
                        .min(usize::try_from(self.left).unwrap_or(usize::MAX));
                    let buf = self.reader.insert(want);
                    let n = self.file.read(buf).map_err(|e| e.to_string())?;
                    self.left -= n as u64;
                    self.reader.notify_read(n);
                }
                mcap::sans_io::LinearReadEvent::Record {
                    opcode: mcap::records::op::CHUNK,
                    data,
                } => {
                    // The chunk record's length framed it: damage inside leaves the
                    // records after it readable.
                    match unchunk(data, self.limit) {
                        Ok(records) => {
                            self.chunk = records;
                            self.chunk_at = 0;
                        }
                        Err(e) => {
                            let why = format!("{e}{}", logged_between(data));
                            return Ok(Some(self.damaged_chunk(why, topics)));
                        }
                    }
                }
                mcap::sans_io::LinearReadEvent::Record { opcode, data } => {
                    if let Some(m) = read_record(&mut self.channels, opcode, data, topics)? {
                        return Ok(Some(Found::Message(m)));
                    }
                }
            }
        }
    }

    /// Counts a damaged chunk. The first one of a file also reads the channels its summary
    /// section repeats (a file closed by its writer has one), since the writer puts a
    /// channel's record in the chunk of its first message: without them, every later
    /// message of a channel defined in the damaged chunk would be lost as well.
    fn damaged_chunk(&mut self, why: String, topics: &Topics) -> Found {
        self.damaged_chunks += 1;
        if self.damaged_chunks == 1 {
            match self.summary_channels(topics) {
                Ok(summary) => {
                    for (id, topic) in summary.ids {
                        self.channels.ids.entry(id).or_insert(topic);
                    }
                }
                Err(e) => tracing::debug!(
                    "playback: {}: no channels from the summary section ({e})",
                    self.path.display()
                ),
            }
        }
        Found::DamagedChunk(why)
    }

    /// The channels listed in the file's summary section, found through its footer; the
    /// file's read position is kept.
    fn summary_channels(&mut self, topics: &Topics) -> Result<Channels, String> {
        use std::io::SeekFrom;
        // The footer record (opcode, length 20, summary start, summary offset start, CRC)
        // and the closing magic.
        const TAIL: u64 = 1 + 8 + 20 + 8;
        let back = self.file.stream_position().map_err(|e| e.to_string())?;
        let mut read_at = |at: u64, buf: &mut [u8]| {
            self.file
                .seek(SeekFrom::Start(at))
                .and_then(|_| self.file.read_exact(buf))
                .map_err(|e| e.to_string())
        };
        let footer_at = self.len.checked_sub(TAIL).ok_or("no footer")?;
        let mut tail = [0u8; TAIL as usize];
        let summary = read_at(footer_at, &mut tail).and_then(|()| {
            let mut f = Fields(&tail);
            let (opcode, len, start, offsets) =
                (|| Some((f.array::<1>()?[0], f.u64()?, f.u64()?, f.u64()?)))()
                    .ok_or("no footer")?;
            if opcode != mcap::records::op::FOOTER || len != 20 || &tail[29..] != mcap::MAGIC {
                return Err("no footer: the file was not closed by its writer".to_owned());
            }
            let end = if offsets == 0 { footer_at } else { offsets };
            if start < 8 || start > end || end > footer_at {
                return Err(format!("no summary section (it starts at {start})"));
            }
            if end - start > SUMMARY_LIMIT {
                return Err(format!(
                    "a summary section of {} bytes, more than the {SUMMARY_LIMIT} read",
                    end - start
                ));
            }
            let mut records = vec![0; (end - start) as usize];
            read_at(start, &mut records)?;
            let mut channels = Channels::default();
            let mut at = 0;
            while at < records.len() {
                let (opcode, record) = next_in_chunk(&records, &mut at)?;
                if opcode == mcap::records::op::CHANNEL {
                    read_record(&mut channels, opcode, record, topics)?;
                }
            }
            Ok(channels)
        });
        self.file
            .seek(SeekFrom::Start(back))
            .map_err(|e| e.to_string())?;
        summary
    }
}

/// When the messages of a chunk record were logged, as its header says (local time), for
/// the warning about a damaged chunk; nothing when the header itself does not read as
/// times (0, or an end before the start).
fn logged_between(chunk: &[u8]) -> String {
    let mut f = Fields(chunk);
    let (Some(start), Some(end)) = (f.u64(), f.u64()) else {
        return String::new();
    };
    let local = |ns: u64| {
        let at = chrono::DateTime::from_timestamp_nanos(i64::try_from(ns).ok()?);
        Some(at.with_timezone(&chrono::Local))
    };
    match (local(start), local(end)) {
        (Some(a), Some(b)) if start > 0 && start <= end => format!(
            "; its messages were logged from {} to {}",
            a.format("%Y-%m-%d %H:%M:%S%.3f"),
            b.format("%H:%M:%S%.3f")
        ),
        _ => String::new(),
    }
}

/// The played topics: a name → its index among them.
type Topics = std::collections::HashMap<String, usize>;

/// A record outside chunks or in one: a channel is remembered in `channels`, a message of
/// a played topic returned, one of no known channel counted, anything else passed over
/// unread.
fn read_record(
    channels: &mut Channels,
    opcode: u8,
    data: &[u8],
    topics: &Topics,
) -> Result<Option<Recorded>, String> {
    use mcap::records::op;
    let mut f = Fields(data);
    match opcode {
        op::CHANNEL => {
            // id, schema id, topic (then the encoding and the metadata, not needed).
            let (id, _, topic) = (|| Some((f.u16()?, f.u16()?, f.text()?)))()
                .ok_or("a channel record that does not read as one")?;
            channels.ids.insert(id, topics.get(topic).copied());
        }
        op::MESSAGE => {
            let (channel, sequence, log_time, publish_time) =
                (|| Some((f.u16()?, f.u32()?, f.u64()?, f.u64()?)))()
                    .ok_or("a message record shorter than its header")?;
            match channels.ids.get(&channel) {
                Some(Some(topic)) => {
                    return Ok(Some(Recorded {
                        topic: *topic,
                        log_time,
                        publish_time,
                        sequence,
                        data: f.0.to_vec(),
                    }))
                }
                Some(None) => {}
                None => channels.orphans += 1,
            }
        }
        _ => {}
    }
    Ok(None)
}

/// The fields of a record, read in order with every length checked against what is left
/// (the `mcap` crate reserves what a string's length claims, up to 4 GiB, before reading
/// it).
struct Fields<'a>(&'a [u8]);

impl<'a> Fields<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        if n > self.0.len() {
            return None;
        }
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Some(head)
    }
    fn array<const N: usize>(&mut self) -> Option<[u8; N]> {
        self.take(N)?.try_into().ok()
    }
    fn u16(&mut self) -> Option<u16> {
        self.array().map(u16::from_le_bytes)
    }
    fn u32(&mut self) -> Option<u32> {
        self.array().map(u32::from_le_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.array().map(u64::from_le_bytes)
    }
    /// A string: its length (u32), then its UTF-8 bytes.
    fn text(&mut self) -> Option<&'a str> {
        let len = usize::try_from(self.u32()?).ok()?;
        std::str::from_utf8(self.take(len)?).ok()
    }
}

/// The records of a chunk record, decompressed and checked: the size and the CRC it
/// declares, at most `limit` bytes.
fn unchunk(record: &[u8], limit: u64) -> Result<Vec<u8>, String> {
    let mut f = Fields(record);
    // Start and end time, size decompressed, CRC, compression, size compressed, records.
    let (_, _, size, crc, compression, compressed) =
        (|| Some((f.u64()?, f.u64()?, f.u64()?, f.u32()?, f.text()?, f.u64()?)))()
            .ok_or("a chunk record shorter than its header")?;
    let data = usize::try_from(compressed)
        .ok()
        .and_then(|n| f.take(n))
        .ok_or_else(|| {
            format!(
                "a chunk claims {compressed} bytes of records, it has {}",
                f.0.len()
            )
        })?;
    if size > limit {
        return Err(format!(
            "a chunk claims {size} bytes decompressed, more than the {limit} allowed"
        ));
    }
    let records = match compression {
        "" => data.to_vec(),
        "zstd" => zstd::bulk::decompress(data, size as usize)
            .map_err(|e| format!("a zstd chunk does not decompress: {e}"))?,
        "lz4" => {
            use std::io::Read;
            let mut out = Vec::new();
            lz4::Decoder::new(data)
                .and_then(|d| d.take(size + 1).read_to_end(&mut out))
                .map_err(|e| format!("an lz4 chunk does not decompress: {e}"))?;
            out
        }
        other => {
            return Err(format!(
                "a chunk compressed with '{other}', which is not zstd or lz4"
            ))
        }
    };
    if records.len() as u64 != size {
        return Err(format!(
            "a chunk decompresses to {} bytes, its header says {size}",
            records.len()
        ));
    }
    let computed = crc32fast::hash(&records);
    if crc != 0 && crc != computed {
        return Err(format!(
            "a chunk's CRC is {computed:#010x}, its header says {crc:#010x}"
        ));
    }
    Ok(records)
}

/// The record of `chunk` at `at` (its opcode and body); moves `at` past it.
fn next_in_chunk<'c>(chunk: &'c [u8], at: &mut usize) -> Result<(u8, &'c [u8]), String> {
    let rest = &chunk[*at..];
    let (head, body) = rest
        .split_first_chunk::<9>()
        .ok_or("a record cut at the end of its chunk")?;
    let len = u64::from_le_bytes(head[1..].try_into().unwrap_or_default());
    if len > body.len() as u64 {
        return Err(format!(
            "a record in a chunk claims {len} bytes, the chunk has {} left",
            body.len()
        ));
    }
    *at += 9 + len as usize;
    Ok((head[0], &body[..len as usize]))
}

/// What one MCAP file in memory reads as: its messages, the damaged chunks passed over,
/// the messages of lost channels, and the damage that ended it (`None`: it read to its
/// end). For tests and the `mcap` fuzz target.
pub(crate) struct ReadBack {
    pub(crate) messages: Vec<Recorded>,
    pub(crate) damaged_chunks: Vec<String>,
    pub(crate) orphans: u64,
    pub(crate) end: Option<String>,
}

/// Reads `bytes` as one file of a bag whose played topics are `topics`.
pub(crate) fn read_bytes(bytes: &[u8], topics: &Topics) -> ReadBack {
    let mut r = FileReader::new(
        "memory.mcap".into(),
        std::io::Cursor::new(bytes),
        bytes.len() as u64,
    );
    let mut back = ReadBack {
        messages: Vec::new(),
        damaged_chunks: Vec::new(),
        orphans: 0,
        end: None,
    };
    loop {
        match r.step(topics) {
            Ok(Some(Found::Message(m))) => back.messages.push(m),
            Ok(Some(Found::DamagedChunk(e))) => back.damaged_chunks.push(e),
            Ok(None) => break,
            Err(e) => {
                back.end = Some(e);
                break;
            }
        }
    }
    back.orphans = r.channels.orphans;
    back
}

#[cfg(test)]
mod tests {
    use super::*;
    use stats_alloc::{Region, StatsAlloc, INSTRUMENTED_SYSTEM};

    #[global_allocator]
    static GLOBAL: &StatsAlloc<std::alloc::System> = &INSTRUMENTED_SYSTEM;

    /// The bytes allocated in the process while `f` ran (other tests of this binary add
    /// their little).
    fn allocated_by<T>(f: impl FnOnce() -> T) -> (T, usize) {
        let region = Region::new(GLOBAL);
        let out = f();
        (out, region.change().bytes_allocated)
    }

    /// Eight recorders opening a bag in the same second, in the same `bag_path`, where one
    /// bag of that second exists already: each gets a folder, and a file in it, of its own.
    #[test]
    fn names_wanted_at_once_are_each_given_once() {
        let dir = std::env::temp_dir().join(format!("aimrt_fresh_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let base = "aimrtbag_20261129_010000";
        std::fs::create_dir_all(dir.join(base)).unwrap();
        let made: Vec<(PathBuf, PathBuf)> = (0..8)
            .map(|_| {
                let dir = dir.clone();
                std::thread::spawn(move || {
                    let (folder, ()) =
                        create_fresh(&dir, base, "", |p| std::fs::create_dir(p)).unwrap();
                    let (file, _) = create_fresh(&dir, base, ".mcap", new_file).unwrap();
                    (folder, file)
                })
            })
            .collect::<Vec<_>>()
            .into_iter()
            .map(|t| t.join().unwrap())
            .collect();
        let folders: std::collections::BTreeSet<_> = made.iter().map(|(f, _)| f).collect();
        let files: std::collections::BTreeSet<_> = made.iter().map(|(_, f)| f).collect();
        assert_eq!(folders.len(), 8, "{made:?}");
        assert_eq!(files.len(), 8, "{made:?}");
        assert!(
            !folders.contains(&dir.join(base)),
            "the existing bag was taken"
        );
        assert!(files.contains(&dir.join(format!("{base}.mcap"))));
        // A missing bag_path is made; another error is said.
        let (deep, ()) =
            create_fresh(&dir.join("a/b"), base, "", |p| std::fs::create_dir(p)).unwrap();
        assert_eq!(deep, dir.join("a/b").join(base));
        let blocked = dir.join(format!("{base}.mcap")).join("x");
        assert!(create_fresh(&blocked, base, "", |p| std::fs::create_dir(p)).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// An MCAP file of `n` messages of 16 bytes on `/t`, in chunks compressed as
    /// `compression`, or without chunks.
    fn mcap_file(n: u32, compression: Option<mcap::Compression>, chunked: bool) -> Vec<u8> {
        let mut w = mcap::WriteOptions::new()
            .compression(compression)
            .use_chunks(chunked)
            .chunk_size(Some(200))
            .create(std::io::Cursor::new(Vec::new()))
            .expect("a writer");
        let channel = w
            .add_channel(0, "/t", "pb", &BTreeMap::new())
            .expect("a channel");
        for i in 0..n {
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: i,
                log_time: u64::from(i),
                publish_time: u64::from(i),
            };
            w.write_to_known_channel(&header, &[i as u8; 16])
                .expect("a message");
        }
        w.finish().expect("finished");
        w.into_inner().into_inner()
    }

    fn read(bytes: &[u8]) -> ReadBack {
        read_bytes(bytes, &[("/t".to_owned(), 0)].into())
    }

    const KINDS: [(Option<mcap::Compression>, bool); 4] = [
        (None, false),
        (None, true),
        (Some(mcap::Compression::Zstd), true),
        (Some(mcap::Compression::Lz4), true),
    ];

    #[test]
    fn an_intact_file_reads_whole() {
        for (compression, chunked) in KINDS {
            let back = read(&mcap_file(10, compression, chunked));
            assert_eq!(back.end, None, "{compression:?}, chunks {chunked}");
            assert_eq!(back.damaged_chunks, Vec::<String>::new());
            let seqs: Vec<u32> = back.messages.iter().map(|m| m.sequence).collect();
            assert_eq!(seqs, (0..10).collect::<Vec<_>>());
            assert!(back
                .messages
                .iter()
                .all(|m| m.data == [m.sequence as u8; 16]));
        }
    }

    /// Each kind of file damaged every way (every byte flipped, huge 16-, 32- and 64-bit
    /// lengths at every offset): read up to the damage or whole, never a panic or a hang
    /// (the test would not end), never an allocation of what a damaged length claims (the
    /// `mcap` crate's record parser reserved a string's claimed length, up to 4 GiB,
    /// before reading it).
    #[test]
    fn a_damaged_file_is_read_up_to_the_damage_without_a_panic_a_hang_or_a_huge_allocation() {
        for (compression, chunked) in KINDS {
            let file = mcap_file(10, compression, chunked);
            for (what, damaged) in aimrt_plugin_api::__private::damaged(&file) {
                let (back, bytes) = allocated_by(|| read(&damaged));
                let n = back.messages.len();
                assert!(n <= 10, "{compression:?}, {what}: {n}");
                assert!(
                    bytes < 64 << 20,
                    "{compression:?}, {what}: {bytes} bytes allocated"
                );
            }
        }
    }

    /// The chunk records of an MCAP file: where each starts (its opcode) and the times of
    /// its first and last message (here the sequences of its messages).
    fn chunks(file: &[u8]) -> Vec<(usize, std::ops::RangeInclusive<u32>)> {
        let mut out = Vec::new();
        let mut at = 8;
        while at + 9 <= file.len() {
            let len = u64::from_le_bytes(file[at + 1..at + 9].try_into().unwrap()) as usize;
            if file[at] == mcap::records::op::CHUNK {
                let time = |i: usize| {
                    u64::from_le_bytes(file[at + 9 + i..at + 17 + i].try_into().unwrap()) as u32
                };
                out.push((at, time(0)..=time(8)));
            }
            at += 9 + len;
        }
        out
    }

    /// `file` with one byte of the records of the chunk at `at` flipped.
    fn with_chunk_damaged(file: &[u8], at: usize) -> Vec<u8> {
        let mut damaged = file.to_vec();
        // Opcode and length; start, end, size, CRC; the compression's name; the size
        // compressed; then the records.
        let name = u32::from_le_bytes(file[at + 37..at + 41].try_into().unwrap()) as usize;
        let records = at + 41 + name + 8;
        damaged[records + 3] ^= 0xff;
        damaged
    }

    /// A chunk whose bytes are damaged is passed over, with the damage named, and every
    /// message of the other chunks is read in order: also when the damaged chunk is the
    /// first, which holds the channel's record (the summary section repeats it).
    #[test]
    fn a_damaged_chunk_is_passed_over_and_the_file_goes_on_after_it() {
        for (compression, chunked) in KINDS.into_iter().filter(|(_, chunked)| *chunked) {
            let file = mcap_file(20, compression, chunked);
            let chunks = chunks(&file);
            assert!(
                chunks.len() >= 3,
                "{compression:?}: {} chunks",
                chunks.len()
            );
            for (at, lost) in [chunks[0].clone(), chunks[1].clone()] {
                let back = read(&with_chunk_damaged(&file, at));
                let seqs: Vec<u32> = back.messages.iter().map(|m| m.sequence).collect();
                let expected: Vec<u32> = (0..20).filter(|i| !lost.contains(i)).collect();
                assert_eq!(seqs, expected, "{compression:?}, chunk at {at}");
                assert_eq!(
                    back.damaged_chunks.len(),
                    1,
                    "{compression:?}, chunk at {at}"
                );
                // When its messages were logged, from its header (the first chunk's
                // start, 0, is no time).
                let says_when = back.damaged_chunks[0].contains("; its messages were logged from ");
                assert_eq!(says_when, *lost.start() > 0, "{}", back.damaged_chunks[0]);
                assert_eq!(back.end, None);
                assert_eq!(back.orphans, 0);
            }
        }
    }

    /// The summary section and the footer, read for the channels after a damaged chunk,
    /// damaged every way as well: never a panic, a hang or a huge allocation, and never
    /// more messages than the file has.
    #[test]
    fn a_damaged_summary_read_after_a_damaged_chunk_is_harmless() {
        let file = mcap_file(20, Some(mcap::Compression::Zstd), true);
        let chunks = chunks(&file);
        let first = with_chunk_damaged(&file, chunks[0].0);
        // The summary starts after the data section: after the last chunk and the
        // message indexes that follow it (the footer says where).
        let summary = u64::from_le_bytes(
            file[file.len() - 37 + 9..file.len() - 37 + 17]
                .try_into()
                .unwrap(),
        ) as usize;
        assert!(summary > chunks[chunks.len() - 1].0 && summary < file.len() - 37);
        let mut tried = 0;
        for (what, tail) in aimrt_plugin_api::__private::damaged(&first[summary..]) {
            let mut damaged = first[..summary].to_vec();
            damaged.extend_from_slice(&tail);
            let (back, bytes) = allocated_by(|| read(&damaged));
            let n = back.messages.len();
            assert!(n <= 20, "{what}: {n}");
            assert!(bytes < 64 << 20, "{what}: {bytes} bytes allocated");
            tried += 1;
        }
        assert!(tried > 100, "{tried}");
    }

    /// A file cut by a killed recorder has no summary: after a damaged first chunk, the
    /// messages of the channel it defined are counted as lost, not passed over unsaid.
    #[test]
    fn messages_whose_channel_was_in_a_damaged_chunk_are_counted() {
        let file = mcap_file(20, Some(mcap::Compression::Zstd), true);
        let chunks = chunks(&file);
        let (last, ref in_last) = chunks[chunks.len() - 1];
        let last_len = u64::from_le_bytes(file[last + 1..last + 9].try_into().unwrap());
        // Cut after the last chunk (and its message indexes, if any): no footer.
        let cut = &file[..last + 9 + last_len as usize];
        let back = read(&with_chunk_damaged(cut, chunks[0].0));
        assert!(back.messages.is_empty());
        assert_eq!(back.damaged_chunks.len(), 1);
        assert_eq!(back.orphans, u64::from(19 - chunks[0].1.end()));
        assert!(in_last.contains(&19));
    }

    #[test]
    fn a_record_longer_than_what_is_left_of_the_file_is_named() {
        let file = mcap_file(10, None, false);
        // The first message record (opcode 0x05) after the header, schema and channel.
        let at = (8..file.len())
            .find(|&i| file[i] == 0x05 && file[i + 1..i + 9] == 38u64.to_le_bytes())
            .expect("a message record of 22 + 16 bytes");
        for (len, says) in [
            (1u64 << 20, "more bytes, the file has"),
            (1 << 40, "exceeds limit"),
        ] {
            let mut damaged = file.clone();
            damaged[at + 1..at + 9].copy_from_slice(&len.to_le_bytes());
            let back = read(&damaged);
            assert!(back.messages.is_empty());
            let err = back.end.expect("damage reported");
            assert!(err.contains(says), "{err}");
        }
    }

    /// A `metadata.yaml` that is a FIFO, a directory or larger than the limit is refused at
    /// once: a FIFO used to hold start-up until the process was killed.
    #[test]
    fn metadata_that_is_no_regular_file_or_too_large_is_refused_without_waiting() {
        let dir = std::env::temp_dir().join(format!("aimrt_badmeta_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let refusal = |name: &str, make: &dyn Fn(&Path)| -> String {
            let bag = dir.join(name);
            std::fs::create_dir_all(&bag).unwrap();
            make(&bag.join("metadata.yaml"));
            // Read on a thread of its own: a wait for a writer fails the test, not hangs it.
            let (tx, rx) = std::sync::mpsc::channel();
            std::thread::spawn(move || {
                let _ = tx.send(read_metadata(&bag).err());
            });
            rx.recv_timeout(std::time::Duration::from_secs(10))
                .unwrap_or_else(|_| panic!("{name}: reading metadata.yaml waited"))
                .unwrap_or_else(|| panic!("{name}: metadata.yaml was accepted"))
        };
        let fifo = refusal("fifo", &|p| {
            let made = std::process::Command::new("mkfifo")
                .arg(p)
                .status()
                .unwrap();
            assert!(made.success());
        });
        assert!(fifo.contains("not a regular file"), "{fifo}");
        let folder = refusal("folder", &|p| std::fs::create_dir(p).unwrap());
        assert!(folder.contains("not a regular file"), "{folder}");
        let large = refusal("large", &|p| {
            File::create(p)
                .unwrap()
                .set_len(MAX_METADATA_BYTES + 1)
                .unwrap()
        });
        assert!(large.contains("more than 67108864 bytes"), "{large}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
