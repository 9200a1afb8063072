//! AimRT's bag layout on disk: a folder `aimrtbag_YYYYMMDD_hhmmss` holding
//! `aimrtbag_YYYYMMDD_hhmmss.mcap` files and a `metadata.yaml` that lists the topics and
//! the files.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use serde::Serialize;

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
#[derive(Debug, Clone, Serialize)]
pub(crate) struct TopicEntry {
    pub(crate) id: usize,
    pub(crate) topic_name: String,
    pub(crate) msg_type: String,
    pub(crate) serialization_type: String,
}

/// One file of `metadata.yaml`.
#[derive(Debug, Clone, Serialize)]
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
