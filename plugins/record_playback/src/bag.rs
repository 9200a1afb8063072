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

/// The largest record read, and the largest chunk once decompressed, unless the file
/// itself is larger: a length field above it is damage, refused before anything is
/// allocated for it.
const RECORD_LIMIT: u64 = 256 << 20;

/// One MCAP file read in order, from a file or (in tests) from memory.
///
/// The `mcap` crate finds the records; chunks are decompressed and read here, whole and
/// with every length checked against what holds it, because the crate's streaming reader
/// can loop forever on a damaged compressed chunk (mcap 0.24).
struct FileReader<R = File> {
    path: PathBuf,
    file: R,
    /// Bytes of the file not read yet: a record that claims more is cut or damaged.
    left: u64,
    limit: u64,
    reader: mcap::sans_io::LinearReader,
    channels: std::collections::HashMap<u16, Option<usize>>,
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
                match File::open(&path).and_then(|f| Ok((f.metadata()?.len(), f))) {
                    Ok((len, file)) => self.current = Some(FileReader::new(path, file, len)),
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

impl<R: std::io::Read> FileReader<R> {
    /// A reader of `file`, `len` bytes long, named `path` in what it reports.
    fn new(path: PathBuf, file: R, len: u64) -> FileReader<R> {
        let limit = len.max(RECORD_LIMIT);
        FileReader {
            path,
            file,
            left: len,
            limit,
            reader: mcap::sans_io::LinearReader::new_with_options(
                mcap::sans_io::LinearReaderOptions::default()
                    .with_emit_chunks(true)
                    .with_record_length_limit(usize::try_from(limit).unwrap_or(usize::MAX)),
            ),
            channels: Default::default(),
            chunk: Vec::new(),
            chunk_at: 0,
        }
    }

    /// The next message of a played topic in this file; `Ok(None)` at its end.
    fn step(
        &mut self,
        topics: &std::collections::HashMap<String, usize>,
    ) -> Result<Option<Recorded>, String> {
        loop {
            while self.chunk_at < self.chunk.len() {
                let (opcode, record) = next_in_chunk(&self.chunk, &mut self.chunk_at)?;
                if let Some(m) = read_record(&mut self.channels, opcode, record, topics)? {
                    return Ok(Some(m));
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
                    self.chunk = unchunk(data, self.limit)?;
                    self.chunk_at = 0;
                }
                mcap::sans_io::LinearReadEvent::Record { opcode, data } => {
                    if let Some(m) = read_record(&mut self.channels, opcode, data, topics)? {
                        return Ok(Some(m));
                    }
                }
            }
        }
    }
}

/// A record outside chunks or in one: a channel is remembered in `channels` (its id → the
/// index of its topic when played), a message of a played topic returned, anything else
/// passed over unread.
fn read_record(
    channels: &mut std::collections::HashMap<u16, Option<usize>>,
    opcode: u8,
    data: &[u8],
    topics: &std::collections::HashMap<String, usize>,
) -> Result<Option<Recorded>, String> {
    use mcap::records::op;
    let mut f = Fields(data);
    match opcode {
        op::CHANNEL => {
            // id, schema id, topic (then the encoding and the metadata, not needed).
            let (id, _, topic) = (|| Some((f.u16()?, f.u16()?, f.text()?)))()
                .ok_or("a channel record that does not read as one")?;
            channels.insert(id, topics.get(topic).copied());
        }
        op::MESSAGE => {
            let (channel, sequence, log_time, publish_time) =
                (|| Some((f.u16()?, f.u32()?, f.u64()?, f.u64()?)))()
                    .ok_or("a message record shorter than its header")?;
            if let Some(Some(topic)) = channels.get(&channel) {
                return Ok(Some(Recorded {
                    topic: *topic,
                    log_time,
                    publish_time,
                    sequence,
                    data: f.0.to_vec(),
                }));
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

    /// The messages read from `bytes` until the end or the first damage (`Err`).
    fn read(bytes: &[u8]) -> (Vec<Recorded>, Option<String>) {
        let topics = [("/t".to_owned(), 0)].into();
        let mut r = FileReader::new("t.mcap".into(), bytes, bytes.len() as u64);
        let mut out = Vec::new();
        loop {
            match r.step(&topics) {
                Ok(Some(m)) => out.push(m),
                Ok(None) => return (out, None),
                Err(e) => return (out, Some(e)),
            }
        }
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
            let (read, err) = read(&mcap_file(10, compression, chunked));
            assert_eq!(err, None, "{compression:?}, chunks {chunked}");
            let seqs: Vec<u32> = read.iter().map(|m| m.sequence).collect();
            assert_eq!(seqs, (0..10).collect::<Vec<_>>());
            assert!(read.iter().all(|m| m.data == [m.sequence as u8; 16]));
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
                let ((read, _), bytes) = allocated_by(|| read(&damaged));
                assert!(read.len() <= 10, "{compression:?}, {what}: {}", read.len());
                assert!(
                    bytes < 64 << 20,
                    "{compression:?}, {what}: {bytes} bytes allocated"
                );
            }
        }
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
            let (read, err) = read(&damaged);
            assert!(read.is_empty());
            let err = err.expect("damage reported");
            assert!(err.contains(says), "{err}");
        }
    }
}
