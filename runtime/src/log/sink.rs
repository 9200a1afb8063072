//! Where formatted lines end up: the console and rotating files. Sinks are owned by the log
//! thread; nothing else touches them.

use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use aimrt_plugin_api::{LogEntry, LogLevel};

use super::pattern::Record;
use super::settings::RotateFileOptions;

/// A line's parts, owned, for a sink that takes them (a plugin's backend): what the line
/// was formatted from.
pub(crate) struct Parts {
    time: std::time::SystemTime,
    thread: i32,
    source_line: u32,
    /// Where the logger's name, the file and the function end in `text`; the message
    /// follows.
    ends: [usize; 3],
    text: String,
}

impl Parts {
    pub(crate) fn of(record: &Record<'_>) -> Parts {
        let pieces = [record.name, record.file, record.function, record.message];
        let mut text = String::with_capacity(pieces.iter().map(|p| p.len()).sum());
        let mut ends = [0; 3];
        for (i, piece) in pieces.into_iter().enumerate() {
            text.push_str(piece);
            if let Some(end) = ends.get_mut(i) {
                *end = text.len();
            }
        }
        Parts {
            time: record.time.into(),
            thread: record.thread,
            source_line: record.line,
            ends,
            text,
        }
    }

    /// The entry a plugin's backend gets: these parts and `formatted`.
    pub(crate) fn entry<'a>(&'a self, level: LogLevel, formatted: &'a str) -> LogEntry<'a> {
        let [module, file, function] = self.ends;
        let mut entry = LogEntry::new(level, formatted);
        entry.time = self.time;
        entry.thread_id = i64::from(self.thread);
        entry.module = &self.text[..module];
        entry.file = &self.text[module..file];
        entry.source_line = self.source_line;
        entry.function = &self.text[file..function];
        entry.message = &self.text[function..];
        entry
    }
}

/// One backend's output.
pub(crate) trait Sink: Send {
    /// Whether this sink takes a line's [`Parts`] (they are copied for it).
    fn takes_parts(&self) -> bool {
        false
    }
    /// Writes one line (the newline is added here), with its parts where
    /// [`Sink::takes_parts`] asked for them.
    fn write(&mut self, level: LogLevel, text: &str, parts: Option<&Parts>) -> io::Result<()>;
    /// Hands buffered lines to the OS.
    fn flush(&mut self) -> io::Result<()>;
    /// Flushes and asks the OS to put the data on disk.
    fn sync(&mut self) -> io::Result<()> {
        self.flush()
    }
}

/// A backend of a type a plugin registered (ABI 1.10), handed each line with its parts
/// (1.11).
pub(crate) struct PluginSink(pub(crate) aimrt_plugin_api::ffi::RawLogBackend);

impl Sink for PluginSink {
    fn takes_parts(&self) -> bool {
        true
    }
    fn write(&mut self, level: LogLevel, text: &str, parts: Option<&Parts>) -> io::Result<()> {
        let entry = match parts {
            Some(parts) => parts.entry(level, text),
            None => LogEntry::new(level, text),
        };
        self.0.write(&entry).map_err(io::Error::other)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.0.flush().map_err(io::Error::other)
    }
}

/// Standard output, colored per level when asked and stdout is a terminal.
pub(crate) struct Console {
    color: bool,
    out: BufWriter<io::Stdout>,
}

impl Console {
    pub(crate) fn new(color: bool) -> Console {
        use std::io::IsTerminal;
        Console {
            color: color && io::stdout().is_terminal(),
            out: BufWriter::with_capacity(64 * 1024, io::stdout()),
        }
    }
}

/// AimRT's colors.
fn color_of(level: LogLevel) -> &'static str {
    match level {
        LogLevel::Debug => "\x1b[0;34m",
        LogLevel::Info => "\x1b[0;32m",
        LogLevel::Warn => "\x1b[1;33m",
        LogLevel::Error => "\x1b[0;35m",
        LogLevel::Fatal => "\x1b[0;31m",
        LogLevel::Trace | LogLevel::Off => "",
    }
}

impl Sink for Console {
    fn write(&mut self, level: LogLevel, text: &str, _: Option<&Parts>) -> io::Result<()> {
        if self.color {
            writeln!(self.out, "{}{text}\x1b[0m", color_of(level))
        } else {
            self.out.write_all(text.as_bytes())?;
            self.out.write_all(b"\n")
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}

/// `<path>/<filename>`, rotated to `<filename>_<idx>[_YYYYMMDD_hhmmss]` once it holds more
/// than `max_file_size`; after each open, the oldest rotated files beyond `max_file_num` are
/// deleted (0 keeps all). At most every [`RECHECK`], the active path is checked to still be
/// the open file: one moved or deleted from outside (logrotate, `rm -r log`) is followed
/// by a new one, the directory created again if it is gone.
pub(crate) struct RotateFile {
    options: RotateFileOptions,
    /// Flush after every line (`enable_sync`).
    flush_each: bool,
    file: BufWriter<File>,
    size: u64,
    /// The open file's device and inode.
    id: (u64, u64),
    checked: Instant,
}

/// How often the active path is checked to be the open file.
const RECHECK: Duration = Duration::from_secs(1);

impl RotateFile {
    /// Creates the directory if needed and opens the active file for appending.
    pub(crate) fn open(options: RotateFileOptions) -> io::Result<RotateFile> {
        std::fs::create_dir_all(&options.path)?;
        let (file, size, id) = open_active(&options.path.join(&options.filename))?;
        let sink = RotateFile {
            flush_each: options.sync.is_some(),
            options,
            file,
            size,
            id,
            checked: Instant::now(),
        };
        sink.clean()?;
        Ok(sink)
    }

    /// Opens `<path>/<filename>` again (the directory too, if it is gone), in place of the
    /// open file, which is flushed first as far as it can be.
    fn reopen(&mut self) -> io::Result<()> {
        let _ = self.file.flush();
        std::fs::create_dir_all(&self.options.path)?;
        let (file, size, id) = open_active(&self.active())?;
        self.file = file;
        self.size = size;
        self.id = id;
        self.clean()
    }

    /// Whether the active path is still the open file.
    fn still_there(&self) -> bool {
        std::fs::metadata(self.active()).is_ok_and(|m| (m.dev(), m.ino()) == self.id)
    }

    fn active(&self) -> PathBuf {
        self.options.path.join(&self.options.filename)
    }

    fn rotate(&mut self) -> io::Result<()> {
        self.file.flush()?;
        let idx = rotated(&self.options.path, &self.options.filename)?
            .last()
            .map_or(1, |(i, _)| i + 1);
        let mut name = format!("{}_{idx}", self.options.filename);
        if self.options.suffix_with_timestamp {
            name.push_str(&chrono::Local::now().format("_%Y%m%d_%H%M%S").to_string());
        }
        match std::fs::rename(self.active(), self.options.path.join(name)) {
            Ok(()) => {}
            // Moved or deleted from outside: nothing to rename.
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(e),
        }
        self.reopen()
    }

    /// Deletes rotated files beyond `max_file_num`, lowest index first.
    fn clean(&self) -> io::Result<()> {
        let keep = self.options.max_file_num as usize;
        if keep == 0 {
            return Ok(());
        }
        let files = rotated(&self.options.path, &self.options.filename)?;
        let excess = files.len().saturating_sub(keep);
        for (_, path) in &files[..excess] {
            std::fs::remove_file(path)?;
        }
        Ok(())
    }
}

/// The active file opened for appending: the writer, its size, its device and inode. A
/// FIFO, a device, a socket or a directory at the path is refused before it is opened:
/// opening a FIFO for writing waits for a reader, which held start-up until a second
/// Ctrl-C.
fn open_active(path: &Path) -> io::Result<(BufWriter<File>, u64, (u64, u64))> {
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "it is not a regular file (a FIFO, a device, a socket or a directory); rotate_file writes and rotates regular files",
        ));
    }
    let file = OpenOptions::new().create(true).append(true).open(path)?;
    let meta = file.metadata()?;
    let id = (meta.dev(), meta.ino());
    Ok((BufWriter::with_capacity(64 * 1024, file), meta.len(), id))
}

/// The rotated files of `filename` in `dir`, by index: `<filename>_<idx>` with an optional
/// `_<anything>` after the index.
fn rotated(dir: &Path, filename: &str) -> io::Result<Vec<(u64, PathBuf)>> {
    let prefix = format!("{filename}_");
    let mut out = Vec::new();
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name();
        let Some(rest) = name.to_str().and_then(|n| n.strip_prefix(&prefix)) else {
            continue;
        };
        let digits = rest.split('_').next().unwrap_or_default();
        if let Ok(idx) = digits.parse::<u64>() {
            out.push((idx, entry.path()));
        }
    }
    out.sort();
    Ok(out)
}

impl Sink for RotateFile {
    fn write(&mut self, _: LogLevel, text: &str, _: Option<&Parts>) -> io::Result<()> {
        if self.checked.elapsed() >= RECHECK {
            self.checked = Instant::now();
            if !self.still_there() {
                self.reopen()?;
            }
        }
        if self.size > self.options.max_file_size {
            self.rotate()?;
        }
        self.file.write_all(text.as_bytes())?;
        self.file.write_all(b"\n")?;
        self.size += text.len() as u64 + 1;
        if self.flush_each {
            self.file.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }

    fn sync(&mut self) -> io::Result<()> {
        self.file.flush()?;
        self.file.get_ref().sync_data()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(dir: &Path, max_file_num: u32, suffix: bool) -> RotateFileOptions {
        RotateFileOptions {
            path: dir.join("log"),
            filename: "app.log".into(),
            max_file_size: 100,
            max_file_num,
            sync: None,
            suffix_with_timestamp: suffix,
        }
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir.join("log"))
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_fifo_or_a_directory_at_the_active_path_is_refused_without_waiting() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("log/app.log")).unwrap();
        let err = RotateFile::open(options(dir.path(), 2, false))
            .err()
            .unwrap();
        assert!(err.to_string().contains("not a regular file"), "{err}");
        std::fs::remove_dir(dir.path().join("log/app.log")).unwrap();
        let made = std::process::Command::new("mkfifo")
            .arg(dir.path().join("log/app.log"))
            .status()
            .unwrap();
        assert!(made.success());
        // Opened on a thread of its own: a wait for a reader fails the test, not hangs it.
        let (tx, rx) = std::sync::mpsc::channel();
        let opts = options(dir.path(), 2, false);
        std::thread::spawn(move || {
            let _ = tx.send(RotateFile::open(opts).err().map(|e| e.to_string()));
        });
        let said = rx
            .recv_timeout(Duration::from_secs(10))
            .expect("opening a FIFO with no reader waited");
        assert!(said.unwrap().contains("not a regular file"));
    }

    #[test]
    fn rotates_past_the_size_and_keeps_the_newest() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = RotateFile::open(options(dir.path(), 2, false)).unwrap();
        let line = "x".repeat(59); // 60 bytes a line: the file rotates after every 2nd line
        for _ in 0..9 {
            f.write(LogLevel::Info, &line, None).unwrap();
        }
        f.flush().unwrap();
        // 9 lines: files _1.._4 rotated with 2 lines each, 1 line active; only _3, _4 kept.
        assert_eq!(names(dir.path()), ["app.log", "app.log_3", "app.log_4"]);
        let active = std::fs::read_to_string(dir.path().join("log/app.log")).unwrap();
        assert_eq!(active.lines().count(), 1);
        let last = std::fs::read_to_string(dir.path().join("log/app.log_4")).unwrap();
        assert_eq!(last.lines().count(), 2);
    }

    #[test]
    fn index_continues_after_restart_and_timestamp_suffix() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("log")).unwrap();
        std::fs::write(dir.path().join("log/app.log_7_20240101_000000"), "old\n").unwrap();
        std::fs::write(dir.path().join("log/app.log"), "x".repeat(150)).unwrap();
        std::fs::write(dir.path().join("log/other.log_99"), "").unwrap();
        let mut f = RotateFile::open(options(dir.path(), 0, true)).unwrap();
        f.write(LogLevel::Info, "new", None).unwrap();
        f.flush().unwrap();
        let names = names(dir.path());
        assert_eq!(names.len(), 4, "{names:?}");
        let eighth = names.iter().find(|n| n.starts_with("app.log_8_")).unwrap();
        // app.log_8_YYYYMMDD_hhmmss
        assert_eq!(eighth.len(), "app.log_8_".len() + 15, "{eighth}");
        assert_eq!(&eighth[18..19], "_");
        assert_eq!(
            std::fs::read_to_string(dir.path().join("log/app.log")).unwrap(),
            "new\n"
        );
    }

    #[test]
    fn a_file_or_folder_removed_from_outside_is_opened_again() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = RotateFile::open(options(dir.path(), 0, false)).unwrap();
        f.write(LogLevel::Info, "one", None).unwrap();
        f.flush().unwrap();
        // logrotate moves the file away: the next check follows the path.
        std::fs::rename(dir.path().join("log/app.log"), dir.path().join("moved")).unwrap();
        f.checked -= RECHECK;
        f.write(LogLevel::Info, "two", None).unwrap();
        f.flush().unwrap();
        assert_eq!(
            std::fs::read_to_string(dir.path().join("moved")).unwrap(),
            "one\n"
        );
        assert_eq!(
            std::fs::read_to_string(dir.path().join("log/app.log")).unwrap(),
            "two\n"
        );
        // The whole folder deleted: it is made again.
        std::fs::remove_dir_all(dir.path().join("log")).unwrap();
        f.checked -= RECHECK;
        f.write(LogLevel::Info, "three", None).unwrap();
        f.flush().unwrap();
        assert_eq!(
            std::fs::read_to_string(dir.path().join("log/app.log")).unwrap(),
            "three\n"
        );
        // Deleted again, and found at a rotation before the next check.
        std::fs::remove_dir_all(dir.path().join("log")).unwrap();
        f.checked = Instant::now();
        for _ in 0..2 {
            f.write(LogLevel::Info, &"z".repeat(120), None).unwrap();
        }
        f.flush().unwrap();
        assert_eq!(names(dir.path()), ["app.log"]);
    }

    #[test]
    fn unlimited_keeps_everything() {
        let dir = tempfile::tempdir().unwrap();
        let mut f = RotateFile::open(options(dir.path(), 0, false)).unwrap();
        for _ in 0..10 {
            f.write(LogLevel::Info, &"y".repeat(120), None).unwrap();
        }
        f.sync().unwrap();
        assert_eq!(names(dir.path()).len(), 10);
    }
}
